"""Auto-correlations of one UVH5 file read block by block, in bounded memory.

:func:`iter_uvh5_blocks` slices the file's data sets with h5py along the baseline-time
axis and yields :class:`autocal.core.observation.Observation` blocks of consecutive
integrations, so a HERA file of 350 antennas x 1536 channels x 192 integrations (1.65 GB as
complex64) never sits in memory whole. Reading is a two-stage pipeline in background
threads (HDF5 reads and decompression; conversion to the ``(Nant, Npol, Ntime, Nfreq)``
layout and the observation checks) running ahead of the caller, with the file's SHA-256
computed alongside; chunks of flags and nsamples that are stored identically (raw files:
no flags, uniform nsamples) are decoded once. :class:`ReadStats` counts what was read (the
night benchmark's "data read once" figures). Headers, selections and whole-file reads are in
:mod:`autocal.io.uvh5`.
"""

from __future__ import annotations

import io
import itertools
import logging
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.files import file_checksum
from autocal.core.observation import Observation
from autocal.errors import AutocalError
from autocal.io.uvh5 import (
    UVH5File,
    UVH5FormatError,
    _FileMeta,
    _lst_mask,
    _scan,
    _select_antennas,
    _select_channels,
    _select_pols,
    _site,
)

logger = logging.getLogger(__name__)

#: Default largest number of values (antennas x pols x integrations x channels) in one
#: block of :func:`iter_uvh5_blocks`: 2**23 = 8.4 M values, i.e. 67 MB as float64.
BLOCK_SAMPLES = 1 << 23


@dataclass
class ReadStats:
    """What :func:`iter_uvh5_blocks` read (counters add up over files and blocks).

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
        Of those, bytes copied from a stored chunk identical to one already decoded
        instead of decoded again (uniform nsamples, unflagged data; see
        :class:`_RepeatedChunks`).
    largest_array
        Bytes of the largest single array read from a data set (bounded by the block).
    checksum_bytes
        Bytes read to compute the files' SHA-256 (provenance).
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


class _CountingFile(io.FileIO):
    """A binary file that counts the bytes read through it (h5py file-object driver)."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, "rb")
        self.nread = 0

    def readinto(self, buffer: Any) -> int | None:
        n = super().readinto(buffer)
        self.nread += n or 0
        return n

    def read(self, size: int = -1) -> bytes:
        data = super().read(size)
        self.nread += len(data)
        return data


def _time_blocks(kept: np.ndarray, block_size: int) -> list[tuple[int, int]]:
    """Split kept time indices into runs of consecutive indices of at most block_size."""
    blocks: list[tuple[int, int]] = []
    if kept.size == 0:
        return blocks
    breaks = np.flatnonzero(np.diff(kept) != 1) + 1
    for run in np.split(kept, breaks):
        for start in range(0, run.size, block_size):
            part = run[start : start + block_size]
            blocks.append((int(part[0]), int(part[-1]) + 1))
    return blocks


def _read_rows(
    dset: Any,
    rows: np.ndarray,
    chans: slice,
    pols: slice,
    stats: ReadStats,
    buffers: _Buffers | None = None,
    repeats: _RepeatedChunks | None = None,
) -> np.ndarray:
    """Read ``rows`` (sorted blt indices) of a data set as ``(Nrows, Nchan, Npol)``.

    A dense set of rows is read as one slab (one hyperslab, whole chunks) and the rows
    picked in memory; a sparse one (e.g. autos among cross-correlations) by h5py's
    point selection, so memory stays bounded by the rows asked for. With ``buffers`` a
    slab of consecutive rows is decoded into a reused array (``read_direct``; no fresh
    pages to fault in per block); the result is then only valid until the next read of
    this data set. With ``repeats`` such a slab is assembled from the data set's distinct
    stored chunks, each decoded once (:class:`_RepeatedChunks`).
    """
    lo, hi = int(rows[0]), int(rows[-1]) + 1
    dense = rows.size >= 0.5 * (hi - lo)
    first: slice | np.ndarray = slice(lo, hi) if dense else rows
    index: tuple[Any, ...] = (first, 0, chans, pols) if dset.ndim == 4 else (first, chans, pols)
    slab = dense and rows.size == hi - lo and not dset.dtype.names
    if slab and (buffers is not None or (repeats is not None and repeats.active)):
        nchan = len(range(*chans.indices(dset.shape[-2])))
        npol = len(range(*pols.indices(dset.shape[-1])))
        shape = (rows.size, nchan, npol)
        arr = (
            np.empty(shape, dset.dtype)
            if buffers is None
            else buffers.get(f"raw {dset.name}", shape, dset.dtype)
        )
        if repeats is None or not repeats.fill(arr, lo, hi, chans, pols, stats):
            dset.read_direct(arr, source_sel=index)
    else:
        arr = dset[index]
    if arr.dtype.names:  # the HERA correlator's compound type (fields r, i)
        arr = arr["r"] + 1j * arr["i"].astype(np.float64)
    stats.bytes_decoded += arr.nbytes
    stats.largest_array = max(stats.largest_array, arr.nbytes)
    if dense and rows.size != hi - lo:
        arr = arr[rows - lo]
    return arr


class _Buffers:
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


#: Polarisation codes whose autos are real powers (pyuvdata makes them real with abs()).
SAME_FEED_POL_CODES = (-1, -2, -5, -6, 1, 2, 3, 4)


class _RepeatedChunks:
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
        self.seen = 0
        self.reused = 0

    def fill(
        self, out: np.ndarray, lo: int, hi: int, chans: slice, pols: slice, stats: ReadStats
    ) -> bool:
        """Fill ``out`` (rows ``lo:hi``, ``chans``, ``pols``) and return ``True``.

        ``False`` (nothing to rely on in ``out``) when the data set is to be read
        normally.
        """
        if not self.active:
            return False
        dset = self.dset
        c0, c1, _ = chans.indices(self.shape[-2])
        p0, p1, _ = pols.indices(self.shape[-1])
        # (start, stop) per data set axis; the legacy 4-d layout has a spectral-window axis
        ranges = [(lo, hi), (c0, c1), (p0, p1)]
        if self.ndim == 4:
            ranges.insert(1, (0, 1))
        grids = [
            range(start - start % size, stop, size)
            for (start, stop), size in zip(ranges, self.chunks, strict=True)
        ]
        copies = []
        for offset in itertools.product(*grids):
            try:
                mask, stored = self.dsid.read_direct_chunk(offset)
            except (KeyError, OSError, RuntimeError, ValueError):  # not stored: fill value
                self.active = False
                self.decoded.clear()
                return False
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
            self.seen += 1
            self.reused += reused
            copies.append((offset, chunk, reused))
        if self.seen >= self.TRIAL_CHUNKS and 2 * self.reused < self.seen:
            logger.debug("%s: stored chunks rarely repeat; decoding all", self.name)
            self.active = False
            self.decoded.clear()
        for offset, chunk, reused in copies:
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
            out[tuple(dst)] = block
            if reused:
                stats.bytes_reused += block.nbytes
        return True


def _auto_power(arr: np.ndarray, same_feed: np.ndarray) -> np.ndarray:
    """Real auto power of complex ``(Nrows, Nchan, Npol)`` values, as pyuvdata reads it.

    pyuvdata replaces same-feed autos that carry an imaginary part by their modulus
    (``UVData.check(fix_autos=True)``); other values keep their real part.
    """
    real = arr.real
    imag = arr.imag
    if not np.any(imag if same_feed.all() else imag[..., same_feed]):
        return real
    fix = (imag != 0) & same_feed[None, None, :]
    logger.debug("replacing %d same-feed autos with imaginary parts by |V|", int(fix.sum()))
    return np.where(fix, np.abs(arr), real)


def _meta_of(file: UVH5File | _FileMeta | str | Path) -> _FileMeta:
    if isinstance(file, _FileMeta):
        return file
    if isinstance(file, UVH5File) and isinstance(file.header, _FileMeta):
        return file.header
    path = file.path if isinstance(file, UVH5File) else Path(file)
    return _scan([path])[0]


def iter_uvh5_blocks(
    file: UVH5File | _FileMeta | str | Path,
    *,
    antennas: Sequence[int] | None = None,
    pols: Sequence[str] | None = None,
    freq_range: tuple[float, float] | None = None,
    lst_range: tuple[float, float] | None = None,
    block_size: int | None = None,
    max_block_samples: int = BLOCK_SAMPLES,
    stats: ReadStats | None = None,
    checksum: bool = True,
    prefetch: bool = True,
    reuse_buffers: bool = False,
    decode_repeats_once: bool = True,
) -> Iterator[Observation]:
    """Yield the autos of one UVH5 file in blocks of consecutive integrations.

    The data sets are sliced with h5py along the baseline-time axis, so memory is
    bounded by the block, not by the file (a HERA file of 350 antennas x 1536 channels
    x 192 integrations is 1.65 GB as complex64). Selections are those of
    :func:`read_uvh5`; the values equal what :func:`read_uvh5` returns for the same
    integrations.

    Parameters
    ----------
    file
        A :class:`UVH5File` from :func:`scan_uvh5` (its header is reused) or a path.
    antennas, pols, freq_range, lst_range
        As for :func:`read_uvh5`.
    block_size
        Integrations per block (default: as many as fit in ``max_block_samples``).
        Blocks never span a gap in the LST selection.
    max_block_samples
        Largest number of values per block when ``block_size`` is not given.
    stats
        Counters to add to (bytes read, largest array, blocks, ...).
    checksum
        Compute the file's SHA-256 (``meta["sha256"]``; memoised per process). It is
        computed in a second thread while the first block is read; it reads the file
        faster than HDF5 decodes it, so the data are then served from the page cache.
    prefetch
        Read and decode the next blocks in background threads while the caller works on
        the current one (HDF5 decompression releases the GIL): at most three blocks are
        in memory (the caller's, the next one decoded, the one after that being read).
        Errors are raised at the block they belong to; closing the generator early waits
        for the blocks in flight and closes the file.
    reuse_buffers
        Decode every block into the same two sets of arrays (alternating) instead of
        fresh ones, which spares faulting in new pages for every block (~7 % of a night
        file's time here, ``benchmarks/reader.py``). A yielded block is then valid only
        until the next one is requested: copy what must outlive the loop iteration. The
        values are the same.
    decode_repeats_once
        Decode each distinct stored chunk of the flags and nsamples once and copy its
        repeats (:class:`_RepeatedChunks`; on raw files a third of the HDF5 time). The
        values are the same; ``False`` decodes every chunk.

    Yields
    ------
    Observation
        One block: ``meta`` has ``source``, ``files``, ``sha256``, ``block`` and
        ``nblocks``, ``x_orientation``, ``vis_units``.

    Raises
    ------
    UVH5FormatError, ObservationError
        As :func:`read_uvh5`; ``ValueError`` for a block size below 1.
    """
    import h5py

    meta = _meta_of(file)
    stats = stats if stats is not None else ReadStats()
    ants = _select_antennas(meta, antennas)
    pol_idx = _select_pols(meta, pols)
    chans = _select_channels(meta, freq_range)
    kept = np.flatnonzero(_lst_mask(meta.lsts, lst_range))
    if kept.size == 0:
        return
    nant, npol, nfreq = len(ants), len(pol_idx), chans.size
    if block_size is None:
        block_size = max(1, int(max_block_samples) // (nant * npol * nfreq))
    if int(block_size) < 1:
        raise AutocalError(f"block_size must be at least 1 integration, got {block_size}")
    blocks = _time_blocks(kept, int(block_size))

    telescope = meta.uv.telescope
    names_by_number = {
        int(n): str(name)
        for n, name in zip(telescope.antenna_numbers, telescope.antenna_names, strict=True)
    }
    common: dict[str, Any] = {
        "freqs": meta.freqs[chans],
        "antennas": np.array(ants),
        "pols": tuple(meta.pol_names[i] for i in pol_idx),
        "site": _site(meta.uv),
        "channel_width": meta.channel_width[chans],
        "antenna_names": tuple(names_by_number.get(a, f"ant{a}") for a in ants),
        "telescope_name": str(telescope.name),
    }
    file_meta: dict[str, Any] = {
        "source": "uvh5",
        "files": [str(meta.path)],
        "x_orientation": meta.x_orientation,
        "vis_units": str(meta.uv.vis_units),
    }
    c0, c1 = int(chans.min()), int(chans.max()) + 1
    fidx = chans - c0
    fidx_all = bool(np.array_equal(fidx, np.arange(c1 - c0)))
    p0, p1 = min(pol_idx), max(pol_idx) + 1
    pidx = np.asarray(pol_idx) - p0
    pidx_all = bool(np.array_equal(pidx, np.arange(p1 - p0)))
    same_feed = np.array([meta.pol_codes[i] in SAME_FEED_POL_CODES for i in pol_idx])
    block_sets = (_Buffers(), _Buffers()) if reuse_buffers else None
    raw_sets = (_Buffers(), _Buffers()) if reuse_buffers else None

    raw = _CountingFile(meta.path)
    counted = 0
    try:
        with h5py.File(raw, "r") as h5:
            try:
                header = h5["Header"]
                ant1 = np.asarray(header["ant_1_array"][()])
                ant2 = np.asarray(header["ant_2_array"][()])
                times = np.asarray(header["time_array"][()], np.float64)
                tint_blt = np.broadcast_to(
                    np.asarray(header["integration_time"][()], np.float64), times.shape
                )
                datasets = [h5["Data/visdata"], h5["Data/flags"], h5["Data/nsamples"]]
            except KeyError as err:
                raise UVH5FormatError(f"{meta.path} lacks a UVH5 data set: {err}") from err
            if datasets[0].dtype.names is None and datasets[0].dtype.kind != "c":
                raise UVH5FormatError(
                    f"{meta.path}: visdata has data type {datasets[0].dtype}, not complex"
                )
            # Map every baseline-time row onto (selected antenna, file time index).
            tpos = np.searchsorted(meta.times, times)
            tclip = np.clip(tpos, 0, meta.times.size - 1)
            tvalid = np.isclose(meta.times[tclip], times, rtol=0, atol=1e-9)
            order = np.argsort(ants)
            sorted_ants = np.asarray(ants)[order]
            k = np.clip(np.searchsorted(sorted_ants, ant1), 0, nant - 1)
            ia_all = np.where((sorted_ants[k] == ant1) & (ant1 == ant2) & tvalid, order[k], -1)
            wrows = np.flatnonzero(ia_all >= 0)
            wrows = wrows[np.argsort(tclip[wrows], kind="stable")]
            wtimes = tclip[wrows]
            # flags and nsamples of raw files repeat chunk for chunk: decode each once
            repeats = [None] + [
                _RepeatedChunks(d) if decode_repeats_once else None for d in datasets[1:]
            ]

            def read(iblock: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
                """Stage 1: the block's rows of the three data sets, as stored (HDF5)."""
                nonlocal counted
                t0, t1 = blocks[iblock]
                lo, hi = np.searchsorted(wtimes, [t0, t1])
                rows = np.sort(wrows[lo:hi])
                arrays: dict[str, np.ndarray] = {}
                if rows.size:
                    bufs = None if raw_sets is None else raw_sets[iblock % 2]
                    keys = ("data", "flags", "nsamples")
                    for key, dset, rep in zip(keys, datasets, repeats, strict=True):
                        try:
                            arrays[key] = _read_rows(
                                dset, rows, slice(c0, c1), slice(p0, p1), stats, bufs, rep
                            )
                        except OSError as err:  # a chunk that does not decode, a short file
                            raise UVH5FormatError(
                                f"{meta.path}: cannot read {dset.name} for integrations "
                                f"{t0}-{t1 - 1} ({err}); the file is corrupt or truncated: "
                                "copy it again from the archive, or leave it out"
                            ) from err
                stats.bytes_read += raw.nread - counted
                counted = raw.nread
                return arrays, rows

            def convert(
                iblock: int, stored: tuple[dict[str, np.ndarray], np.ndarray]
            ) -> Observation:
                """Stage 2: the (Nant, Npol, Ntime, Nfreq) block as a checked Observation."""
                arrays, rows = stored
                t0, t1 = blocks[iblock]
                nt = t1 - t0
                shape = (nant, npol, nt, nfreq)
                ia, it = ia_all[rows], tclip[rows] - t0
                # Time-major rows in the selection's antenna order: a reshape, no scatter.
                regular = (
                    rows.size == nant * nt
                    and np.array_equal(ia, np.tile(np.arange(nant), nt))
                    and np.array_equal(it, np.repeat(np.arange(nt), nant))
                )
                dtypes = {"data": np.float64, "flags": bool, "nsamples": np.float64}
                if block_sets is None:
                    block = {key: np.empty(shape, dt) for key, dt in dtypes.items()}
                else:
                    bufs = block_sets[iblock % 2]
                    block = {key: bufs.get(key, shape, dt) for key, dt in dtypes.items()}
                if not regular:
                    for key, fill in (("data", np.nan), ("flags", True), ("nsamples", 0.0)):
                        block[key].fill(fill)
                for key, arr in arrays.items():
                    if not fidx_all:
                        arr = arr[:, fidx]
                    if not pidx_all:
                        arr = arr[:, :, pidx]
                    if arr.dtype.kind == "c":
                        arr = _auto_power(arr, same_feed)
                    if regular:
                        block[key][...] = arr.reshape(nt, nant, nfreq, npol).transpose(1, 3, 0, 2)
                    else:
                        block[key][ia, :, it, :] = arr.transpose(0, 2, 1)
                tint = np.full(nt, np.nan)
                tint[it] = tint_blt[rows]
                if rows.size < nant * nt:
                    logger.warning(
                        "%s: %d antenna-time samples are missing; they are flagged",
                        meta.name,
                        nant * nt - rows.size,
                    )
                if np.any(np.isnan(tint)):
                    fallback = float(np.nanmedian(tint)) if np.any(np.isfinite(tint)) else 0.0
                    tint = np.where(np.isnan(tint), fallback, tint)
                stats.blocks += 1
                stats.integrations += nt
                stats.samples += block["data"].size
                return Observation(
                    **block,
                    **common,
                    lsts=meta.lsts[t0:t1],
                    jds=meta.times[t0:t1],
                    integration_time=tint,
                    meta={**file_meta, "block": iblock, "nblocks": len(blocks)},
                )

            if checksum:
                stats.checksum_bytes += meta.path.stat().st_size
            yield from _run_blocks(
                read, convert, len(blocks), meta.path if checksum else None, prefetch
            )
    finally:
        stats.bytes_read += raw.nread - counted
        stats.files += 1
        raw.close()


def _run_blocks(
    read: Callable[[int], Any],
    convert: Callable[[int, Any], Observation],
    nblocks: int,
    checksum_of: Path | None,
    prefetch: bool,
) -> Iterator[Observation]:
    """Yield ``convert(i, read(i))`` for every block ``i`` in order.

    With ``prefetch`` the two stages run in their own threads, pipelined: while the
    caller uses block ``i``, block ``i + 1`` is converted and block ``i + 2`` read (HDF5
    and numpy release the GIL). Each stage's buffers alternate between two sets, and a
    set is handed back only when the block that used it is done: ``read(i + 2)`` starts
    once ``convert(i)`` has finished, ``convert(i + 2)`` once the caller has asked for
    block ``i + 1``. With ``checksum_of`` the file's SHA-256 is computed in a third
    thread and added to every block's ``meta["sha256"]``.
    """
    sha: dict[str, str] = {}
    if not prefetch:
        if checksum_of is not None:
            sha[str(checksum_of)] = file_checksum(checksum_of)
        for i in range(nblocks):
            obs = convert(i, read(i))
            if sha:
                obs.meta["sha256"] = dict(sha)
            yield obs
        return
    readers = ThreadPoolExecutor(1, thread_name_prefix="autocal-uvh5-read")
    converters = ThreadPoolExecutor(1, thread_name_prefix="autocal-uvh5-convert")
    digester = ThreadPoolExecutor(1, thread_name_prefix="autocal-uvh5-sha256")
    digest = None if checksum_of is None else digester.submit(file_checksum, checksum_of)
    reads: dict[int, Future] = {}
    converts: dict[int, Future] = {}

    def start_read(i: int) -> None:
        if i < nblocks:
            reads[i] = readers.submit(read, i)

    def start_convert(i: int) -> None:
        if i < nblocks:
            converts[i] = converters.submit(lambda: convert(i, reads.pop(i).result()))

    try:
        for i in (0, 1):
            start_read(i)
            start_convert(i)
        for i in range(nblocks):
            obs = converts.pop(i).result()
            start_read(i + 2)  # convert(i) is done with raw set i % 2
            if digest is not None:
                sha[str(checksum_of)] = digest.result()
                digest = None
            if sha:
                obs.meta["sha256"] = dict(sha)
            yield obs
            del obs
            start_convert(i + 2)  # the caller is done with block i (set i % 2)
    finally:
        # an early close (or an error) waits for the blocks in flight, never leaves them
        for future in [*reads.values(), *converts.values(), digest]:
            if future is not None:
                future.cancel()
        for pool in (readers, converters, digester):
            pool.shutdown(wait=True)
