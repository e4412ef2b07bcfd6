"""Partial normal sums of one file: the unit of work, serial or on a Dask worker.

:func:`compute_partial` reads one file block by block
(:func:`autocal.io.uvh5_blocks.iter_uvh5_blocks`), turns each block into normal-equation sums
(:func:`autocal.fit.sums.accumulate`) added in order into the file's sums, and drops it, so
memory is bounded by the block. It also keeps, per waterfall row, the weighted sums of the
shown antennas that give the residual waterfall once solved. :func:`fold` adds the files'
partials in file order: the serial run and the Dask run (:mod:`autocal.pipeline.scaleout`)
give the same sums bit for bit.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.fit.blocks import base_sums, extended_model
from autocal.fit.model import FitModel, design, weights_for
from autocal.fit.sums import NormalSums, accumulate
from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_chunks import ReadStats
from autocal.pipeline.config import PipelineError
from autocal.pipeline.decoded import ScanChunk, cached_blocks
from autocal.pipeline.rfi import RfiMask

#: Whether the block reader runs ahead of its caller in background threads
#: (:func:`autocal.io.uvh5_blocks.iter_uvh5_blocks`'s ``prefetch``) in this process; reader
#: processes set it when they start (:mod:`autocal.pipeline.readers`).
READ_AHEAD = True


@dataclass(frozen=True)
class PartialSpec:
    """What every file's partial sums of one pass need (shared by all tasks of a pass).

    Attributes
    ----------
    model
        The fit model (its LST span covers the whole observation).
    weights
        ``"radiometer"`` or ``"identity"``.
    selection
        Antennas, pols, frequency range (Hz) and LST range (hours) to read.
    nshow
        Antennas (the first of the selection) whose residual waterfall is kept.
    bin_size
        Integrations per waterfall row.
    block_size
        Integrations per read block (``None``: automatic, see
        :data:`autocal.io.uvh5.BLOCK_SAMPLES`).
    coeffs
        ``(Nant, Npol, Nfreq, nparam)`` the previous pass's solution: radiometer
        weights then use its model instead of the data (``None`` in the first pass).
    edges
        Integration indices (of the whole observation) that split it into the time
        blocks of the total uncertainty (:func:`autocal.fit.blocks.block_edges`): the
        partial then holds one set of sums of the extended model
        (:func:`autocal.fit.blocks.extended_model`) per block it overlaps. ``None``:
        one set of sums of ``model``.
    rfi
        Band-edge and RFI flags ORed into every block before its sums
        (:mod:`autocal.pipeline.flagging`); ``None``: the data's own flags only.
    """

    model: FitModel
    weights: str
    selection: dict[str, Any]
    nshow: int
    bin_size: int
    block_size: int | None = None
    coeffs: np.ndarray | None = None
    edges: tuple[int, ...] | None = None
    rfi: RfiMask | None = None


@dataclass(frozen=True)
class FileTask:
    """One file of the observation (or the whole in-memory observation).

    Attributes
    ----------
    index
        Position of the file in time order.
    file
        The scanned UVH5 file (``None`` for an in-memory observation).
    offset
        Index of the file's first selected integration in the observation.
    lsts
        The file's selected LSTs (hours), as scanned.
    tsky
        ``(Npol, Ntime_file, Nfreq)`` model Tsky of the file's integrations.
    observation
        In-memory data (Miriad, EDGES) instead of a file.
    weights
        Inverse variances of in-memory data whose format defines them (EDGES).
    """

    index: int
    file: Any
    offset: int
    lsts: np.ndarray
    tsky: np.ndarray
    observation: Observation | None = None
    weights: np.ndarray | None = None


@dataclass
class FilePartial:
    """A file's normal sums and the by-products of reading it once.

    Attributes
    ----------
    index
        The task's index.
    sums
        The file's normal sums (its read blocks added in order); ``None`` with time blocks.
    blocks
        With ``PartialSpec.edges``: ``{block: sums of the fitted model}`` for the time
        blocks the file overlaps; else ``None``.
    extended
        With ``PartialSpec.edges``: the file's sums of the extended model
        (:func:`autocal.fit.blocks.extended_model`); else ``None``.
    waterfall
        ``(Nshow, Npol, Nbins_file, Nfreq, nparam + 2)`` per waterfall row: the sums
        over its integrations of ``w R``, ``w`` and ``w a_m`` (``a`` the design columns).
    bin0
        Waterfall row of ``waterfall[:, :, 0]``.
    ntime
        Integrations read.
    antennas, antenna_names
        The selected antennas.
    checksums
        ``{path: sha256}`` of the inputs read.
    bt_min
        Smallest positive ``dnu dt N`` of the usable samples (``inf`` when none).
    stats
        :class:`autocal.io.uvh5_blocks.ReadStats` counters.
    seconds
        Wall time spent on the file.
    """

    index: int
    sums: NormalSums | None
    waterfall: np.ndarray
    bin0: int
    ntime: int
    antennas: np.ndarray
    antenna_names: tuple[str, ...]
    checksums: dict[str, str]
    bt_min: float
    stats: dict[str, int]
    seconds: float
    blocks: dict[int, NormalSums] | None = None
    extended: NormalSums | None = None


def compute_partial(
    spec: PartialSpec, task: FileTask, tick: Callable[[int], None] | None = None
) -> FilePartial:
    """Read one file block by block and return its partial normal sums.

    This is the unit of work of the serial run and of a Dask worker: both add the
    blocks of a file in order, so the partial is the same wherever it is computed.

    Parameters
    ----------
    spec
        The pass's settings.
    task
        The file.
    tick
        Called with the number of integrations after each block (progress).

    Returns
    -------
    FilePartial
        The file's sums, waterfall sums, checksums and read counters.

    Raises
    ------
    PipelineError
        If the file's LSTs changed since the scan, it yields a different number of
        integrations, or radiometer weights lack channel widths / times / nsamples.
    """
    started = time.perf_counter()
    stats = ReadStats()
    running = _FileSums.start(spec, task)
    for chunk in read_chunks(spec.selection, spec.block_size, task, stats):
        nt = chunk.ntime
        running.add(chunk)
        del chunk
        if tick is not None:
            tick(nt)
    return running.finish(stats, time.perf_counter() - started)


def read_chunks(
    selection: dict[str, Any],
    block_size: int | None,
    task: FileTask,
    stats: ReadStats | None = None,
    scan: bool = False,
) -> Iterator[Observation | ScanChunk]:
    """Return a task's data: its file block by block, or its in-memory observation at once.

    Inside :func:`autocal.pipeline.decoded.keep_decoded`, a file read before with the same
    selection and block size is replayed from memory (with ``scan``, as
    :class:`~autocal.pipeline.decoded.ScanChunk`: power and flags only, what the flagging's
    scans read; every block has ``data``, ``flags`` and ``ntime``).

    Parameters
    ----------
    selection
        Antennas, pols, frequency range (Hz) and LST range (hours) to read.
    block_size
        Integrations per read block (``None``: automatic).
    task
        The file.
    stats
        Read counters to add to.
    scan
        Replay kept blocks as :class:`~autocal.pipeline.decoded.ScanChunk` (the flagging's
        scans), not as :class:`~autocal.core.observation.Observation`.

    Returns
    -------
    Iterator
        The blocks, each used up before the next is asked for (the reader's buffers and a
        replay's float64 buffers are reused).
    """
    if task.observation is not None:
        obs = task.observation
        if selection.get("antennas") is not None:
            obs = obs.select(antennas=selection["antennas"])
        return iter([obs])
    stats = stats if stats is not None else ReadStats()

    def read() -> Iterator[Observation]:
        return iter_uvh5_blocks(  # each block is used up before the next is asked for
            task.file,
            **selection,
            block_size=block_size,
            stats=stats,
            reuse_buffers=True,
            prefetch=READ_AHEAD,
        )

    key = (str(getattr(task.file, "path", task.file)), _canonical(selection), block_size)
    return cached_blocks(key, read, stats, scan)


def _canonical(selection: dict[str, Any]) -> str:
    """Return the selection as text that two equal selections share (arrays in full)."""
    items = ((k, None if v is None else np.asarray(v).tolist()) for k, v in selection.items())
    return repr(sorted(items))


@dataclass
class _FileSums:
    """The running sums of one file while its blocks are read (:func:`compute_partial`).

    Attributes
    ----------
    spec, task
        The pass's settings and the file.
    acc_model
        The model whose sums are accumulated: ``spec.model``, or its extended model with
        time blocks.
    bin0, nbins
        The file's first waterfall row and its number of rows.
    sums
        The file's sums so far (without time blocks).
    blocks
        ``{block: sums of the extended model}`` of the blocks still being read (with time
        blocks).
    fitted, extended
        The blocks read to their end (the file's blocks come in time order): each one's
        fitted-model sums, and the extended model's sums of them all, added in block order
        (:meth:`_retire`).
    offset
        Integrations added so far.
    """

    spec: PartialSpec
    task: FileTask
    acc_model: FitModel
    bin0: int
    nbins: int
    sums: NormalSums | None = None
    blocks: dict[int, NormalSums] = field(default_factory=dict)
    fitted: dict[int, NormalSums] = field(default_factory=dict)
    extended: NormalSums | None = None
    waterfall: np.ndarray | None = None
    checksums: dict[str, str] = field(default_factory=dict)
    antennas: np.ndarray | None = None
    names: tuple[str, ...] = ()
    bt_min: float = np.inf
    offset: int = 0

    @classmethod
    def start(cls, spec: PartialSpec, task: FileTask) -> _FileSums:
        """Return the empty sums of a file."""
        ntot = task.lsts.size
        bin0 = task.offset // spec.bin_size
        nbins = (task.offset + ntot - 1) // spec.bin_size - bin0 + 1
        acc_model = spec.model if spec.edges is None else extended_model(spec.model)
        return cls(spec, task, acc_model, bin0, nbins)

    def add(self, chunk: Observation) -> None:
        """Add one block of the file (the next one in time) into the sums."""
        spec, task = self.spec, self.task
        nt = chunk.ntime
        window = slice(self.offset, self.offset + nt)
        if self.offset + nt > task.lsts.size or not np.allclose(
            chunk.lsts, task.lsts[window], atol=1e-6
        ):
            raise PipelineError(f"{chunk.meta.get('files')}: LSTs changed between scan and read")
        if spec.rfi is not None:  # a copy: an in-memory observation is the caller's
            flags = spec.rfi.apply(chunk.data, chunk.flags, task.offset + self.offset)
            chunk = copy.copy(chunk)
            object.__setattr__(chunk, "flags", flags)
        if self.antennas is None:
            self.antennas, self.names = chunk.antennas, chunk.antenna_names
            nshow = min(spec.nshow, chunk.nant)
            self.waterfall = np.zeros(
                (nshow, chunk.data.shape[1], self.nbins, chunk.nfreq, spec.model.nparam + 2)
            )
        self.checksums.update(chunk.meta.get("sha256", {}))
        tsky = task.tsky[:, window]
        weights, bt = self._weights(chunk, window)
        reference = None
        if spec.coeffs is not None:
            pred = np.einsum("pftm,apfm->aptf", design(spec.model, tsky, chunk.lsts), spec.coeffs)
            reference = np.where(np.isfinite(pred) & (pred > 0), pred, chunk.data)
            del pred
        self._accumulate(chunk, tsky, weights, bt, reference)
        assert self.waterfall is not None
        _add_waterfall(
            self.waterfall,
            spec,
            chunk,
            tsky,
            weights,
            bt,
            reference,
            task.offset + self.offset - self.bin0 * spec.bin_size,
        )
        self.offset += nt

    def _weights(
        self, chunk: Observation, window: slice
    ) -> tuple[str | np.ndarray, np.ndarray | None]:
        """Return the block's weights (a kind or inverse variances) and ``dnu dt N``.

        Checks that radiometer weights have a positive ``dnu dt N`` and keeps its smallest
        value.
        """
        spec, task = self.spec, self.task
        weights: str | np.ndarray = spec.weights
        bt = None
        if spec.weights == "radiometer":  # dnu dt N (Observation.bandwidth_time, one pass)
            bt = bandwidth_time(chunk)
        if task.weights is not None and spec.weights == "radiometer":
            weights, bt = task.weights[:, :, window], None
        if bt is not None:
            # a (Ntime, Nfreq) bt is checked where any antenna-pol is unflagged (the same
            # result as broadcasting it to the block, 30x faster)
            used = ~chunk.flags if bt.ndim == 4 else ~chunk.flags.all(axis=(0, 1))
            if np.any((bt <= 0) & used):
                raise PipelineError(
                    f"{chunk.meta.get('files')}: radiometer weights need positive channel "
                    "width, integration time and nsamples; use weights='identity'"
                )
            self.bt_min = min(self.bt_min, float(np.min(bt, where=used, initial=np.inf)))
        return weights, bt

    def _accumulate(
        self,
        chunk: Observation,
        tsky: np.ndarray,
        weights: str | np.ndarray,
        bt: np.ndarray | None,
        reference: np.ndarray | None,
    ) -> None:
        """Add the block's normal sums into the running sums of its time block(s), in place."""
        spec = self.spec
        nt = chunk.ntime
        start = self.task.offset + self.offset
        for b, sl in _block_slices(spec.edges, start, start + nt):
            if b in self.fitted:  # pragma: no cover - a reader yields blocks in time order
                raise PipelineError(f"file {self.task.index}: time block {b} read again")
            self._retire(before=b)
            # the local name is dropped at once, so a block retired at the next boundary is
            # freed there, before the next block's sums are made (else both, 0.4 GB for a
            # HERA file, were alive at once)
            sums = accumulate(  # added into the running sums of its block, in place
                self.acc_model,
                chunk.data[:, :, sl],
                tsky[:, sl],
                chunk.lsts[sl],
                flags=chunk.flags[:, :, sl],
                weights=_time_part(weights, sl, nt),
                bandwidth_time=_time_part(bt, sl, nt),
                reference=_time_part(reference, sl, nt),
                into=self.sums if spec.edges is None else self.blocks.get(b),
            )
            if spec.edges is None:
                self.sums = sums
            else:
                self.blocks[b] = sums
            del sums

    def _retire(self, before: int | None = None) -> None:
        """Reduce the time blocks read to their end (all, or those before ``before``).

        Each keeps the fitted model's sums (a copy) and its extended sums are added into the
        file's extended total, in block order: the operations, and so the values, of
        reducing them all when the file ends, without holding every block's extended sums
        until then (five blocks of a HERA-size file: 1 GB).
        """
        for b in sorted(self.blocks):
            if before is not None and b >= before:
                break
            part = self.blocks.pop(b)
            self.fitted[b] = base_sums(part, self.spec.model)
            self.extended = part if self.extended is None else _add_into(self.extended, part)

    def finish(self, stats: ReadStats, seconds: float) -> FilePartial:
        """Return the file's partial once all its blocks were added.

        With time blocks, the extended model's sums are added once per file and each
        block keeps the fitted model's sums (copies), as :meth:`_retire` reduces them.
        """
        task = self.task
        self._retire()
        blocks = self.fitted
        if (self.sums is None and not blocks) or self.antennas is None or self.waterfall is None:
            raise PipelineError(f"file {task.index}: the selection left no data")
        extended = self.extended
        if self.offset != task.lsts.size:
            raise PipelineError(
                f"file {task.index} yielded {self.offset} integrations, "
                f"{task.lsts.size} were scanned"
            )
        return FilePartial(
            task.index,
            self.sums,
            self.waterfall,
            self.bin0,
            self.offset,
            self.antennas,
            self.names,
            self.checksums,
            self.bt_min,
            stats.as_dict(),
            seconds,
            blocks or None,
            extended,
        )


def add_stats(total: dict[str, int], stats: dict[str, int]) -> None:
    """Add a file's read counters into a run's (the largest array: the maximum), in place."""
    for key, value in stats.items():
        if key == "largest_array":
            total[key] = max(total.get(key, 0), value)
        else:
            total[key] = total.get(key, 0) + value


def compute_partial_with_hits(
    spec: PartialSpec, item: tuple[FileTask, dict[tuple[int, tuple[int, ...]], np.ndarray]]
) -> FilePartial:
    """:func:`compute_partial` of ``(task, hits)``: the flagging's kept hits of that file.

    For executors in other processes: the pass's shared mask travels without its kept
    hits (:meth:`~autocal.pipeline.rfi.RfiMask.portable`) and each file with its own
    (:meth:`~autocal.pipeline.rfi.RfiMask.hits_between`), so no block is flagged twice.
    """
    task, hits = item
    if hits and spec.rfi is not None:
        spec = replace(spec, rfi=replace(spec.rfi, hits=hits))
    return compute_partial(spec, task)


def _block_slices(edges: tuple[int, ...] | None, start: int, stop: int) -> list[tuple[int, slice]]:
    """Split integrations ``start:stop`` of the observation at the time-block edges.

    Returns ``(block, slice of the chunk)`` pairs; without edges one pair for the whole
    chunk (block 0).
    """
    if edges is None:
        return [(0, slice(0, stop - start))]
    out = []
    for b in range(len(edges) - 1):
        lo, hi = max(start, edges[b]), min(stop, edges[b + 1])
        if hi > lo:
            out.append((b, slice(lo - start, hi - start)))
    return out


def _time_part(value: Any, sl: slice, ntime: int) -> Any:
    """Slice an array with a time axis of length ``ntime`` (the chunk's) to ``sl``.

    Arrays ``(..., Ntime, Nfreq)`` (per sample, per pol or shared by all); anything else
    (strings, scalars, ``(Nfreq,)`` rows, ``None``) is returned as it is.
    """
    if sl == slice(0, ntime) or not isinstance(value, np.ndarray):
        return value
    if value.ndim >= 2 and value.shape[-2] == ntime:  # (..., Ntime, Nfreq)
        return value[..., sl, :]
    return value


def bandwidth_time(chunk: Observation) -> np.ndarray:
    """Return ``dnu dt N``: ``(Ntime, Nfreq)`` when ``nsamples`` is uniform, else per sample.

    The shared form spares a chunk-sized array and a third of the fit kernel's reads (which
    reads it as one ``(Nfreq,)`` row when the integration time is uniform too).
    """
    tf = chunk.integration_time[:, None] * chunk.channel_width
    ns = chunk.nsamples
    if ns.size and (not any(ns.strides) or not np.any(ns != ns.flat[0])):  # one value
        return tf * float(ns.flat[0])
    return ns * tf


def _add_into(total: NormalSums, part: NormalSums) -> NormalSums:
    """Add ``part`` into ``total`` in place (the same values as ``total + part``).

    Saves a new set of arrays per file; ``total`` must be owned by the caller.
    """
    total += part
    return total


def _add_waterfall(
    waterfall: np.ndarray,
    spec: PartialSpec,
    chunk: Observation,
    tsky: np.ndarray,
    weights: str | np.ndarray,
    bt: np.ndarray | None,
    reference: np.ndarray | None,
    row0: int,
) -> None:
    """Add a block's weighted sums of the shown antennas into the waterfall rows.

    ``row0`` is the block's first integration counted from the start of the file's
    first waterfall row.
    """
    ns = waterfall.shape[0]
    data = chunk.data[:ns]
    usable = np.isfinite(data) & ~chunk.flags[:ns]
    if isinstance(weights, np.ndarray):
        w = np.where(usable, np.broadcast_to(weights, chunk.data.shape)[:ns], 0.0)
    else:
        w = weights_for(
            weights,
            data,
            usable,
            None if bt is None else bt[:ns] if bt.ndim == 4 else bt,
            None if reference is None else reference[:ns],
        )
    a = design(spec.model, tsky, chunk.lsts)  # (P, F, T, M)
    terms = np.concatenate(
        [
            (w * np.where(usable, data, 0.0))[..., None],
            w[..., None],
            w[..., None] * np.swapaxes(a, 1, 2)[None],
        ],
        axis=-1,
    )  # (S, P, T, F, M + 2)
    rows = (row0 + np.arange(chunk.ntime)) // spec.bin_size
    starts = np.flatnonzero(np.r_[True, np.diff(rows) != 0])
    waterfall[:, :, rows[starts]] += np.add.reduceat(terms, starts, axis=2)


def fold(
    partials: Iterator[FilePartial],
    ntasks: int,
    waterfall_shape: tuple[int, ...] | None,
    report: Callable[[float, str], None],
    progress_range: tuple[float, float],
) -> tuple[NormalSums | tuple[dict[int, NormalSums], NormalSums], np.ndarray, list[FilePartial]]:
    """Add the files' partials in file order (the same order serially and on Dask).

    Returns the summed normal sums (or, with time blocks, the fitted model's sums of each
    block and the extended model's total), the waterfall sums and the partials' other
    information.
    """
    sums: NormalSums | None = None
    blocks: dict[int, NormalSums] = {}
    waterfall: np.ndarray | None = None
    infos: list[FilePartial] = []
    lo, hi = progress_range
    for i, partial in enumerate(partials):
        if partial.index != i:  # pragma: no cover - executors yield in order
            raise PipelineError(f"partial {partial.index} arrived in place of {i}")
        if partial.blocks is not None:
            for b, part in partial.blocks.items():
                blocks[b] = part if b not in blocks else _add_into(blocks[b], part)
            assert partial.extended is not None
            sums = partial.extended if sums is None else _add_into(sums, partial.extended)
            partial.blocks = partial.extended = None
        else:
            assert partial.sums is not None
            sums = partial.sums if sums is None else _add_into(sums, partial.sums)
        if waterfall is None:
            waterfall = np.zeros(
                (*partial.waterfall.shape[:2], waterfall_shape[0], *partial.waterfall.shape[3:])
                if waterfall_shape is not None
                else partial.waterfall.shape
            )
        nb = partial.waterfall.shape[2]
        waterfall[:, :, partial.bin0 : partial.bin0 + nb] += partial.waterfall
        partial.sums = None  # type: ignore[assignment]  # free the file's arrays
        partial.waterfall = None  # type: ignore[assignment]
        infos.append(partial)
        report(lo + (hi - lo) * (i + 1) / ntasks, f"file {i + 1}/{ntasks} summed")
    if sums is None or waterfall is None:
        raise PipelineError("the selection left no data")
    return (sums if not blocks else (blocks, sums)), waterfall, infos
