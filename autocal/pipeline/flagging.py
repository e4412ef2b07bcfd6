"""The flagging stage of a calibration: band edges and RFI found before the fit.

:func:`scan_flags` reads the observation twice, block by block (the time-mean spectra,
then the outliers given them; a small observation is decoded once, the later reads replaying
its blocks, :mod:`autocal.pipeline.decoded`), and returns the
:class:`~autocal.pipeline.rfi.RfiMask` that every pass then ORs into each block's flags
(:meth:`autocal.pipeline.partials._FileSums.add`), so flagged samples never enter the normal
sums. :func:`mark_flag_reasons` tells, in the solution's ``flag_reason``, the channels that had
no sample left because of band edges or RFI. On by default; ``rfi_flagging=False``
(``autocal calibrate --no-rfi-flagging``) turns it off. EDGES spectra (``Q`` ratios, their
own format's weights) are not flagged here.

:func:`flag_observation` is the same stage for an observation held in memory (``autocal
diagnose``, which reads its UVH5 files whole): the same two scans (:func:`scan_blocks`) over
blocks of its integrations, the mask ORed into its flags. Both give the same flags for the
same data whatever the blocks and whichever process read the files: each file is scanned on
its own and the files' scans are added in file order (:mod:`autocal.pipeline.flag_partials`),
in this process, in reader processes (:mod:`autocal.pipeline.readers`) or on Dask.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Iterable, Iterator, Sequence
from itertools import groupby
from operator import itemgetter
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.fit.solve import FLAG_BAND_EDGE, FLAG_NO_DATA, FLAG_RFI, FLAG_TOO_FEW
from autocal.io.uvh5_blocks import BLOCK_SAMPLES
from autocal.pipeline.config import CalibrationConfig, read_selection
from autocal.pipeline.flag_partials import FileScan, ScanSpec, level_of, rfi_of, scan_file
from autocal.pipeline.partials import add_stats
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
    executor: Any = None,
) -> tuple[RfiMask | None, dict[str, Any]]:
    """Read the observation (twice) and decide its band-edge and RFI flags.

    Each read is done file by file (:func:`autocal.pipeline.flag_partials.scan_file`) and
    the files' scans added in file order, so the mask is the same whichever executor read
    the files.

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
    executor
        Reads the files (``map_ordered``: reader processes,
        :class:`~autocal.pipeline.readers.ProcessReaders`, or Dask); ``None``: in this
        process.

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
    stats: dict[str, int] = {}  # the flagging's own reads, reported beside the fit's
    ntask = len(tasks)

    def scans(spec: ScanSpec, lo: float, what: str) -> Iterator[FileScan]:
        parts = (
            (scan_file(spec, task) for task in tasks)
            if executor is None or source.kind != "uvh5"
            else executor.map_ordered(scan_file, spec, tasks)
        )
        for i, part in enumerate(parts):
            add_stats(stats, part.stats)
            report(lo + 0.015 * (i + 1) / ntask, f"flagging: {what}, file {i + 1}/{ntask}")
            yield part

    levels = LevelScan()  # first read: the time-mean spectra
    for part in scans(ScanSpec(selection, block_size), 0.07, "time-mean spectra"):
        assert part.level is not None
        levels.add_scan(part.level)
    sky = band_sky(tsky_all, len(source.pols if config.pols is None else config.pols))
    scan = RfiScan(int(source.lsts.size), levels.level(), sky)
    spec = ScanSpec(selection, block_size, scan.level)  # second read: the outliers
    for task, part in zip(tasks, scans(spec, 0.085, "outliers"), strict=True):
        assert part.rfi is not None
        scan.add_scan(part.rfi, task.offset)
    mask = _finish(scan)
    mask.counts["io"] = stats
    return mask, mask.counts


def scan_blocks(
    blocks: Callable[[], Blocks],
    ntime: int,
    sky: np.ndarray | None = None,
    starts: Sequence[int] = (0,),
) -> RfiMask:
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
    starts
        The first integration of each of the observation's files: each file is scanned
        on its own and the scans added in order, as :func:`scan_flags` does (so the mask
        is the one a calibration of the files finds). Blocks are split where a file starts.

    Returns
    -------
    RfiMask
        The mask, its ``counts`` the summary's ``rfi_flagging`` block.
    """
    bounds = [*sorted({0, *(int(s) for s in starts if 0 < int(s) < ntime)}), int(ntime)]
    levels = LevelScan()
    for _, group in groupby(_in_files(blocks(), bounds), key=itemgetter(0)):
        levels.add_scan(level_of(block for _, block in group))  # first read: the mean spectra
    scan = RfiScan(ntime, levels.level(), sky)
    for k, group in groupby(_in_files(blocks(), bounds), key=itemgetter(0)):
        part = rfi_of((block for _, block in group), scan.level, bounds[k + 1] - bounds[k])
        scan.add_scan(part, bounds[k])  # second read: the outliers, given the mean spectra
    return _finish(scan)


def _in_files(
    blocks: Blocks, bounds: list[int]
) -> Iterator[tuple[int, tuple[int, np.ndarray, np.ndarray]]]:
    """Yield ``(file, (offset in the file, data, flags))``, blocks split where a file starts."""
    k = 0
    for offset, data, flags in blocks:
        t, stop = offset, offset + data.shape[2]
        while t < stop:
            while t >= bounds[k + 1]:
                k += 1
            end = min(stop, bounds[k + 1])
            window = slice(t - offset, end - offset)
            whole = window == slice(0, data.shape[2])
            yield (
                k,
                (
                    t - bounds[k],
                    data if whole else data[:, :, window],
                    flags if whole else flags[:, :, window],
                ),
            )
            t = end


def _finish(scan: RfiScan) -> RfiMask:
    """Return the scan's mask and log its counts."""
    mask = scan.finish()
    counts = mask.counts
    logger.info(
        "flagged before the fit: %d band-edge channel(s), %d without usable data, "
        "%d RFI channel(s), %d RFI integration(s); samples %s",
        counts["band_edge_channels"],
        counts["no_data_channels"],
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
    mask = scan_blocks(blocks, ntime, sky, file_starts(obs))
    flags = np.empty_like(obs.flags)
    for offset, data, old in blocks():  # the scan's hits of these very blocks are reused
        flags[:, :, offset : offset + data.shape[2]] = mask.apply(data, old, offset)
    flagged = copy.copy(obs)  # the data are shared; already-validated flags need no check
    object.__setattr__(flagged, "flags", flags)
    return flagged, mask.counts


def file_starts(obs: Observation) -> list[int]:
    """Return the first integration of each file an observation was read from.

    ``obs.meta["file_starts"]`` (:func:`autocal.diagnosis.reading.read_observation`) when it
    fits the observation's integrations, else ``[0]`` (one stretch).
    """
    starts = obs.meta.get("file_starts")
    if not starts:
        return [0]
    values = [int(s) for s in starts]
    if values[0] != 0 or values != sorted(set(values)) or values[-1] >= obs.ntime:
        logger.debug("file starts %s do not fit %d integrations: one stretch", values, obs.ntime)
        return [0]
    return values


def mark_flag_reasons(solved: dict[str, np.ndarray], mask: RfiMask | None) -> None:
    """Say in ``solved["flag_reason"]`` which empty channels the flagging emptied.

    A channel the fit flagged for too few samples is marked ``no usable data``
    (:data:`~autocal.fit.solve.FLAG_NO_DATA`) when it had no usable sample at all (its
    time-mean spectrum is not positive and finite: every sample flagged by the file, NaN,
    inf, zero or negative), else ``band edge`` (:data:`~autocal.fit.solve.FLAG_BAND_EDGE`)
    or ``RFI`` (:data:`~autocal.fit.solve.FLAG_RFI`) when the mask flagged it whole. In
    place.
    """
    if mask is None:
        return
    reason = solved["flag_reason"]
    too_few = reason == FLAG_TOO_FEW
    with np.errstate(invalid="ignore"):
        no_data = ~(np.isfinite(mask.level) & (mask.level > 0))
    reason[too_few & no_data] = FLAG_NO_DATA
    too_few &= ~no_data
    reason[too_few & mask.band_edge] = FLAG_BAND_EDGE
    reason[too_few & mask.channels & ~mask.band_edge] = FLAG_RFI
    whole_time = mask.integrations.all(axis=2)[..., None]
    reason[too_few & whole_time & ~mask.band_edge & ~mask.channels] = FLAG_RFI
