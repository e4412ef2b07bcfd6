"""Decoding the deflate-compressed chunks of a UVH5 data set on threads, outside HDF5.

HDF5 decodes a chunked data set one chunk at a time under h5py's lock, so a process decodes
on one core however many threads read: for a HERA night file (visibilities in gzip level 1
chunks with the shuffle filter, as pyuvdata and the correlator write them) that was 6.5 s of
a ~10 s fit on this two-core machine. For a data set whose filters are shuffle and deflate
only, :class:`InflatingReader` reads the stored bytes of each chunk with h5py's
``read_direct_chunk`` (no decoding; a few milliseconds per block), inflates them with ISA-L
(the ``isal`` package; the standard library's ``zlib`` without it; both release the GIL)
and undoes the shuffle (:mod:`autocal.io.shuffle_kernel`), chunk by chunk on a pool of
threads, each writing its chunk's part of the slab. Inflating and unshuffling are exact,
so the values are those HDF5 decodes, bit for bit (``tests/io/test_uvh5_inflate.py``).
Any other filter, a chunk stored with a filter skipped, or a chunk not stored at all
leaves the data set to HDF5.
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import h5py
import numpy as np

logger = logging.getLogger(__name__)

try:  # ISA-L inflates deflate streams ~1.6x faster than zlib, bit for bit the same bytes
    from isal import isal_zlib as _inflate_lib
except ImportError:  # pragma: no cover - isal is a dependency; zlib is the fallback
    _inflate_lib = zlib

#: The HDF5 filters this module undoes: shuffle, then deflate (their order on writing).
SHUFFLE, DEFLATE = h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_DEFLATE

_pool_lock = threading.Lock()
_pool: tuple[int, int, ThreadPoolExecutor] | None = None  # (pid, threads, pool)


def _threads() -> int:
    from autocal.fit.sums import default_threads  # AUTOCAL_FIT_THREADS / OMP_NUM_THREADS

    return default_threads()


def _map(run: Callable[[Any], None], tasks: list[Any]) -> None:
    """Run ``run`` over ``tasks`` on the process's decoding threads (inline with one)."""
    global _pool
    nthreads = min(_threads(), len(tasks))
    if nthreads <= 1:
        for task in tasks:
            run(task)
        return
    with _pool_lock:  # one pool per process (a forked child makes its own)
        if _pool is None or _pool[0] != os.getpid() or _pool[1] < nthreads:
            _pool = (
                os.getpid(),
                nthreads,
                ThreadPoolExecutor(nthreads, thread_name_prefix="autocal-inflate"),
            )
        pool = _pool[2]
    list(pool.map(run, tasks))


def _pipeline(dset: Any) -> tuple[int, ...] | None:
    """Return the data set's filter ids in writing order (``None``: not chunked)."""
    if dset.chunks is None:
        return None
    plist = dset.id.get_create_plist()
    return tuple(plist.get_filter(i)[0] for i in range(plist.get_nfilters()))


class InflatingReader:
    """Fill slabs of a shuffle/deflate data set from its stored chunks, on threads.

    Parameters
    ----------
    dset
        An h5py data set of ``(Nblt, Nfreq, Npol)`` or the legacy ``(Nblt, 1, Nfreq,
        Npol)``.

    Attributes
    ----------
    active
        Whether :meth:`fill` decodes this data set (its filters are a deflate, with or
        without a shuffle before it, and nothing has sent it back to HDF5).
    """

    def __init__(self, dset: Any) -> None:
        filters = _pipeline(dset)
        self.active = (
            filters in ((DEFLATE,), (SHUFFLE, DEFLATE))
            and not dset.dtype.names
            and dset.dtype.kind in "biufc"
        )
        self.shuffled = filters is not None and SHUFFLE in filters
        # h5py properties take its lock on every access: read them once
        self.dsid, self.name, self.ndim = dset.id, dset.name, dset.ndim
        self.shape, self.chunks, self.dtype = dset.shape, dset.chunks, dset.dtype
        self.chunk_bytes = int(np.prod(self.chunks or (0,))) * self.dtype.itemsize

    def fill(self, out: np.ndarray, lo: int, hi: int, chans: slice, pols: slice) -> bool:
        """Fill ``out`` (C-ordered: rows ``lo:hi``, ``chans``, ``pols``) and return ``True``.

        ``False`` (nothing written to ``out``) when the data set is to be read by HDF5:
        it is then for the rest of the file.

        Raises
        ------
        OSError
            A stored chunk that does not inflate to a chunk's size (corrupt data).
        """
        if not self.active:
            return False
        c0, c1, _ = chans.indices(self.shape[-2])
        p0, p1, _ = pols.indices(self.shape[-1])
        ranges = [(lo, hi), (c0, c1), (p0, p1)]
        if self.ndim == 4:
            ranges.insert(1, (0, 1))
        grids = [
            range(start - start % size, stop, size)
            for (start, stop), size in zip(ranges, self.chunks, strict=True)
        ]
        tasks = []
        for offset in itertools.product(*grids):
            try:
                mask, stored = self.dsid.read_direct_chunk(offset)
            except (KeyError, OSError, RuntimeError, ValueError, MemoryError):  # not stored
                # (h5py raises MemoryError for a chunk never written): a fill value
                mask, stored = -1, b""
            if mask != 0:  # a filter skipped for this chunk, or no chunk: HDF5 knows
                logger.debug("%s: chunk %s is not plainly stored; HDF5 decodes", self.name, offset)
                self.active = False
                return False
            tasks.append((offset, stored))
        _map(lambda task: self._decode_into(out, ranges, *task), tasks)
        return True

    def _decode_into(
        self,
        out: np.ndarray,
        ranges: list[tuple[int, int]],
        offset: tuple[int, ...],
        stored: bytes,
    ) -> None:
        """Inflate one chunk and copy its part of the slab into ``out``."""
        try:
            raw = _inflate_lib.decompress(stored)
        except (_inflate_lib.error, zlib.error, ValueError, OSError) as err:
            raise OSError(f"{self.name}: the chunk at {offset} does not inflate ({err})") from err
        if len(raw) != self.chunk_bytes:
            raise OSError(
                f"{self.name}: the chunk at {offset} inflates to {len(raw)} bytes, "
                f"not {self.chunk_bytes}"
            )
        flat = np.frombuffer(raw, np.uint8)
        if self.shuffled:  # byte k of every value, then byte k + 1, ...
            from autocal.io.shuffle_kernel import unshuffle  # numba

            flat = unshuffle(flat, self.dtype.itemsize, np.empty(flat.size, np.uint8))
        chunk = flat.view(self.dtype).reshape(self.chunks)
        src, dst = [], []
        for (start, stop), o, size in zip(ranges, offset, self.chunks, strict=True):
            a, b = max(start, o), min(stop, o + size)
            src.append(slice(a - o, b - o))
            dst.append(slice(a - start, b - start))
        part = chunk[tuple(src)]
        if self.ndim == 4:
            part, dst = part[:, 0], [dst[0], *dst[2:]]
        out[tuple(dst)] = part
