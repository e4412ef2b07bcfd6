"""How much of a solution is flagged, and why: the ``quality`` block of every run's summary.

A solution whose channels are all or mostly flagged is not a calibration. Every caller of
:func:`autocal.pipeline.calibrate.calibrate` (the CLI, service jobs, nightly runs, a
notebook) finds the counts and reasons under ``quality`` in ``summary.json``; ``autocal
calibrate`` exits with status 3 on such a result, and a service job's message says so
(:func:`flagged_verdict`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from autocal.fit.solution import Solution
from autocal.fit.solve import FLAG_REASONS

#: Fraction of flagged channels above which a solution counts as mostly flagged.
MOSTLY_FLAGGED = 0.5
#: Words of the ``status`` of a solution that is not a calibration.
FLAGGED_WORDS = {"mostly_flagged": "mostly flagged", "fully_flagged": "fully flagged"}


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


def flagged_verdict(quality: Mapping[str, Any] | None) -> str | None:
    """Say in a few words that a solution is fully or mostly flagged (``None`` if not).

    Parameters
    ----------
    quality
        A summary's ``quality`` block (:func:`flag_quality`); ``None`` (a summary without
        one) is not judged.

    Returns
    -------
    str or None
        ``"<flagged> of <total> channels flagged (mostly flagged)"`` (or ``fully
        flagged``) when ``status`` is ``mostly_flagged`` or ``fully_flagged``; ``None`` for
        ``ok`` or no block.
    """
    if not quality or quality.get("status") not in FLAGGED_WORDS:
        return None
    words = FLAGGED_WORDS[quality["status"]]
    return f"{quality['flagged']} of {quality['total']} channels flagged ({words})"
