"""An observation's decoded blocks, kept between its reads when they fit in memory.

A calibration reads its UVH5 files more than once: the flagging's two scans (the time-mean
spectra, then the outliers given them; :mod:`autocal.pipeline.flagging`) and the fit's
pass(es) (:mod:`autocal.pipeline.passes`), and HDF5 decoding is the largest single cost of
each read. When the whole observation, decoded, fits in :func:`budget_bytes`, the first read
keeps every block in a compact and lossless form and the later reads replay it:

* the auto power as ``float32`` when every value is one (the autos are stored as
  ``complex64`` in UVH5, so their real part always is), else ``float64``;
* the flags as they were yielded (the data's own flags and its non-finite samples), or
  nothing when the block flags no sample (raw HERA files flag none);
* ``nsamples`` as one number when uniform in the block (HERA's are), else ``float32`` or
  ``float64`` likewise.

A replayed block is the block the reader yielded, bit for bit (same values, flags,
integrations and metadata; only the payload bits of a NaN, a sample flagged as non-finite,
may differ), so the flags and the solution do not depend on whether the
cache was used (``tests/pipeline/test_decoded.py``). For HERA data (float32 power, uniform
``nsamples``) it holds 5 bytes per sample (1.03 GB for a whole HERA file of 350 antennas x 2
pols x 1536 channels x 192 integrations; 4 bytes, 0.83 GB, when the file flags nothing),
against the 9 to 16 of the reader's float64 power and flags (and float64 sample counts
when they are not one value). Reads in reader processes or on
Dask never use it; nor does an observation larger than the budget (a night is streamed, file
by file, as before).

Usage: :func:`keep_decoded` around the reads (``autocal.pipeline.calibrate`` does, and
calls :meth:`DecodedBlocks.final_read` after the flagging unless two passes are asked for:
the fit's first read then releases the blocks as it replays them, so that the memory goes
back while the fit's own grows; a second pass that ``passes="auto"`` decides on decodes the
files again); the block
reader of the pipeline (:func:`autocal.pipeline.partials.read_chunks`) calls
:func:`cached_blocks`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import closing, contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.io.uvh5_chunks import ReadStats
from autocal.pipeline.config import PipelineError

logger = logging.getLogger(__name__)

#: Environment variable: the most memory (GB) the decoded blocks may take; ``0`` turns the
#: cache off.
BUDGET_ENV = "AUTOCAL_DECODED_CACHE_GB"
#: Default budget (GB): a whole HERA file (1.03 GB) with room for a smaller selection's
#: overhead.
DEFAULT_BUDGET_GB = 1.5
#: Bytes a sample takes in the cache for HERA data (float32 power and a flag): the estimate
#: a read is kept on; a read that turns out larger is streamed, not kept.
BYTES_PER_SAMPLE = 5

_BIG = ("data", "flags", "nsamples")
_ACTIVE: ContextVar[DecodedBlocks | None] = ContextVar("autocal_decoded_blocks", default=None)


def budget_bytes() -> int:
    """Return the cache's budget in bytes (:data:`BUDGET_ENV`, default :data:`DEFAULT_BUDGET_GB`).

    Raises
    ------
    PipelineError
        When the variable is not a number >= 0.
    """
    raw = os.environ.get(BUDGET_ENV, "").strip()
    try:
        gb = DEFAULT_BUDGET_GB if not raw else float(raw)
    except ValueError:
        gb = float("nan")
    if not (math.isfinite(gb) and gb >= 0):
        raise PipelineError(
            f"{BUDGET_ENV}={raw!r} is not a size in GB >= 0 (e.g. 1.5; 0 turns the cache off)"
        )
    return int(gb * 2**30)


def _compact(values: np.ndarray) -> np.ndarray | float:
    """Return ``values`` as one number, float32 or float64, whichever holds them exactly.

    One number only when every value has the same bits (a ``-0.0`` among zeros is kept),
    as a broadcast of one value (zero strides, the reader's uniform ``nsamples``) always is.
    A C-contiguous float64 array is tested in one compiled pass
    (:mod:`autocal.pipeline.compact_kernel`), others as numpy arrays, with the same result.
    """
    if values.size and not any(values.strides) and np.isfinite(values.flat[0]):
        return float(values.flat[0])  # one value broadcast (a reader's uniform nsamples)
    if values.dtype == np.float64 and values.flags.c_contiguous and values.size:
        from autocal.pipeline.compact_kernel import compact_pass  # numba

        small = np.empty(values.shape, np.float32)
        same, exact = compact_pass(values, small)
        if same and np.isfinite(values.flat[0]):
            return float(values.flat[0])
        return small if exact else values.copy()
    bits = values.view(np.uint64) if values.dtype == np.float64 else None
    if bits is not None and np.all(bits == bits.flat[0]) and np.isfinite(values.flat[0]):
        return float(values.flat[0])
    with np.errstate(over="ignore", invalid="ignore"):  # as the compiled pass: no warning
        small = values.astype(np.float32)
    if np.array_equal(small, values, equal_nan=True):
        return small
    return values.copy()


@dataclass(frozen=True)
class _Block:
    """One block, compact: its big arrays and the rest of its fields."""

    data: np.ndarray | float
    flags: np.ndarray | bool
    nsamples: np.ndarray | float
    shape: tuple[int, ...]
    fields: dict[str, Any]

    @classmethod
    def of(cls, obs: Observation) -> _Block:
        rest = {
            f.name: _owned(getattr(obs, f.name))
            for f in dataclasses.fields(obs)
            if f.name not in _BIG
        }
        flags = obs.flags.copy() if obs.flags.any() else False  # raw files flag nothing
        return cls(_compact(obs.data), flags, _compact(obs.nsamples), obs.shape, rest)

    def observation(self, buffers: dict[str, np.ndarray] | None = None) -> Observation:
        """Return the block as the reader yielded it.

        With ``buffers``, its float64 arrays are written into the ones there of its shape
        (made on first use): a read that replays block after block reuses them, as the
        reader reuses its own (``reuse_buffers``), instead of mapping fresh memory (page
        faults and zeroing) for every block.
        """
        return Observation(
            data=_full(self.data, self.shape, buffers, "data"),
            flags=self.flags if isinstance(self.flags, np.ndarray) else None,  # None: none
            nsamples=self.nsamples
            if isinstance(self.nsamples, float)
            else _full(self.nsamples, self.shape, buffers, "nsamples"),
            **self.fields,
        )

    def scan_chunk(self, buffers: dict[str, np.ndarray] | None = None) -> ScanChunk:
        """Return the block's power (as kept: float32 or float64) and flags, for a scan.

        A block that flagged nothing gets an array of no flags, from ``buffers`` when given
        (made once for the read's blocks of its shape).
        """
        data = self.data
        if not isinstance(data, np.ndarray):
            data = np.broadcast_to(np.float64(data), self.shape)
        flags = self.flags if isinstance(self.flags, np.ndarray) else self._no_flags(buffers)
        return ScanChunk(_read_only(data), _read_only(flags))

    def _no_flags(self, buffers: dict[str, np.ndarray] | None) -> np.ndarray:
        """Return an array of no flags of the block's shape (``buffers["no_flags"]``, reused)."""
        zeros = (buffers or {}).get("no_flags")
        if zeros is None or zeros.shape != self.shape:
            zeros = np.zeros(self.shape, bool)
            if buffers is not None:
                buffers["no_flags"] = zeros
        return zeros

    @property
    def nbytes(self) -> int:
        return sum(int(getattr(a, "nbytes", 0)) for a in (self.data, self.flags, self.nsamples))


def _read_only(values: np.ndarray) -> np.ndarray:
    """Return a read-only view (the kept arrays are replayed again, to the fit)."""
    view = values.view()
    view.flags.writeable = False
    return view


@dataclass(frozen=True, eq=False)
class ScanChunk:
    """A replayed block as the flagging's scans read it: its power and flags, no copy.

    Attributes
    ----------
    data
        ``(Nant, Npol, Ntime, Nfreq)`` the auto power as kept (float32 when that holds it
        exactly, the reader's float64 values widened back give the same numbers), or one
        value broadcast; a read-only view.
    flags
        ``(Nant, Npol, Ntime, Nfreq)`` the block's flags (its data's own and the
        non-finite samples, as the reader yielded them); a read-only view.
    """

    data: np.ndarray
    flags: np.ndarray

    @property
    def ntime(self) -> int:
        """Integrations of the block."""
        return int(self.data.shape[2])


def _drain(queue: deque[_Block]) -> Iterator[_Block]:
    """Yield the blocks, each removed from ``queue`` first (so it is freed once used)."""
    while queue:
        yield queue.popleft()


def _owned(value: Any) -> Any:
    """Return a copy of an array (the reader may reuse its buffers), other values as they are."""
    if isinstance(value, np.ndarray):
        return value.copy()
    if isinstance(value, dict):
        return {k: _owned(v) for k, v in value.items()}
    return value


def _full(
    value: np.ndarray | float,
    shape: tuple[int, ...],
    buffers: dict[str, np.ndarray] | None = None,
    name: str = "",
) -> np.ndarray:
    """Return a kept array (or one value) as a float64 array of ``shape``.

    Into ``buffers[name]`` when it is given (made, or made again for another shape).
    """
    if buffers is None:
        return value.astype(np.float64) if isinstance(value, np.ndarray) else np.full(shape, value)
    out = buffers.get(name)
    if out is None or out.shape != shape:
        out = buffers[name] = np.empty(shape)
    np.copyto(out, value)
    return out


@dataclass
class DecodedBlocks:
    """The blocks kept so far, per read (file and selection), within a budget of bytes.

    Attributes
    ----------
    budget
        Bytes the blocks may take in all.
    reads
        ``{key: blocks}`` of the reads kept whole.
    used
        Bytes they take.
    replayed
        Blocks served from memory so far.
    last_read
        Set by :meth:`final_read`: kept reads are replayed once and released, nothing new
        is kept.
    """

    budget: int
    reads: dict[tuple[Any, ...], list[_Block]] = field(default_factory=dict)
    used: int = 0
    replayed: int = 0
    last_read: bool = False

    def blocks(
        self,
        key: tuple[Any, ...],
        read: Callable[[], Iterator[Observation]],
        stats: ReadStats,
        scan: bool = False,
    ) -> Iterator[Observation | ScanChunk]:
        """Yield the read's blocks: replayed when kept, else read (and kept if they fit).

        After :meth:`final_read`, a kept read is replayed once, each block released as it
        is yielded, and nothing new is kept. A replayed block's float64 arrays are reused
        for the next block (each block is used up before the next is asked for, as with
        the reader's reused buffers). With ``scan``, a replayed block is yielded as
        a :class:`ScanChunk` (its power as kept, not widened to a new float64 array, and
        no :class:`~autocal.core.observation.Observation` built): what the flagging's
        scans read.

        Parameters
        ----------
        key
            The read (file, selection, block size).
        read
            Reads the blocks from the file.
        stats
            Read counters to add to.
        scan
            Yield replayed blocks as :class:`ScanChunk`.
        """
        kept = self.reads.pop(key, None) if self.last_read else self.reads.get(key)
        if kept is not None:
            # on the last read the list is used up as it goes: each block freed once yielded
            queue = deque(kept) if self.last_read else None
            if queue is not None:
                kept.clear()  # the queue holds the only references
            buffers: dict[str, np.ndarray] = {}  # reused block after block
            try:
                for block in kept if queue is None else _drain(queue):
                    if queue is not None:
                        self.used -= block.nbytes
                    self.replayed += 1
                    stats.blocks_from_memory += 1
                    yield block.scan_chunk(buffers) if scan else block.observation(buffers)
            finally:  # left early on the last read: the rest is freed too
                self.used -= sum(b.nbytes for b in queue or ())
            return
        if self.last_read:
            yield from read()
            return
        new: list[_Block] | None = []
        size = 0
        with closing(read()) as blocks:  # closed at once if the caller stops early
            for obs in blocks:
                if new is not None:
                    block = _Block.of(obs)
                    size += block.nbytes
                    if self.used + size <= self.budget:
                        new.append(block)
                    else:  # larger than expected: stream it, keep nothing
                        logger.info("decoded blocks exceed the budget; later reads decode again")
                        new = None
                yield obs
        if new is not None:  # read to the end: keep it
            self.reads[key] = new
            self.used += size

    def final_read(self) -> None:
        """Say that the next read of each file is its last: replay it once, keep nothing."""
        self.last_read = True


@contextmanager
def keep_decoded(expected_bytes: int) -> Iterator[DecodedBlocks | None]:
    """Keep the decoded blocks of the reads inside the block when they fit.

    Parameters
    ----------
    expected_bytes
        The observation's size in the cache (:data:`BYTES_PER_SAMPLE` per sample).

    Yields
    ------
    DecodedBlocks or None
        The cache, or ``None`` (not used) when ``expected_bytes`` exceeds
        :func:`budget_bytes`.
    """
    budget = budget_bytes()
    if expected_bytes > budget or budget == 0:
        yield None
        return
    cache = DecodedBlocks(budget)
    token = _ACTIVE.set(cache)
    try:
        yield cache
    finally:
        _ACTIVE.reset(token)
        logger.debug(
            "decoded blocks: %.2f GB kept, %d blocks replayed", cache.used / 2**30, cache.replayed
        )


def cached_blocks(
    key: tuple[Any, ...],
    read: Callable[[], Iterator[Observation]],
    stats: ReadStats,
    scan: bool = False,
) -> Iterator[Observation | ScanChunk]:
    """Return the read's blocks through the active cache, or ``read()`` without one.

    Parameters
    ----------
    key, read, stats, scan
        As :meth:`DecodedBlocks.blocks` (with ``scan``, replayed blocks are
        :class:`ScanChunk`).

    Returns
    -------
    Iterator
        The blocks.
    """
    cache = _ACTIVE.get()
    return read() if cache is None else cache.blocks(key, read, stats, scan)
