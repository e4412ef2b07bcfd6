"""What ``autocal calibrate`` checks after a run: flagged channels and stale products.

A solution whose channels are all or mostly flagged is not a calibration: the command says
how many channels were flagged and why, records it under ``quality`` in ``summary.json`` and
exits with :data:`EXIT_FLAGGED`. The output folder is autocal's: after a successful run every
product autocal writes there that this run did not write (an old comparison, an old plot) is
removed, so nothing stale sits beside the new solution.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from autocal.compare.report import OUTPUT_NAMES
from autocal.core.files import atomic_path
from autocal.fit.solution import Solution
from autocal.fit.solve import FLAG_REASONS
from autocal.pipeline.products import FIGURE_FILES, PRODUCT_FILES, SUMMARY_NAME

#: Exit status of a run whose solution is fully or mostly flagged (products are written).
EXIT_FLAGGED = 3
#: Fraction of flagged channels above which a solution counts as mostly flagged.
MOSTLY_FLAGGED = 0.5
#: Every file name ``autocal calibrate`` writes into ``--out``.
OWNED_NAMES = frozenset(
    {*PRODUCT_FILES.values(), *FIGURE_FILES.values(), SUMMARY_NAME, *OUTPUT_NAMES.values()}
)


def flag_quality(solution: Solution) -> dict[str, Any]:
    """Return how much of a solution is flagged, and why.

    Parameters
    ----------
    solution
        The fitted solution.

    Returns
    -------
    dict
        ``status`` (``ok``, ``mostly_flagged`` or ``fully_flagged``), ``flagged`` and
        ``total`` (antenna-pol-channels), ``flagged_fraction``, ``reasons`` (reason ->
        count), ``fully_flagged`` (``"ANT POL"`` labels of antenna-pols without one
        solved channel) and ``message`` (one line saying all that).
    """
    reason = np.asarray(solution.flag_reason)
    total = int(reason.size)
    flagged = int(np.count_nonzero(reason))
    codes, counts = np.unique(reason[reason != 0], return_counts=True)
    reasons = {
        FLAG_REASONS.get(int(c), str(int(c))): int(n) for c, n in zip(codes, counts, strict=True)
    }
    dead = [
        f"{ant} {pol}"
        for i, ant in enumerate(solution.antennas)
        for j, pol in enumerate(solution.pols)
        if reason[i, j].size and np.all(reason[i, j] != 0)
    ]
    fraction = flagged / total if total else 1.0
    status = (
        "fully_flagged"
        if flagged == total
        else ("mostly_flagged" if fraction > MOSTLY_FLAGGED else "ok")
    )
    nfreq = reason.shape[-1] if reason.ndim else 0
    why = ", ".join(f"{n} {r}" for r, n in reasons.items()) or "none"
    message = (
        f"{flagged} of {total} channels flagged ({100 * fraction:.0f} %; "
        f"{len(solution.antennas)} antenna(s) x {len(solution.pols)} pol(s) x {nfreq} channels): "
        f"{why}"
    )
    if dead:
        message += f"; no solved channel for {', '.join(dead[:8])}" + (
            f" and {len(dead) - 8} more" if len(dead) > 8 else ""
        )
    return {
        "status": status,
        "flagged": flagged,
        "total": total,
        "flagged_fraction": round(fraction, 6),
        "reasons": reasons,
        "fully_flagged": dead,
        "message": message,
    }


def record_quality(out: Path, quality: dict[str, Any]) -> None:
    """Add ``quality`` to the ``summary.json`` in ``out`` (rewritten atomically)."""
    path = out / SUMMARY_NAME
    summary = json.loads(path.read_text())
    summary["quality"] = quality
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(summary, indent=2))


def remove_stale(out: Path, products: dict[str, str]) -> list[Path]:
    """Remove the files autocal owns in ``out`` that this run did not write.

    Parameters
    ----------
    out
        The output folder.
    products
        Product name -> path of what the run wrote (``summary.json``'s ``products``).

    Returns
    -------
    list of Path
        The files removed.
    """
    kept = {Path(p).name for p in products.values()} | {SUMMARY_NAME}
    removed = []
    for name in sorted(OWNED_NAMES - kept):
        path = out / name
        if path.is_file():
            path.unlink()
            removed.append(path)
    return removed
