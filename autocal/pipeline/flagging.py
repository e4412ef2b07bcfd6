"""The flagging stage of a calibration: band edges and RFI found before the fit.

:func:`scan_flags` reads the observation twice, block by block (the time-mean spectra,
then the outliers given them), and returns the
:class:`~autocal.pipeline.rfi.RfiMask` that every pass then ORs into each block's flags
(:meth:`autocal.pipeline.partials._FileSums.add`), so flagged samples never enter the normal
sums. :func:`mark_flag_reasons` tells, in the solution's ``flag_reason``, the channels that had
no sample left because of band edges or RFI. On by default; ``rfi_flagging=False``
(``autocal calibrate --no-rfi-flagging``) turns it off. EDGES spectra (``Q`` ratios, their
own format's weights) are not flagged here.

:func:`flag_observation` is the same stage for an observation held in memory (``autocal
diagnose``, which reads its UVH5 files whole): the same two scans (:func:`scan_blocks`) over
blocks of its integrations, the mask ORed into its flags. Both give the same flags for the
same data whatever the blocks.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.fit.solve import FLAG_BAND_EDGE, FLAG_RFI, FLAG_TOO_FEW
from autocal.io.uvh5_blocks import BLOCK_SAMPLES
from autocal.io.uvh5_chunks import ReadStats
from autocal.pipeline.config import CalibrationConfig, read_selection
from autocal.pipeline.partials import read_chunks
from autocal.pipeline.rfi import LevelScan, RfiMask, RfiScan, band_sky
from autocal.pipeline.sources import Source

logger = logging.getLogger(__name__)

#: The summary's ``rfi_flagging`` block when the flagging is turned off.
TURNED_OFF: dict[str, Any] = {"applied": False, "why": "turned off (rfi_flagging=false)"}

#: Blocks of an observation's data and flags: ``(offset, data, flags)``, each block
#: ``(Nant, Npol, Ntime_block, Nfreq)`` starting at integration ``offset``, in time order.
Blocks = Iterable[tuple[int, np.ndarray, np.ndarray]]


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
        and the read counters of the flagging's two reads (``io``, as the fit's
        ``execution.io``), or why nothing was flagged.
    """
    if not config.rfi_flagging:
        return None, dict(TURNED_OFF)
    if source.kind == "edges":
        return None, {"applied": False, "why": "EDGES spectra are not flagged from the autos"}
    report(0.07, "flagging band edges and RFI from the autos")
    selection = read_selection(config)
    tasks = source.tasks(tsky_all)
    stats = ReadStats()  # the flagging's own reads, reported beside the fit's

    def blocks() -> Blocks:
        for task in tasks:
            offset = task.offset
            for chunk in read_chunks(selection, block_size, task, stats):
                yield offset, chunk.data, chunk.flags
                offset += chunk.ntime
                del chunk

    sky = band_sky(tsky_all, len(source.pols if config.pols is None else config.pols))
    mask = scan_blocks(blocks, int(source.lsts.size), sky)
    mask.counts["io"] = stats.as_dict()
    return mask, mask.counts


def scan_blocks(blocks: Callable[[], Blocks], ntime: int, sky: np.ndarray | None = None) -> RfiMask:
    """Scan an observation's blocks twice and return its band-edge and RFI mask.

    Parameters
    ----------
    blocks
        Called once per scan, returns the observation's blocks ``(offset, data, flags)``
        in time order (each block is used up before the next is asked for).
    ntime
        Integrations of the observation.
    sky
        ``(Npol, Ntime)`` the model sky's band level
        (:func:`~autocal.pipeline.rfi.band_sky`): the flags in time follow it.

    Returns
    -------
    RfiMask
        The mask, its ``counts`` the summary's ``rfi_flagging`` block.
    """
    levels = LevelScan()
    for _, data, flags in blocks():  # first read: the time-mean spectra
        levels.add(data, flags)
    scan = RfiScan(ntime, levels.level(), sky)
    for offset, data, flags in blocks():  # second read: the outliers, given the mean spectra
        scan.add(data, flags, offset)
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
    return mask


def flag_observation(
    obs: Observation, block_size: int | None = None, tsky: np.ndarray | None = None
) -> tuple[Observation, dict[str, Any]]:
    """Flag band edges and RFI in an observation held in memory, as a calibration does.

    The observation is scanned in blocks of integrations (:func:`scan_blocks`: the same
    :class:`~autocal.pipeline.rfi.RfiScan` as :func:`scan_flags`) and the mask is ORed into
    its flags block by block (:meth:`~autocal.pipeline.rfi.RfiMask.apply`: band edges, RFI
    channels, RFI integrations and each spectrum's frequency hits). For UVH5 and Miriad
    autos; EDGES spectra are not flagged from the autos (:func:`scan_flags`).

    Parameters
    ----------
    obs
        The observation (not modified).
    block_size
        Integrations per block (default: about
        :data:`~autocal.io.uvh5_blocks.BLOCK_SAMPLES` samples; the flags do not depend
        on it).
    tsky
        ``(Npol, Ntime, Nfreq)`` the model Tsky, whose band level the flags in time follow
        (:func:`~autocal.pipeline.rfi.band_sky`), or ``None``.

    Returns
    -------
    tuple
        A shallow copy of ``obs`` with the new flags (its data are ``obs``'s), and the
        summary's ``rfi_flagging`` block (counts per reason, as :func:`scan_flags`).
    """
    nant, npol, ntime, nfreq = obs.shape
    if block_size is None:
        block_size = max(1, BLOCK_SAMPLES // max(1, nant * npol * nfreq))
    step = max(1, int(block_size))

    def blocks() -> Blocks:
        for t in range(0, ntime, step):
            window = slice(t, min(t + step, ntime))
            yield t, obs.data[:, :, window], obs.flags[:, :, window]

    sky = None if tsky is None else band_sky(tsky, npol)
    mask = scan_blocks(blocks, ntime, sky)
    flags = np.empty_like(obs.flags)
    for offset, data, old in blocks():  # the scan's hits of these very blocks are reused
        flags[:, :, offset : offset + data.shape[2]] = mask.apply(data, old, offset)
    flagged = copy.copy(obs)  # the data are shared; already-validated flags need no check
    object.__setattr__(flagged, "flags", flags)
    return flagged, mask.counts


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
