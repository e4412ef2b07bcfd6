"""Writing an autocal solution's gains as calh5 or calfits files.

:func:`write_calh5` and :func:`write_calfits` write the ``UVCal`` that
:func:`autocal.io.calsol_uvcal.solution_to_uvcal` builds (gains ``|g| = sqrt(G)``,
``gain_convention="divide"``, ``gain_scale="K str"``, ``pol_convention="avg"``, the time model
at every fitted integration; see that module for what the file
holds). calfits is written by pyuvdata; calh5 has pyuvdata's header and datasets, its
arrays written an antenna at a time as deflate chunks compressed on threads
(:func:`_write_calh5_file`). Files are written
atomically (temporary file in the same folder, then rename) and existing files are replaced
only with ``overwrite=True``.
"""

from __future__ import annotations

import logging
import threading
import zlib
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from autocal.core.files import atomic_path
from autocal.io.calsol_files import CalsolFormatError
from autocal.io.calsol_uvcal import solution_to_uvcal
from autocal.io.pyuvdata_helpers import warnings_to_log

if TYPE_CHECKING:
    from autocal.fit.solution import Solution

logger = logging.getLogger(__name__)

#: Largest calh5 chunk (bytes) of one antenna's channels x integrations x feeds.
MAX_CHUNK_BYTES = 8 << 20

#: An integer or complex type as wide as a (channel, integration)'s feeds, by bytes.
_WIDE = {2: np.int16, 4: np.int32, 8: np.int64, 16: np.complex128}


def _antenna_chunks(shape: tuple[int, ...], itemsize: int) -> tuple[int, ...]:
    """Chunk shape of a calh5's ``(antenna, channel, integration, feed)`` array.

    One antenna's whole spectra and integrations, cut in time to keep a chunk under
    :data:`MAX_CHUNK_BYTES` (but never below one integration): how the files are read, an
    antenna at a time. pyuvdata's ``chunks=True`` lets h5py guess ~30 kB chunks, ~200 000
    of them for a 350-antenna HERA file, and compressing the qualities and flags through
    them took ~13 s of the calh5's ~18 s (``benchmarks/README.md``).
    """
    _, nfreq, ntime, njones = shape
    ntimes = max(1, min(ntime, MAX_CHUNK_BYTES // max(1, nfreq * njones * itemsize)))
    return (1, nfreq, ntimes, njones)


def _fill(out: np.ndarray, src: np.ndarray) -> np.ndarray:
    """Copy one antenna's ``(channel, integration, feed)`` values into ``out``.

    A time-constant solution's arrays are views with a zero time stride; numpy copies
    them two feeds at a time (3.5 s for a HERA file's gains). Seen as one wide item per
    (channel, integration), the copy is a fill along time (0.4 s).
    """
    wide = _WIDE.get(out.shape[-1] * out.itemsize)
    if wide is not None and src.dtype == out.dtype and src.strides[-1] == src.itemsize:
        np.copyto(out.view(wide), src.view(wide))
    else:
        np.copyto(out, src, casting="same_kind")
    return out


def _write_calh5_file(uvc: Any, path: Path) -> None:
    """Write ``uvc`` as a calh5 file, one antenna at a time, deflated on threads.

    The header is pyuvdata's own (``CalH5._write_header``, as ``UVCal.write_calh5`` writes
    it), and so are the datasets' names and types. The gains, flags and qualities are
    written an antenna at a time from the solution's arrays, so a time-constant
    solution's are never materialised whole (pyuvdata's writer made contiguous copies of
    the 1.65 GB of gains of a HERA file), as deflate (gzip) chunks of one antenna each,
    compressed on the process's threads (:func:`_deflated_chunks`) and stored with
    ``write_direct_chunk``: any HDF5 reader decodes them without a plugin. The file reads
    back equal to the one ``UVCal.write_calh5`` writes (``tests/io/test_calsol_write.py``).
    """
    calh5 = uvc._convert_to_filetype("calh5")
    arrays = {"gains": (uvc.gain_array, uvc.gain_array.dtype), "flags": (uvc.flag_array, bool)}
    if uvc.quality_array is not None:
        arrays["qualities"] = (uvc.quality_array, np.float32)
    with h5py.File(path, "w") as f:
        calh5._write_header(f.create_group("Header"))
        data = f.create_group("Data")
        for name, (src, dtype) in arrays.items():
            chunks = _antenna_chunks(src.shape, np.dtype(dtype).itemsize)
            dset = data.create_dataset(
                name,
                shape=src.shape,
                dtype=dtype,
                chunks=chunks,
                compression="gzip",
                compression_opts=DEFLATE_LEVEL,
            )
            for offset, stored in _deflated_chunks(src, np.dtype(dtype), chunks):
                dset.id.write_direct_chunk(offset, stored)
        if uvc.total_quality_array is not None:
            data.create_dataset(
                "total_qualities",
                data=np.asarray(uvc.total_quality_array, dtype=np.float32),
                chunks=True,
                compression="lzf",
            )


#: The gzip level declared for the calh5's deflated data sets (what HDF5 would use to
#: rewrite a chunk); the chunks autocal stores are ISA-L's fastest level (level 0), which
#: compresses a constant model's per-time gains ~75x.
DEFLATE_LEVEL = 1

#: Antennas compressed per round of the threads (bounds the compressed bytes held).
_ANTENNAS_PER_ROUND = 32


def _deflated_chunks(
    src: np.ndarray, dtype: np.dtype, chunks: tuple[int, ...]
) -> Iterator[tuple[tuple[int, ...], bytes]]:
    """Yield ``(offset, zlib stream)`` of every chunk of ``src`` as ``dtype``, in order.

    Each antenna's values are copied into a per-thread buffer (:func:`_fill`), cut into
    its chunks along time (the last one padded, as HDF5 stores edge chunks) and deflated
    with ISA-L (``zlib`` without it), antennas side by side on the process's threads.
    """
    from autocal.fit.sums import default_threads

    try:
        from isal import isal_zlib

        def deflate(raw: np.ndarray) -> bytes:
            return isal_zlib.compress(raw, 0)
    except ImportError:  # pragma: no cover - isal is a dependency

        def deflate(raw: np.ndarray) -> bytes:
            return zlib.compress(raw, DEFLATE_LEVEL)

    nant, _, ntime, _ = src.shape
    step = chunks[2]
    local = threading.local()

    def one_antenna(ant: int) -> list[tuple[tuple[int, ...], bytes]]:
        buffer = getattr(local, "buffer", None)
        if buffer is None or buffer.shape != src.shape[1:] or buffer.dtype != dtype:
            buffer = local.buffer = np.empty(src.shape[1:], dtype)
        _fill(buffer, src[ant])
        out = []
        for t0 in range(0, ntime, step):
            part = buffer[:, t0 : t0 + step]
            if part.shape[1] < step:  # the edge chunk, padded to a whole chunk
                whole = np.zeros((buffer.shape[0], step, buffer.shape[2]), dtype)
                whole[:, : part.shape[1]] = part
                part = whole
            out.append(((ant, 0, t0, 0), deflate(np.ascontiguousarray(part))))
        return out

    with ThreadPoolExecutor(max(1, default_threads())) as pool:
        for first in range(0, nant, _ANTENNAS_PER_ROUND):
            ants = range(first, min(nant, first + _ANTENNAS_PER_ROUND))
            for done in pool.map(one_antenna, ants):
                yield from done


def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.DEBUG)


def _write(
    solution: Solution, path: str | Path, file_type: str, overwrite: bool, **kwargs: Any
) -> Path:
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    uvc = solution_to_uvcal(solution, shared_times=True, **kwargs)
    with atomic_path(path) as tmp, _warnings_to_log(f"writing {path.name}"):
        tmp.unlink()  # the writers make a new file
        try:
            if file_type == "calh5":
                _write_calh5_file(uvc, tmp)
            else:
                uvc.write_calfits(str(tmp))
        except ValueError as err:
            raise CalsolFormatError(f"cannot write {path} as {file_type}: {err}") from err
    logger.info(
        "wrote %s (%s): %d antennas, pols %s, %d channels, %d time(s)",
        path,
        file_type,
        uvc.Nants_data,
        ",".join(solution.pols),
        uvc.Nfreqs,
        uvc.Ntimes,
    )
    return path


def write_calh5(
    solution: Solution,
    path: str | Path,
    *,
    overwrite: bool = False,
    time_range: tuple[float, float] | None = None,
    per_time: bool | None = None,
    telescope: str | None = None,
    site: Any = None,
    history: str = "",
) -> Path:
    """Write a solution's gains ``|g| = sqrt(G)`` as a calh5 file (atomically).

    Parameters
    ----------
    solution
        An :class:`autocal.fit.solution.Solution`.
    path
        Output file.
    overwrite
        Replace an existing file.
    time_range, per_time, telescope, site, history
        See :func:`~autocal.io.calsol_uvcal.solution_to_uvcal`.

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.
    CalsolFormatError
        If the solution cannot be written.
    """
    return _write(
        solution,
        path,
        "calh5",
        overwrite,
        time_range=time_range,
        per_time=per_time,
        telescope=telescope,
        site=site,
        history=history,
    )


def write_calfits(
    solution: Solution,
    path: str | Path,
    *,
    overwrite: bool = False,
    time_range: tuple[float, float] | None = None,
    per_time: bool | None = None,
    telescope: str | None = None,
    site: Any = None,
    history: str = "",
) -> Path:
    """Write a solution's gains ``|g| = sqrt(G)`` as a calfits file (atomically).

    calfits needs uniformly spaced channels. Parameters, return value and errors as
    :func:`write_calh5`.
    """
    return _write(
        solution,
        path,
        "calfits",
        overwrite,
        time_range=time_range,
        per_time=per_time,
        telescope=telescope,
        site=site,
        history=history,
    )
