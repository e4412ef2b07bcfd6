"""Auto-correlations of one UVH5 file read block by block, in bounded memory.

:func:`iter_uvh5_blocks` slices the file's data sets with h5py along the baseline-time
axis and yields :class:`autocal.core.observation.Observation` blocks of consecutive
integrations, so a HERA file of 350 antennas x 1536 channels x 192 integrations (1.65 GB as
complex64) never sits in memory whole. Reading is a two-stage pipeline in background
threads (HDF5 reads and decompression; conversion to the ``(Nant, Npol, Ntime, Nfreq)``
layout and the observation checks) running ahead of the caller, with the file's SHA-256
computed alongside; chunks of flags and nsamples that are stored identically (raw files:
no flags, uniform nsamples) are decoded once. The HDF5 reading itself (rows, buffers,
repeated chunks, :class:`~autocal.io.uvh5_chunks.ReadStats`) is
:mod:`autocal.io.uvh5_chunks`; headers and selections are :mod:`autocal.io.uvh5_meta`;
whole-file reads are :mod:`autocal.io.uvh5`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal.core.files import file_checksum
from autocal.core.observation import Observation
from autocal.errors import AutocalError
from autocal.io.uvh5_chunks import (
    Buffers,
    CountingFile,
    ReadStats,
    RepeatedChunks,
    one_value,
    read_rows,
)
from autocal.io.uvh5_inflate import InflatingReader
from autocal.io.uvh5_integrity import data_set_integrity, log_unchecked, read_error
from autocal.io.uvh5_meta import (
    FileMeta,
    UVH5File,
    UVH5FormatError,
    antenna_names,
    file_meta_of,
    lst_mask,
    select_antennas,
    select_channels,
    select_pols,
)

logger = logging.getLogger(__name__)

#: Default largest number of values (antennas x pols x integrations x channels) in one
#: block of :func:`iter_uvh5_blocks`: 2**23 = 8.4 M values, i.e. 67 MB as float64.
BLOCK_SAMPLES = 1 << 23

#: Polarisation codes whose autos are real powers (pyuvdata makes them real with abs()).
SAME_FEED_POL_CODES = (-1, -2, -5, -6, 1, 2, 3, 4)


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


def iter_uvh5_blocks(
    file: UVH5File | FileMeta | str | Path,
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
    inflate: bool = True,
) -> Iterator[Observation]:
    """Yield the autos of one UVH5 file in blocks of consecutive integrations.

    The data sets are sliced with h5py along the baseline-time axis, so memory is
    bounded by the block, not by the file (a HERA file of 350 antennas x 1536 channels
    x 192 integrations is 1.65 GB as complex64). Selections are those of
    :func:`~autocal.io.uvh5.read_uvh5`; the values equal what it returns for the same
    integrations.

    Parameters
    ----------
    file
        A :class:`~autocal.io.uvh5_meta.UVH5File` from
        :func:`~autocal.io.uvh5_meta.scan_uvh5` (its header is reused) or a path.
    antennas, pols, freq_range, lst_range
        As for :func:`~autocal.io.uvh5.read_uvh5`.
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
        repeats (:class:`~autocal.io.uvh5_chunks.RepeatedChunks`; on raw files a third
        of the HDF5 time). The values are the same; ``False`` decodes every chunk.
    inflate
        Inflate the chunks of shuffle/deflate (gzip) data sets on the process's threads
        outside HDF5 (:class:`~autocal.io.uvh5_inflate.InflatingReader`: HDF5 decodes on
        one core); ``False`` leaves every chunk to HDF5. The values are the same.

    Yields
    ------
    Observation
        One block: ``meta`` has ``source``, ``files``, ``sha256``, ``block`` and
        ``nblocks``, ``x_orientation``, ``vis_units``. A block whose stored ``nsamples``
        all have the same bits (raw HERA files) has them as that one value broadcast (a
        read-only array with zero strides), not a block-sized array.

    Raises
    ------
    UVH5FormatError, ObservationError
        As :func:`~autocal.io.uvh5.read_uvh5`; ``ValueError`` for a block size below 1.
    """
    meta = file_meta_of(file)
    stats = stats if stats is not None else ReadStats()
    ants = select_antennas(meta, antennas)
    pol_idx = select_pols(meta, pols)
    chans = select_channels(meta, freq_range)
    kept = np.flatnonzero(lst_mask(meta.lsts, lst_range))
    if kept.size == 0:
        return
    nant, npol, nfreq = len(ants), len(pol_idx), chans.size
    if block_size is None:
        block_size = max(1, int(max_block_samples) // (nant * npol * nfreq))
    if int(block_size) < 1:
        raise AutocalError(f"block_size must be at least 1 integration, got {block_size}")
    blocks = _time_blocks(kept, int(block_size))

    reader = _BlockReader(meta, blocks, ants, pol_idx, chans, stats, reuse_buffers)
    raw = CountingFile(meta.path)
    try:
        with h5py.File(raw, "r") as h5:
            reader.open(h5, raw, decode_repeats_once, inflate)
            if checksum:
                stats.checksum_bytes += meta.path.stat().st_size
            yield from _run_blocks(
                reader.read, reader.convert, len(blocks), meta.path if checksum else None, prefetch
            )
    finally:
        stats.bytes_read += raw.nread - reader.counted
        stats.files += 1
        raw.close()


class _BlockReader:
    """The two stages of :func:`iter_uvh5_blocks` for one file's selection.

    :meth:`read` reads a block's rows of the three data sets as stored (HDF5) and
    :meth:`convert` turns them into the ``(Nant, Npol, Ntime, Nfreq)`` block as a checked
    :class:`Observation`; :func:`_run_blocks` runs them, pipelined, in threads. With
    ``reuse_buffers`` each stage decodes into two sets of arrays used alternately.
    """

    def __init__(
        self,
        meta: FileMeta,
        blocks: list[tuple[int, int]],
        ants: list[int],
        pol_idx: list[int],
        chans: np.ndarray,
        stats: ReadStats,
        reuse_buffers: bool,
    ) -> None:
        self.meta, self.blocks, self.ants, self.stats = meta, blocks, ants, stats
        self.shape = (len(ants), len(pol_idx), chans.size)
        self.common: dict[str, Any] = {
            "freqs": meta.freqs[chans],
            "antennas": np.array(ants),
            "pols": tuple(meta.pol_names[i] for i in pol_idx),
            "site": meta.header.site,
            "channel_width": meta.channel_width[chans],
            "antenna_names": antenna_names(meta, ants),
            "telescope_name": meta.header.telescope_name,
        }
        self.file_meta: dict[str, Any] = {
            "source": "uvh5",
            "files": [str(meta.path)],
            "x_orientation": meta.x_orientation,
            "vis_units": meta.header.vis_units,
        }
        c0, c1 = int(chans.min()), int(chans.max()) + 1
        self.chans = slice(c0, c1)
        self.fidx = chans - c0
        self.fidx_all = bool(np.array_equal(self.fidx, np.arange(c1 - c0)))
        p0, p1 = min(pol_idx), max(pol_idx) + 1
        self.pols = slice(p0, p1)
        self.pidx = np.asarray(pol_idx) - p0
        self.pidx_all = bool(np.array_equal(self.pidx, np.arange(p1 - p0)))
        self.same_feed = np.array([meta.pol_codes[i] in SAME_FEED_POL_CODES for i in pol_idx])
        self.block_sets = (Buffers(), Buffers()) if reuse_buffers else None
        self.raw_sets = (Buffers(), Buffers()) if reuse_buffers else None
        self.counted = 0  # bytes of the file counted into stats.bytes_read so far

    def open(
        self, h5: Any, raw: CountingFile, decode_repeats_once: bool, inflate: bool = True
    ) -> None:
        """Read the header's per-row arrays and map every row onto (antenna, time)."""
        meta = self.meta
        self.raw = raw
        try:
            header = h5["Header"]
            ant1 = np.asarray(header["ant_1_array"][()])
            ant2 = np.asarray(header["ant_2_array"][()])
            times = np.asarray(header["time_array"][()], np.float64)
            self.tint_blt = np.broadcast_to(
                np.asarray(header["integration_time"][()], np.float64), times.shape
            )
            self.datasets = [h5["Data/visdata"], h5["Data/flags"], h5["Data/nsamples"]]
        except KeyError as err:
            raise UVH5FormatError(f"{meta.path} lacks a UVH5 data set: {err}") from err
        log_unchecked(meta.path, data_set_integrity(h5))
        if self.datasets[0].dtype.names is None and self.datasets[0].dtype.kind != "c":
            raise UVH5FormatError(
                f"{meta.path}: visdata has data type {self.datasets[0].dtype}, not complex"
            )
        # Map every baseline-time row onto (selected antenna, file time index).
        nant = self.shape[0]
        tpos = np.searchsorted(meta.times, times)
        self.tclip = np.clip(tpos, 0, meta.times.size - 1)
        tvalid = np.isclose(meta.times[self.tclip], times, rtol=0, atol=1e-9)
        order = np.argsort(self.ants)
        sorted_ants = np.asarray(self.ants)[order]
        k = np.clip(np.searchsorted(sorted_ants, ant1), 0, nant - 1)
        self.ia_all = np.where((sorted_ants[k] == ant1) & (ant1 == ant2) & tvalid, order[k], -1)
        wrows = np.flatnonzero(self.ia_all >= 0)
        self.wrows = wrows[np.argsort(self.tclip[wrows], kind="stable")]
        self.wtimes = self.tclip[self.wrows]
        # flags and nsamples of raw files repeat chunk for chunk: decode each once
        self.repeats = [None] + [
            RepeatedChunks(d) if decode_repeats_once else None for d in self.datasets[1:]
        ]
        # gzip chunks inflated on threads, not by HDF5 on one core
        self.inflaters = [InflatingReader(d) if inflate else None for d in self.datasets]

    def read(self, iblock: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Stage 1: the block's rows of the three data sets, as stored (HDF5)."""
        t0, t1 = self.blocks[iblock]
        lo, hi = np.searchsorted(self.wtimes, [t0, t1])
        rows = np.sort(self.wrows[lo:hi])
        arrays: dict[str, np.ndarray] = {}
        if rows.size:
            bufs = None if self.raw_sets is None else self.raw_sets[iblock % 2]
            keys = ("data", "flags", "nsamples")
            sets = zip(keys, self.datasets, self.repeats, self.inflaters, strict=True)
            for key, dset, rep, inflater in sets:
                try:
                    arrays[key] = read_rows(
                        dset, rows, self.chans, self.pols, self.stats, bufs, rep, inflater
                    )
                except (OSError, RuntimeError) as err:  # a bad chunk: checksum, decoding, short
                    what = f"integrations {t0}-{t1 - 1}"
                    raise read_error(self.meta.path, dset, what, err) from err
        self.stats.bytes_read += self.raw.nread - self.counted
        self.counted = self.raw.nread
        return arrays, rows

    def _power_into(self, values: np.ndarray, out: np.ndarray) -> bool:
        """Write a regular block's complex64 power into ``out`` in one compiled pass.

        :func:`autocal.io.power_kernel.auto_power_into`; ``False`` (nothing to rely on in
        ``out``) for other data types or when a same-feed value has an imaginary part:
        :func:`_auto_power` does those.
        """
        if values.dtype != np.complex64 or not values.flags.c_contiguous:
            return False
        from autocal.io.power_kernel import auto_power_into  # numba

        return auto_power_into(values, out, self.fidx, self.pidx, self.same_feed)

    def convert(self, iblock: int, stored: tuple[dict[str, np.ndarray], np.ndarray]) -> Observation:
        """Stage 2: the (Nant, Npol, Ntime, Nfreq) block as a checked Observation."""
        arrays, rows = stored
        t0, t1 = self.blocks[iblock]
        nt = t1 - t0
        nant, npol, nfreq = self.shape
        shape = (nant, npol, nt, nfreq)
        ia, it = self.ia_all[rows], self.tclip[rows] - t0
        # Time-major rows in the selection's antenna order: a reshape, no scatter.
        regular = (
            rows.size == nant * nt
            and np.array_equal(ia, np.tile(np.arange(nant), nt))
            and np.array_equal(it, np.repeat(np.arange(nt), nant))
        )
        dtypes = {"data": np.float64, "flags": bool, "nsamples": np.float64}
        uniform = _uniform(arrays.get("nsamples")) if regular else None
        if uniform is not None:  # HERA's: one number, not a block-sized float64 array
            arrays = {k: v for k, v in arrays.items() if k != "nsamples"}
            del dtypes["nsamples"]
        if self.block_sets is None:
            block = {key: np.empty(shape, dt) for key, dt in dtypes.items()}
        else:
            bufs = self.block_sets[iblock % 2]
            block = {key: bufs.get(key, shape, dt) for key, dt in dtypes.items()}
        if not regular:
            for key, fill in (("data", np.nan), ("flags", True), ("nsamples", 0.0)):
                block[key].fill(fill)
        for key, arr in arrays.items():
            if key == "data" and regular and self._power_into(arr, block["data"]):
                continue
            if not self.fidx_all:
                arr = arr[:, self.fidx]
            if not self.pidx_all:
                arr = arr[:, :, self.pidx]
            if arr.dtype.kind != "c" and arr.size and not any(arr.strides):
                value = arr.flat[0]  # one value (repeated chunks): a fill, no copy
                if regular:
                    block[key].fill(value)
                else:
                    block[key][ia, :, it, :] = value
                continue
            if arr.dtype.kind == "c":
                arr = _auto_power(arr, self.same_feed)
            if regular:
                block[key][...] = arr.reshape(nt, nant, nfreq, npol).transpose(1, 3, 0, 2)
            else:
                block[key][ia, :, it, :] = arr.transpose(0, 2, 1)
        tint = np.full(nt, np.nan)
        tint[it] = self.tint_blt[rows]
        if rows.size < nant * nt:
            logger.warning(
                "%s: %d antenna-time samples are missing; they are flagged",
                self.meta.name,
                nant * nt - rows.size,
            )
        if np.any(np.isnan(tint)):
            fallback = float(np.nanmedian(tint)) if np.any(np.isfinite(tint)) else 0.0
            tint = np.where(np.isnan(tint), fallback, tint)
        self.stats.blocks += 1
        self.stats.integrations += nt
        self.stats.samples += block["data"].size
        if uniform is not None:
            block["nsamples"] = uniform  # type: ignore[assignment]
        return Observation(
            **block,
            **self.common,
            lsts=self.meta.lsts[t0:t1],
            jds=self.meta.times[t0:t1],
            integration_time=tint,
            meta={**self.file_meta, "block": iblock, "nblocks": len(self.blocks)},
        )


def _uniform(values: np.ndarray | None) -> float | None:
    """Return the one value of ``values`` when all have the same bits, else ``None``.

    A broadcast (zero strides) is one value; otherwise :func:`~autocal.io.uvh5_chunks.one_value`
    (``-0.0`` among zeros, or NaNs of other payloads, are not one value).
    """
    if values is None or not values.size or values.dtype.kind != "f":
        return None
    if not any(values.strides):  # one value broadcast (repeated chunks)
        return float(values.flat[0])
    one = one_value(values)
    return None if one is None else float(one)


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
