"""The flagging stage of a calibration: band edges and RFI found before the fit.

:func:`scan_flags` reads the observation twice, block by block (the time-mean spectra,
then the outliers given them), and returns the
:class:`~autocal.pipeline.rfi.RfiMask` that every pass then ORs into each block's flags
(:meth:`autocal.pipeline.partials._FileSums.add`), so flagged samples never enter the normal
sums. :func:`mark_flag_reasons` tells, in the solution's ``flag_reason``, the channels that had
no sample left because of band edges or RFI. On by default; ``rfi_flagging=False``
(``autocal calibrate --no-rfi-flagging``) turns it off. EDGES spectra (``Q`` ratios, their
own format's weights) are not flagged here.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from autocal.fit.solve import FLAG_BAND_EDGE, FLAG_RFI, FLAG_TOO_FEW
from autocal.pipeline.config import CalibrationConfig, read_selection
from autocal.pipeline.partials import read_chunks
from autocal.pipeline.rfi import LevelScan, RfiMask, RfiScan
from autocal.pipeline.sources import Source

logger = logging.getLogger(__name__)


def scan_flags(
    config: CalibrationConfig,
    source: Source,
    tsky_all: np.ndarray,
    block_size: int | None,
    report: Callable[[float, str], None],
) -> tuple[RfiMask | None, dict[str, Any]]:
    """Read the observation (twice) and decide its band-edge and RFI flags.

    Parameters
    ----------
    config
        The calibration settings (``rfi_flagging``, the selection).
    source
        The scanned inputs.
    tsky_all
        ``(Npol, Ntime, Nfreq)`` the model Tsky (only to build the file tasks).
    block_size
        Integrations per read block (the flags do not depend on it).
    report
        The run's progress report.

    Returns
    -------
    tuple
        The mask (``None`` when flagging is off or does not apply) and the summary's
        ``rfi`` block: counts per reason (``band_edge``, ``rfi_frequency``, ``rfi_time``)
        or why nothing was flagged.
    """
    if not config.rfi_flagging:
        return None, {"applied": False, "why": "turned off (rfi_flagging=false)"}
    if source.kind == "edges":
        return None, {"applied": False, "why": "EDGES spectra are not flagged from the autos"}
    report(0.07, "flagging band edges and RFI from the autos")
    selection = read_selection(config)
    tasks = source.tasks(tsky_all)
    levels = LevelScan()
    for task in tasks:  # first read: the time-mean spectra
        for chunk in read_chunks(selection, block_size, task):
            levels.add(chunk.data, chunk.flags)
            del chunk
    scan = RfiScan(int(source.lsts.size), levels.level())
    for task in tasks:  # second read: the outliers, given the mean spectra
        offset = task.offset
        for chunk in read_chunks(selection, block_size, task):
            scan.add(chunk.data, chunk.flags, offset)
            offset += chunk.ntime
            del chunk
    mask = scan.finish()
    counts = mask.counts
    logger.info(
        "flagged before the fit: %d band-edge channel(s), %d RFI channel(s), "
        "%d RFI integration(s); samples %s",
        counts["band_edge_channels"],
        counts["rfi_channels"],
        counts["rfi_integrations"],
        counts["samples"],
    )
    return mask, counts


def mark_flag_reasons(solved: dict[str, np.ndarray], mask: RfiMask | None) -> None:
    """Say in ``solved["flag_reason"]`` which empty channels the flagging emptied.

    A channel the fit flagged for too few samples is marked ``band edge``
    (:data:`~autocal.fit.solve.FLAG_BAND_EDGE`) or ``RFI`` (:data:`~autocal.fit.solve.FLAG_RFI`)
    when the mask flagged it whole. In place.
    """
    if mask is None:
        return
    reason = solved["flag_reason"]
    too_few = reason == FLAG_TOO_FEW
    reason[too_few & mask.band_edge] = FLAG_BAND_EDGE
    reason[too_few & mask.channels & ~mask.band_edge] = FLAG_RFI
    whole_time = mask.integrations.all(axis=2)[..., None]
    reason[too_few & whole_time & ~mask.band_edge & ~mask.channels] = FLAG_RFI
