"""Reading the data sets of a UVH5 file with h5py: rows, reused buffers, repeated chunks.

The block reader (:mod:`autocal.io.uvh5_blocks`) reads the ``Data/visdata``,
``Data/flags`` and ``Data/nsamples`` data sets of a UVH5 file a run of baseline-time rows
at a time with :func:`read_rows`. :class:`CountingFile` counts the bytes HDF5 reads from
the file, :class:`Buffers` keeps arrays that are reused from block to block, and
:class:`RepeatedChunks` decodes each distinct stored chunk once (raw files store the same
flags and nsamples chunk over and over). :class:`ReadStats` adds up what was read (the
night benchmark's "data read once" figures).
"""

from __future__ import annotations

import io
import itertools
import logging
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from autocal.io.uvh5_inflate import InflatingReader

logger = logging.getLogger(__name__)


@dataclass
class ReadStats:
    """What :func:`~autocal.io.uvh5_blocks.iter_uvh5_blocks` read (summed over files and blocks).

    Attributes
    ----------
    files, blocks, integrations
        Files opened, blocks yielded, integrations yielded.
    samples
        Values yielded (antennas x pols x integrations x channels).
    bytes_read
        Bytes the HDF5 library read from the files (headers, chunk indices and the
        compressed chunks), counted at the file object.
    bytes_decoded
        Bytes of the arrays the data sets were decoded into.
    bytes_reused
        Of those, bytes taken from a stored chunk identical to one already decoded
        instead of decoded again: copied, or, when every chunk of a slab is one value,
        not even copied (that value broadcast; uniform nsamples, unflagged data; see
        :class:`RepeatedChunks`).
    largest_array
        Bytes of the largest single array read from a data set (bounded by the block).
    checksum_bytes
        Bytes read to compute the files' SHA-256 (provenance).
    blocks_from_memory
        Blocks served from memory instead of the files (not counted in ``blocks``): a
        calibration keeps a small observation's decoded blocks between its reads
        (:mod:`autocal.pipeline.decoded`).
    """

    files: int = 0
    blocks: int = 0
    integrations: int = 0
    samples: int = 0
    bytes_read: int = 0
    bytes_decoded: int = 0
    bytes_reused: int = 0
    largest_array: int = 0
    checksum_bytes: int = 0
    blocks_from_memory: int = 0

    def add(self, other: ReadStats) -> None:
        """Add another reader's counters to these (``largest_array``: the maximum)."""
        for key, value in asdict(other).items():
            if key == "largest_array":
                self.largest_array = max(self.largest_array, value)
            else:
                setattr(self, key, getattr(self, key) + value)

    def as_dict(self) -> dict[str, int]:
        """Return the counters as a dictionary."""
        return asdict(self)


class CountingFile(io.FileIO):
    """A binary file that counts the bytes read through it (h5py file-object driver)."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, "rb")
        self.nread = 0

    def readinto(self, buffer: Any) -> int | None:
        """Read into ``buffer`` and count the bytes."""
        n = super().readinto(buffer)
        self.nread += n or 0
        return n

    def read(self, size: int = -1) -> bytes:
        """Read up to ``size`` bytes and count them."""
        data = super().read(size)
        self.nread += len(data)
        return data


def read_rows(
    dset: Any,
    rows: np.ndarray,
    chans: slice,
    pols: slice,
    stats: ReadStats,
    buffers: Buffers | None = None,
    repeats: RepeatedChunks | None = None,
    inflater: InflatingReader | None = None,
) -> np.ndarray:
    """Read ``rows`` (sorted blt indices) of a data set as ``(Nrows, Nchan, Npol)``.

    A dense set of rows is read as one slab (one hyperslab, whole chunks) and the rows
    picked in memory; a sparse one (e.g. autos among cross-correlations) by h5py's
    point selection, so memory stays bounded by the rows asked for. With ``buffers`` a
    slab of consecutive rows is decoded into a reused array (``read_direct``; no fresh
    pages to fault in per block); the result is then only valid until the next read of
    this data set. With ``repeats`` such a slab is assembled from the data set's distinct
    stored chunks, each decoded once (:class:`RepeatedChunks`; all one value: that value
    broadcast, a read-only array with zero strides), and with ``inflater`` its
    chunks are inflated on threads outside HDF5
    (:class:`~autocal.io.uvh5_inflate.InflatingReader`).
    """
    lo, hi = int(rows[0]), int(rows[-1]) + 1
    dense = rows.size >= 0.5 * (hi - lo)
    first: slice | np.ndarray = slice(lo, hi) if dense else rows
    index: tuple[Any, ...] = (first, 0, chans, pols) if dset.ndim == 4 else (first, chans, pols)
    slab = dense and rows.size == hi - lo and not dset.dtype.names
    repeating = repeats is not None and repeats.active
    inflating = inflater is not None and inflater.active
    if slab and (buffers is not None or repeating or inflating):
        nchan = len(range(*chans.indices(dset.shape[-2])))
        npol = len(range(*pols.indices(dset.shape[-1])))
        shape = (rows.size, nchan, npol)
        arr = _fill_slab(
            dset,
            lambda: (
                np.empty(shape, dset.dtype)
                if buffers is None
                else buffers.get(f"raw {dset.name}", shape, dset.dtype)
            ),
            index,
            (lo, hi, chans, pols),
            stats,
            repeats,
            inflater,
        )
    else:
        arr = dset[index]
    if arr.dtype.names:  # the HERA correlator's compound type (fields r, i)
        arr = arr["r"] + 1j * arr["i"].astype(np.float64)
    stats.bytes_decoded += arr.nbytes
    stats.largest_array = max(stats.largest_array, arr.nbytes)
    if dense and rows.size != hi - lo:
        arr = arr[rows - lo]
    return arr


def _fill_slab(
    dset: Any,
    make: Callable[[], np.ndarray],
    index: tuple[Any, ...],
    where: tuple[int, int, slice, slice],
    stats: ReadStats,
    repeats: RepeatedChunks | None,
    inflater: InflatingReader | None,
) -> np.ndarray:
    """Return a slab: repeated chunks, else inflated on threads, else decoded by HDF5.

    Repeated chunks of one value give that value broadcast; the others fill the array
    ``make()`` returns.
    """
    if repeats is not None:
        arr = repeats.fill(make, *where, stats)
        if arr is not None:
            return arr
    arr = make()
    if inflater is None or not inflater.fill(arr, *where):
        dset.read_direct(arr, source_sel=index)
    return arr


def slab_chunks(
    shape: tuple[int, ...], chunks: tuple[int, ...], lo: int, hi: int, chans: slice, pols: slice
) -> tuple[list[tuple[int, int]], Iterator[tuple[int, ...]]]:
    """Return a slab's ``(start, stop)`` per data set axis and the offsets of its chunks.

    The slab is rows ``lo:hi``, ``chans`` and ``pols`` of a ``(Nblt, Nfreq, Npol)`` data
    set, or of the legacy ``(Nblt, 1, Nfreq, Npol)`` one (its spectral-window axis whole).
    """
    c0, c1, _ = chans.indices(shape[-2])
    p0, p1, _ = pols.indices(shape[-1])
    ranges = [(lo, hi), (c0, c1), (p0, p1)]
    if len(shape) == 4:
        ranges.insert(1, (0, 1))
    grids = [
        range(start - start % size, stop, size)
        for (start, stop), size in zip(ranges, chunks, strict=True)
    ]
    return ranges, itertools.product(*grids)


def one_value(chunk: np.ndarray) -> np.ndarray | None:
    """Return a chunk's one value (0-d) when all its values have the same bits, else ``None``."""
    if not chunk.size or chunk.dtype.names:
        return None
    flat = np.ascontiguousarray(chunk).reshape(-1)
    size = flat.dtype.itemsize
    if size in (1, 2, 4, 8):  # two passes, no temporaries
        bits = flat.view(f"u{size}")
        same = bits.min() == bits.max()
    else:  # e.g. complex128: compare every value's bytes with the first's
        rows = flat.view(np.uint8).reshape(-1, size)
        same = bool((rows == rows[0]).all())
    return np.array(flat[0]) if same else None


class Buffers:
    """Named arrays reused from block to block (grown when a block needs more)."""

    def __init__(self) -> None:
        self._flat: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        """Return an uninitialised C-ordered array of ``shape`` backed by buffer ``name``."""
        dtype = np.dtype(dtype)
        size = int(np.prod(shape))
        flat = self._flat.get(name)
        if flat is None or flat.dtype != dtype or flat.size < size:
            flat = self._flat[name] = np.empty(size, dtype)
        return flat[:size].reshape(shape)


class RepeatedChunks:
    """Decode each distinct stored chunk of a chunked data set once.

    Raw HERA files have flags that are all ``False`` and ``nsamples`` that are all equal,
    so their compressed chunks are identical byte for byte; decoding them took a third of
    the HDF5 time of a night file (profile: 5.7 s -> 3.8 s, ``benchmarks/night.py``).
    Here the stored bytes of every chunk a slab touches are read without decompression
    (``read_direct_chunk``); a chunk whose bytes (and filter mask and extent) were seen
    before is copied from its decoded copy, and only new ones are decoded by HDF5.
    Decompression is deterministic, so the values are exactly those of a plain read.
    After :data:`TRIAL_CHUNKS` chunks with fewer than half reused (e.g. real flags with
    RFI), or on a chunk that is not stored, the data set is read normally for the rest of
    the file.
    """

    #: Decoded chunks kept (distinct contents), and their largest total size in bytes.
    MAX_DISTINCT = 8
    MAX_BYTES = 64 << 20
    #: Chunks looked at before giving up on a data set whose chunks rarely repeat.
    TRIAL_CHUNKS = 64

    def __init__(self, dset: Any) -> None:
        self.dset = dset
        # h5py properties take its lock on every access: read them once
        self.ndim, self.shape, self.chunks, self.name = (
            dset.ndim,
            dset.shape,
            dset.chunks,
            dset.name,
        )
        self.dsid = dset.id
        self.active = self.chunks is not None and not dset.dtype.names
        self.decoded: dict[tuple[Any, ...], np.ndarray] = {}
        self.constant: dict[tuple[Any, ...], np.ndarray | None] = {}  # a kept chunk's one value
        self.seen = 0
        self.reused = 0

    def fill(
        self,
        make: Callable[[], np.ndarray],
        lo: int,
        hi: int,
        chans: slice,
        pols: slice,
        stats: ReadStats,
    ) -> np.ndarray | None:
        """Return the slab (rows ``lo:hi``, ``chans``, ``pols``), or ``None``.

        The slab is the array ``make()`` returns, filled; or, when every chunk it touches
        is one and the same value (raw HERA flags and nsamples), that value broadcast to
        the slab's shape (read-only, no memory). ``None`` when the data set is to be read
        normally.
        """
        if not self.active:
            return None
        dset = self.dset
        ranges, offsets = slab_chunks(self.shape, self.chunks, lo, hi, chans, pols)
        copies = []
        for offset in offsets:
            try:
                mask, stored = self.dsid.read_direct_chunk(offset)
            except (KeyError, OSError, RuntimeError, ValueError, MemoryError):  # not stored
                # (h5py raises MemoryError for a chunk never written): the fill value
                self.active = False
                self.decoded.clear()
                self.constant.clear()
                return None
            extent = tuple(
                min(o + size, n) - o
                for o, size, n in zip(offset, self.chunks, self.shape, strict=True)
            )
            key = (mask, extent, stored)
            chunk = self.decoded.get(key)
            reused = chunk is not None
            if chunk is None:
                chunk = dset[tuple(slice(o, o + e) for o, e in zip(offset, extent, strict=True))]
                kept = sum(c.nbytes for c in self.decoded.values()) + chunk.nbytes
                if len(self.decoded) < self.MAX_DISTINCT and kept <= self.MAX_BYTES:
                    self.decoded[key] = chunk
                    self.constant[key] = one_value(chunk)
            self.seen += 1
            self.reused += reused
            copies.append((offset, chunk, reused, self.constant.get(key)))
        if self.seen >= self.TRIAL_CHUNKS and 2 * self.reused < self.seen:
            logger.debug("%s: stored chunks rarely repeat; decoding all", self.name)
            self.active = False
            self.decoded.clear()
            self.constant.clear()
        # every chunk one and the same value: the value broadcast, no copy at all
        values = {None if c is None else c.tobytes() for *_, c in copies}
        whole = copies[0][3] if len(values) == 1 and None not in values else None
        if whole is None:
            out = make()
        else:
            (r0, r1), (c0, c1), (p0, p1) = ranges[0], ranges[-2], ranges[-1]
            out = np.broadcast_to(whole, (r1 - r0, c1 - c0, p1 - p0))
        for offset, chunk, reused, _ in copies:
            part = [
                (max(start, o), min(stop, o + n))
                for (start, stop), o, n in zip(ranges, offset, chunk.shape, strict=True)
            ]
            src = tuple(slice(a - o, b - o) for (a, b), o in zip(part, offset, strict=True))
            dst = [
                slice(a - start, b - start) for (a, b), (start, _) in zip(part, ranges, strict=True)
            ]
            block = chunk[src]
            if self.ndim == 4:
                block, dst = block[:, 0], [dst[0], *dst[2:]]
            if whole is None:
                out[tuple(dst)] = block
            if reused:
                stats.bytes_reused += block.nbytes
        return out
