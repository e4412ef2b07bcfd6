"""What ``autocal calibrate`` does after a run: the exit status of a flagged result, stale products.

A solution whose channels are all or mostly flagged is not a calibration: the pipeline
records how many channels were flagged and why under ``quality`` in ``summary.json``
(:func:`autocal.pipeline.quality.flag_quality`), and the command says so and exits with
:data:`EXIT_FLAGGED`. The output folder is autocal's: after a successful run every product
autocal writes there that this run did not write (an old comparison, an old plot) is
removed, so nothing stale sits beside the new solution.
"""

from __future__ import annotations

from pathlib import Path

from autocal.compare.names import OUTPUT_NAMES
from autocal.pipeline.products import FIGURE_FILES, PRODUCT_FILES, SUMMARY_NAME

#: Exit status of a run whose solution is fully or mostly flagged (products are written).
EXIT_FLAGGED = 3
#: Every file name ``autocal calibrate`` writes into ``--out``.
OWNED_NAMES = frozenset(
    {*PRODUCT_FILES.values(), *FIGURE_FILES.values(), SUMMARY_NAME, *OUTPUT_NAMES.values()}
)


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
