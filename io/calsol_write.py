"""Writing an autocal solution's gains as calh5 or calfits files.

:func:`write_calh5` and :func:`write_calfits` write the ``UVCal`` that
:func:`autocal.io.calsol_uvcal.solution_to_uvcal` builds (gains ``|g| = sqrt(G)``,
``gain_convention="divide"``, ``gain_scale="K str"``, ``pol_convention="avg"``, the time model
at every fitted integration; see that module for what the file
holds). calfits is written by pyuvdata; calh5 has pyuvdata's header and datasets, its
arrays written an antenna at a time (:func:`_write_calh5_file`). Files are written
atomically (temporary file in the same folder, then rename) and existing files are replaced
only with ``overwrite=True``.
"""

from __future__ import annotations

import logging
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
    antenna at a time. pyuvdata's
    ``chunks=True`` lets h5py guess ~30 kB chunks, ~200 000 of them for a 350-antenna HERA
    file, and compressing the qualities and flags through them took ~13 s of the calh5's
    ~18 s (``benchmarks/README.md``).
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
    """Write ``uvc`` as a calh5 file, one antenna at a time.

    The header is pyuvdata's own (``CalH5._write_header``, as ``UVCal.write_calh5`` writes
    it), and so are the datasets' names, types and filters (gains uncompressed, flags and
    qualities LZF); the arrays are written an antenna at a time from the solution's
    arrays, so a time-constant solution's are never materialised whole (pyuvdata's
    writer made contiguous copies of the 1.65 GB of gains of a HERA file). The file reads
    back equal to the one ``UVCal.write_calh5`` writes (``tests/io/test_calsol_write.py``).
    """
    calh5 = uvc._convert_to_filetype("calh5")
    arrays = {
        "gains": (uvc.gain_array, uvc.gain_array.dtype, None),
        "flags": (uvc.flag_array, np.dtype(bool), "lzf"),
    }
    if uvc.quality_array is not None:
        arrays["qualities"] = (uvc.quality_array, np.dtype(np.float32), "lzf")
    with h5py.File(path, "w") as f:
        calh5._write_header(f.create_group("Header"))
        data = f.create_group("Data")
        for name, (src, dtype, compression) in arrays.items():
            dset = data.create_dataset(
                name,
                shape=src.shape,
                dtype=dtype,
                chunks=_antenna_chunks(src.shape, dtype.itemsize),
                compression=compression,
            )
            buffer = np.empty(src.shape[1:], dtype)
            for ant in range(src.shape[0]):
                dset.write_direct(_fill(buffer, src[ant]), dest_sel=np.s_[ant])
        if uvc.total_quality_array is not None:
            data.create_dataset(
                "total_qualities",
                data=np.asarray(uvc.total_quality_array, dtype=np.float32),
                chunks=True,
                compression="lzf",
            )


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
