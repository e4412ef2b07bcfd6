"""The flagging's two reads file by file: the unit of work, in this process or in readers.

The flagging (:mod:`autocal.pipeline.flagging`) reads the observation twice: the time-mean
spectra (:class:`~autocal.pipeline.rfi.LevelScan`), then the outliers given them
(:class:`~autocal.pipeline.rfi.RfiScan`). Each read is done file by file by
:func:`scan_file` (a file's blocks scanned on their own: per-channel sums over the file's
integrations, and the per-integration results of the file) and the files' scans are added
in file order (``add_scan``), as the fit's partial sums are
(:mod:`autocal.pipeline.partials`). So the mask is the same bit for bit whether the files
were scanned in this process, in reader processes (:mod:`autocal.pipeline.readers`) or on
Dask; an observation held in memory is scanned in the same stretches of integrations (its
files'), :func:`autocal.pipeline.flagging.flag_observation`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from autocal.io.uvh5_chunks import ReadStats
from autocal.pipeline.partials import FileTask, read_chunks
from autocal.pipeline.rfi import LevelScan, RfiScan

#: Blocks of a stretch of integrations: ``(offset, data, flags)``, each block
#: ``(Nant, Npol, Ntime_block, Nfreq)``, ``offset`` counted from the stretch's start.
Blocks = Iterable[tuple[int, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class ScanSpec:
    """What every file's scan of one flagging read needs (shared by all files).

    Attributes
    ----------
    selection
        Antennas, pols, frequency range (Hz) and LST range (hours) to read.
    block_size
        Integrations per read block (``None``: automatic; the flags do not depend on it).
    level
        ``None`` for the first read (the time-mean spectra); for the second, the
        ``(Nant, Npol, Nfreq)`` time-mean spectra the outliers are found against.
    """

    selection: dict[str, Any]
    block_size: int | None = None
    level: np.ndarray | None = None


@dataclass
class FileScan:
    """One file's scan of one read.

    Attributes
    ----------
    index
        The task's index.
    level
        The first read's sums of the file, else ``None``.
    rfi
        The second read's scan of the file (its integrations counted from the file's
        first), else ``None``.
    stats
        :class:`~autocal.io.uvh5_chunks.ReadStats` counters of the file's read.
    """

    index: int
    level: LevelScan | None = None
    rfi: RfiScan | None = None
    stats: dict[str, int] = field(default_factory=dict)


def scan_file(spec: ScanSpec, task: FileTask) -> FileScan:
    """Read one file block by block and scan it (the first or the second read).

    Parameters
    ----------
    spec
        The read's settings (``spec.level`` is ``None`` in the first read).
    task
        The file.

    Returns
    -------
    FileScan
        The file's level sums or its outlier scan, and its read counters.
    """
    stats = ReadStats()
    blocks = _file_blocks(spec, task, stats)
    if spec.level is None:
        return FileScan(task.index, level=level_of(blocks), stats=stats.as_dict())
    scan = rfi_of(blocks, spec.level, int(task.lsts.size))
    return FileScan(task.index, rfi=scan, stats=stats.as_dict())


def _file_blocks(spec: ScanSpec, task: FileTask, stats: ReadStats) -> Iterator[Any]:
    """Yield a file's blocks ``(offset in the file, data, flags)``, each used up in turn."""
    offset = 0
    for chunk in read_chunks(spec.selection, spec.block_size, task, stats, scan=True):
        yield offset, chunk.data, chunk.flags
        offset += chunk.ntime
        del chunk


def level_of(blocks: Blocks) -> LevelScan:
    """Return the first read's sums of one stretch of integrations (a file)."""
    levels = LevelScan()
    for _, data, flags in blocks:
        levels.add(data, flags)
    return levels


def rfi_of(blocks: Blocks, level: np.ndarray, ntime: int) -> RfiScan:
    """Return the second read's scan of one stretch of ``ntime`` integrations (a file)."""
    scan = RfiScan(ntime, level)
    for offset, data, flags in blocks:
        scan.add(data, flags, offset)
    return scan
