"""Decoding the deflate-compressed chunks of a UVH5 data set on threads, outside HDF5.

HDF5 decodes a chunked data set one chunk at a time under h5py's lock, so a process decodes
on one core however many threads read: for a HERA-size night file as ``benchmarks/night.py``
writes them (visibilities in gzip level 1 chunks with the shuffle filter) that was 6.5 s of
a ~10 s fit on this two-core machine. For a data set whose filters are shuffle and deflate
only and whose stored type is the one h5py reads it as, :class:`InflatingReader` reads the
stored bytes of each chunk with h5py's ``read_direct_chunk`` (no decoding; a few
milliseconds per block), inflates them with ISA-L (the ``isal`` package; the standard
library's ``zlib`` without it; both release the GIL) and undoes the shuffle
(:mod:`autocal.io.shuffle_kernel`), chunk by chunk on a pool of threads, each writing its
chunk's part of the slab. Inflating and unshuffling are exact, so the values are those HDF5
decodes, bit for bit (``tests/io/test_uvh5_inflate.py``). Any other filter or stored type
(e.g. uncompressed or LZF data sets, which is how pyuvdata writes visibilities by default and
how the real HERA files of the data folder are stored; the correlator's compound integers), a
chunk stored with a filter skipped, not stored at all, or not inflating to a chunk leaves
the data set to HDF5 (which then reports a chunk that is really corrupt).
"""

from __future__ import annotations

import logging
import zlib
from typing import Any

import h5py
import numpy as np

from autocal.io.uvh5_chunks import slab_chunks

logger = logging.getLogger(__name__)

try:  # ISA-L inflates deflate streams ~1.6x faster than zlib, bit for bit the same bytes
    from isal import isal_zlib as _inflate_lib
except ImportError:  # pragma: no cover - isal is a dependency; zlib is the fallback
    _inflate_lib = zlib

#: The HDF5 filters this module undoes: shuffle, then deflate (their order on writing).
SHUFFLE, DEFLATE = h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_DEFLATE


def _pipeline(dset: Any) -> tuple[int, ...] | None:
    """Return the data set's filter ids in writing order.

    ``None`` when it is not chunked, or its shuffle is for another value size than its own.
    """
    if dset.chunks is None:
        return None
    plist = dset.id.get_create_plist()
    filters = [plist.get_filter(i) for i in range(plist.get_nfilters())]
    for fid, _, values, _ in filters:
        if fid == SHUFFLE and values and values[0] != dset.dtype.itemsize:
            return None
    return tuple(f[0] for f in filters)


class _InflateError(Exception):
    """A stored chunk that does not inflate to a chunk's bytes (HDF5 then reads it)."""


def _stored_as_read(dset: Any) -> bool:
    """Whether the stored type is the one h5py reads the data set as, byte for byte.

    h5py reads some stored types as another numpy type (a compound of two floats as
    complex, whatever its field offsets or padding); their stored bytes are not the
    values' bytes.
    """
    try:
        return bool(dset.id.get_type().equal(h5py.h5t.py_create(dset.dtype, logical=True)))
    except (TypeError, ValueError):  # pragma: no cover - a type h5py cannot describe
        return False


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
            and _stored_as_read(dset)
        )
        self.shuffled = filters is not None and SHUFFLE in filters
        # h5py properties take its lock on every access: read them once
        self.dsid, self.name, self.ndim = dset.id, dset.name, dset.ndim
        self.shape, self.chunks, self.dtype = dset.shape, dset.chunks, dset.dtype
        self.chunk_bytes = int(np.prod(self.chunks or (0,))) * self.dtype.itemsize

    def fill(self, out: np.ndarray, lo: int, hi: int, chans: slice, pols: slice) -> bool:
        """Fill ``out`` (C-ordered: rows ``lo:hi``, ``chans``, ``pols``) and return ``True``.

        ``False`` when the data set is to be read by HDF5 (``out`` may then hold part of
        the slab; HDF5 writes all of it): it is then for the rest of the file.
        """
        if not self.active:
            return False
        ranges, offsets = slab_chunks(self.shape, self.chunks, lo, hi, chans, pols)
        tasks = []
        for offset in offsets:
            try:
                mask, stored = self.dsid.read_direct_chunk(offset)
            except (KeyError, OSError, RuntimeError, ValueError, MemoryError) as err:
                # not stored (h5py raises MemoryError for a chunk never written: the fill
                # value), or not readable: HDF5 reads it, or says what is wrong
                return self._to_hdf5(f"chunk {offset} not read directly ({type(err).__name__})")
            if mask != 0:
                return self._to_hdf5(f"chunk {offset} is stored with filter mask {mask}")
            tasks.append((offset, stored))
        from autocal.fit.threads import in_threads  # AUTOCAL_FIT_THREADS threads

        def decode(lo: int, hi: int) -> None:
            for task in tasks[lo:hi]:
                self._decode_into(out, ranges, *task)

        try:  # every range has finished when in_threads returns or raises
            in_threads(decode, len(tasks))
        except _InflateError as err:  # e.g. an edge chunk stored unfiltered: HDF5 knows
            return self._to_hdf5(str(err))
        return True

    def _to_hdf5(self, why: str) -> bool:
        logger.debug("%s: %s; HDF5 decodes the rest of the file", self.name, why)
        self.active = False
        return False

    def _decode_into(
        self,
        out: np.ndarray,
        ranges: list[tuple[int, int]],
        offset: tuple[int, ...],
        stored: bytes,
    ) -> None:
        """Inflate one chunk and copy its part of the slab into ``out``."""
        try:  # at most one byte more than a chunk: enough to tell a chunk too long
            raw = _inflate_lib.decompressobj().decompress(stored, self.chunk_bytes + 1)
        except (_inflate_lib.error, zlib.error, ValueError, OSError) as err:
            raise _InflateError(f"the chunk at {offset} does not inflate ({err})") from err
        if len(raw) != self.chunk_bytes:
            raise _InflateError(
                f"the chunk at {offset} inflates to {len(raw)} bytes, not {self.chunk_bytes}"
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
