"""Auto-correlations in UVH5 files, read and written whole through pyuvdata.

:func:`read_uvh5` loads only the auto-correlations ``(a, a)`` of one UVH5 file, or of
several consecutive files forming one observation, into an
:class:`autocal.core.observation.Observation`; :func:`iter_uvh5` yields it file by file
(or block by block). :func:`write_uvh5` writes an observation's autos as a genuine UVH5
file (HERA telescope metadata when the telescope is HERA) that pyuvdata, hera_cal and
friends can read.

Conventions
-----------
* Polarisations are named ``ee``/``nn`` (``ee`` = east-west dipole) when the file's
  ``x_orientation`` is known: pyuvdata codes -5/-6 with ``x_orientation="east"``.
  Files with no orientation keep ``xx``/``yy``.
* LSTs are local apparent sidereal times in hours; JDs are UTC Julian dates.
* The data are written as complex128 with zero imaginary part, phase centre "zenith"
  (unprojected, i.e. drift scan), ``vis_units="uncalib"``.

Files named ``*.uvh5_downselected`` (hera_cal test data) are read too: the file type
is always given to pyuvdata explicitly. The other UVH5 modules: headers, the file scan
and selections (:mod:`autocal.io.uvh5_meta`); the UVData the writers build
(:mod:`autocal.io.uvh5_uvdata`); a file written in parts
(:mod:`autocal.io.uvh5_writer`); a file read block by block in bounded memory, as the
calibration pipeline does (:mod:`autocal.io.uvh5_blocks`, :mod:`autocal.io.uvh5_chunks`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.files import atomic_path, file_checksum
from autocal.core.observation import Observation, ObservationError
from autocal.io.pyuvdata_helpers import uvdata_class, warnings_to_log
from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_chunks import ReadStats
from autocal.io.uvh5_integrity import DataIntegrityError, file_integrity
from autocal.io.uvh5_meta import (
    FileMeta,
    UVH5FormatError,
    antenna_names,
    keyword_scalar,
    lst_mask,
    scan_files,
    select_antennas,
    select_channels,
    select_pols,
)
from autocal.io.uvh5_uvdata import build_uvdata, file_history, header_keywords

logger = logging.getLogger(__name__)


def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.INFO)


def write_uvh5(
    obs: Observation,
    path: str | Path,
    *,
    history: str = "",
    extra_keywords: dict | None = None,
    overwrite: bool = False,
) -> Path:
    """Write an observation's auto-correlations as a UVH5 file through pyuvdata.

    The file holds the baselines ``(a, a)`` for every antenna, the observation's
    polarisations, times (``obs.jds``), channels, channel widths, integration times,
    flags and sample counts; the data are complex with zero imaginary part. When
    ``obs.telescope_name`` is ``"HERA"`` the telescope metadata (all 350 antennas,
    positions, location) come from pyuvdata's known-telescope table; otherwise the
    telescope is built from ``obs.site`` with the observation's antennas at zero
    positions. pyuvdata computes the LSTs from the times and location; they must agree
    with ``obs.lsts`` to within 1 s.

    Parameters
    ----------
    obs
        The observation. Its ``integration_time`` and ``channel_width`` must be positive.
    path
        Output file.
    history
        Text appended to the file's history (after ``obs.meta["history"]``).
    extra_keywords
        Extra UVH5 header keywords (scalars or strings), added to those derived from
        ``obs.meta`` (its scalar/string entries and its ``extra_keywords``
        entries); non-scalar values are skipped.
    overwrite
        Replace an existing file.

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.
    ObservationError
        If the observation cannot be written faithfully: unknown HERA antenna
        numbers, non-positive integration times or channel widths, polarisation names
        without a UVH5 code, or LSTs inconsistent with the JDs and site.

    Notes
    -----
    The file is written to a temporary file in the same folder and renamed onto
    ``path``, so a failed write leaves no partial file. Non-finite data (which
    :class:`~autocal.core.observation.Observation` always flags) are stored as 0.
    """
    path = Path(path)
    _check_writable(obs, path, overwrite)
    nant, _, ntime, nfreq = obs.shape
    uv = build_uvdata(
        path.name,
        freqs=obs.freqs,
        pols=obs.pols,
        jds=obs.jds,
        lsts=obs.lsts,
        antennas=obs.antennas,
        antenna_names=obs.antenna_names,
        site=obs.site,
        telescope_name=obs.telescope_name,
        integration_time=obs.integration_time,
        channel_width=obs.channel_width,
        history=file_history(obs.meta, history),
        extra_keywords=header_keywords(obs.meta, extra_keywords),
        arrays=_blt_arrays(obs),
    )

    with atomic_path(path) as tmp, _warnings_to_log(f"writing {path.name}"):
        # atomic_path creates the temporary file; remove it so that pyuvdata need not
        # clobber it (pyuvdata prints when it clobbers).
        tmp.unlink()
        uv.write_uvh5(str(tmp))
    logger.info(
        "wrote %s: %d antennas, pols %s, %d times, %d channels",
        path,
        nant,
        ",".join(obs.pols),
        ntime,
        nfreq,
    )
    return path


def _check_writable(obs: Observation, path: Path, overwrite: bool) -> None:
    """Raise unless ``obs`` can be written to ``path`` (see :func:`write_uvh5`)."""
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    if np.any(obs.integration_time <= 0):
        raise ObservationError("integration_time must be positive to write UVH5")
    if np.any(obs.channel_width <= 0):
        raise ObservationError("channel_width must be positive to write UVH5")
    if obs.ntime > 1 and np.any(np.diff(obs.jds) <= 0):
        raise ObservationError("JDs must be strictly increasing to write UVH5")


def _blt_arrays(obs: Observation) -> dict[str, np.ndarray]:
    """Return the data, flags and nsamples of ``obs`` on the (Nblt, Nfreq, Npol) axes."""
    nant, npol, ntime, nfreq = obs.shape

    # Baseline-time axis: time slowest, antennas fastest -> index it * nant + ia.
    def to_blt(arr: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(arr.transpose(2, 0, 3, 1)).reshape(ntime * nant, nfreq, npol)

    real = np.where(np.isfinite(obs.data), obs.data, 0.0)
    return {
        "data_array": to_blt(real).astype(np.complex128),
        "flag_array": to_blt(obs.flags),
        "nsample_array": to_blt(obs.nsamples).astype(np.float64),
    }


def _read_data(
    meta: FileMeta,
    ants: list[int],
    pol_idx: list[int],
    chans: np.ndarray,
    keep_times: np.ndarray,
) -> dict[str, np.ndarray]:
    """Read the selected autos of one file into (Nant, Npol, Ntime, Nfreq) arrays."""
    UVData = uvdata_class()

    codes = [meta.pol_codes[i] for i in pol_idx]
    try:
        with _warnings_to_log(f"reading {meta.name}"):
            uv = UVData.from_file(
                str(meta.path),
                file_type="uvh5",
                bls=[(a, a) for a in ants],
                polarizations=codes,
                freq_chans=None if chans.size == meta.freqs.size else np.sort(chans),
            )
    except Exception as err:
        if isinstance(err, OSError) and file_integrity(meta.path)["status"] != "unchecked":
            raise DataIntegrityError(
                f"{meta.path}: reading its checksummed data failed ({err}); a chunk failed "
                "its HDF5 Fletcher-32 checksum or the file is damaged: copy it again from "
                "the archive, or leave it out"
            ) from err
        raise UVH5FormatError(
            f"pyuvdata failed to read the auto-correlations of {meta.path}: "
            f"{type(err).__name__}: {err}; the file may be corrupt"
        ) from err

    # Map the read object's axes onto the requested order.
    read_freqs = np.asarray(uv.freq_array, dtype=np.float64).ravel()
    fidx = (
        np.searchsorted(read_freqs, meta.freqs[chans])
        if read_freqs.size > 1
        else np.zeros(chans.size, int)
    )
    if not np.allclose(read_freqs[fidx], meta.freqs[chans], rtol=0, atol=1e-3):
        fidx = np.array([int(np.argmin(np.abs(read_freqs - f))) for f in meta.freqs[chans]])
    read_codes = [int(c) for c in np.asarray(uv.polarization_array).ravel()]
    pidx = [read_codes.index(c) for c in codes]

    times = meta.times[keep_times]
    nant, npol, ntime, nfreq = len(ants), len(codes), times.size, chans.size
    data = np.full((nant, npol, ntime, nfreq), np.nan)
    flags = np.ones((nant, npol, ntime, nfreq), bool)
    nsamples = np.zeros((nant, npol, ntime, nfreq))
    tint = np.full(ntime, np.nan)
    filled = np.zeros((nant, ntime), bool)

    ant_pos = {a: i for i, a in enumerate(ants)}
    tpos = np.searchsorted(times, uv.time_array)
    tpos_clipped = np.clip(tpos, 0, max(ntime - 1, 0))
    in_time = (tpos < ntime) & np.isclose(times[tpos_clipped], uv.time_array, rtol=0, atol=1e-9)
    ia = np.array([ant_pos.get(int(a), -1) for a in uv.ant_1_array])
    blts = np.flatnonzero(in_time & (uv.ant_1_array == uv.ant_2_array) & (ia >= 0))
    ia, it = ia[blts], tpos[blts]
    # (Nblt, Nfreq, Npol) -> (Nblt, Npol, Nfreq) in the requested channel/pol order.
    block = np.ix_(blts, fidx, pidx)
    data[ia, :, it, :] = uv.data_array[block].real.transpose(0, 2, 1)
    flags[ia, :, it, :] = uv.flag_array[block].transpose(0, 2, 1)
    nsamples[ia, :, it, :] = uv.nsample_array[block].transpose(0, 2, 1)
    tint[it] = uv.integration_time[blts]
    filled[ia, it] = True
    if not np.all(filled):
        logger.warning(
            "%s: %d antenna-time samples are missing; they are flagged",
            meta.name,
            int(np.sum(~filled)),
        )
    if np.any(np.isnan(tint)):
        fallback = float(np.nanmedian(tint)) if np.any(np.isfinite(tint)) else 0.0
        tint = np.where(np.isnan(tint), fallback, tint)
    imag = float(np.max(np.abs(uv.data_array.imag))) if uv.data_array.size else 0.0
    if imag > 0:
        logger.debug("%s: dropped imaginary parts up to %.3g", meta.name, imag)
    return {
        "data": data,
        "flags": flags,
        "nsamples": nsamples,
        "integration_time": tint,
        "jds": times,
        "lsts": meta.lsts[keep_times],
    }


def _merge_keywords(metas: list[FileMeta]) -> dict[str, Any]:
    """Extra keywords of all files: one value where they agree, a per-file list otherwise."""
    per_file = [
        {
            str(k): (keyword_scalar(v) if keyword_scalar(v) is not None else v)
            for k, v in m.header.extra_keywords.items()
        }
        for m in metas
    ]
    merged: dict[str, Any] = {}
    for key in dict.fromkeys(k for kw in per_file for k in kw):
        values = [kw.get(key) for kw in per_file]
        if all(_same(values[0], v) for v in values[1:]):
            merged[key] = values[0]
        else:
            merged[key] = values
    return merged


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(np.all(np.asarray(a) == np.asarray(b)))
    except (TypeError, ValueError):
        return False


def iter_uvh5(
    paths: str | Path | Sequence[str | Path],
    *,
    antennas: Sequence[int] | None = None,
    pols: Sequence[str] | None = None,
    freq_range: tuple[float, float] | None = None,
    lst_range: tuple[float, float] | None = None,
    block_size: int | None = None,
    stats: ReadStats | None = None,
) -> Iterator[Observation]:
    """Yield the observation file by file (same selections as :func:`read_uvh5`).

    Files with no integration in ``lst_range`` are skipped. Only one file's autos are in
    memory at a time, so a whole night can be streamed into the fit's normal sums.
    With ``block_size`` (integrations; ``0`` = automatic, see :func:`iter_uvh5_blocks`)
    each file is yielded in blocks of integrations, so memory is bounded by the block,
    not the file.
    """
    for meta in scan_files(paths):
        if not np.any(lst_mask(meta.lsts, lst_range)):
            continue
        if block_size is not None:
            yield from iter_uvh5_blocks(
                meta,
                antennas=antennas,
                pols=pols,
                freq_range=freq_range,
                lst_range=lst_range,
                block_size=block_size or None,
                stats=stats,
            )
            continue
        yield read_uvh5(
            [meta.path], antennas=antennas, pols=pols, freq_range=freq_range, lst_range=lst_range
        )


def read_uvh5(
    paths: str | Path | Sequence[str | Path],
    *,
    antennas: Sequence[int] | None = None,
    pols: Sequence[str] | None = None,
    freq_range: tuple[float, float] | None = None,
    lst_range: tuple[float, float] | None = None,
) -> Observation:
    """Read the auto-correlations of UVH5 files into an :class:`Observation`.

    Only the baselines ``(a, a)`` are read from disk (pyuvdata partial read);
    cross-correlations are never loaded. Several files are joined in time order after
    checking that they share frequencies, antennas (with autos), polarisations and
    telescope.

    Parameters
    ----------
    paths
        One file or a list of consecutive files of one observation (any order; they
        are sorted by time). ``*.uvh5_downselected`` names are fine.
    antennas
        Antenna numbers to keep, in this order (default: every antenna with autos).
    pols
        Polarisations to keep, e.g. ``["ee", "nn"]`` (case-insensitive; ``xx``/``yy``
        are accepted as aliases of ``ee``/``nn`` in files whose x dipole points east).
        Default: the feed-power polarisations (ee/nn, or xx/yy when the orientation is
        unknown); cross-feed autos (en/ne) only when asked for, as their real part.
    freq_range
        ``(low, high)`` channel-centre frequencies to keep, in Hz, inclusive.
    lst_range
        ``(start, stop)`` LSTs to keep, in hours, inclusive; ``start > stop`` wraps
        through 24 h.

    Returns
    -------
    Observation
        Data ``(Nant, Npol, Ntime, Nfreq)`` (real part of the autos), flags, nsamples,
        channel widths, integration times, LSTs (hours) and JDs, antenna numbers and
        names, polarisation names, the telescope site (named after the telescope,
        lowercased) and ``meta`` with ``source`` ("uvh5"), ``files`` (absolute paths
        in time order), ``sha256`` (path -> digest), ``history``, ``extra_keywords``
        (one value per keyword, or a per-file list where the files differ),
        ``vis_units`` and ``x_orientation``.

    Raises
    ------
    UVH5FormatError
        If a file is missing, a directory, not HDF5/UVH5, truncated or corrupt, has no
        auto-correlations, or differs from the first file in frequencies, antennas,
        polarisations or telescope; or if files overlap in time.
    ObservationError
        For an unknown antenna or polarisation, or a frequency or LST selection that
        leaves nothing.
    """
    metas = scan_files(paths)
    first = metas[0]
    ants = select_antennas(first, antennas)
    pol_idx = select_pols(first, pols)
    chans = select_channels(first, freq_range)

    pieces = []
    used = []
    for meta in metas:
        keep = lst_mask(meta.lsts, lst_range)
        if not np.any(keep):
            logger.info("%s: no integrations in LST range %s h; skipped", meta.name, lst_range)
            continue
        pieces.append(_read_data(meta, ants, pol_idx, chans, keep))
        used.append(meta)
    if not pieces:
        covered = ", ".join(f"{m.lsts.min():.3f}-{m.lsts.max():.3f}" for m in metas)
        raise ObservationError(
            f"no integrations in LST range {lst_range} h; the files cover LSTs {covered} h"
        )

    def join(key: str, axis: int) -> np.ndarray:
        return np.concatenate([p[key] for p in pieces], axis=axis)

    meta_out = _provenance(first, used)
    obs = Observation(
        data=join("data", 2),
        freqs=first.freqs[chans],
        lsts=join("lsts", 0),
        jds=join("jds", 0),
        antennas=np.array(ants),
        pols=tuple(first.pol_names[i] for i in pol_idx),
        site=first.header.site,
        flags=join("flags", 2),
        channel_width=first.channel_width[chans],
        integration_time=join("integration_time", 0),
        nsamples=join("nsamples", 2),
        antenna_names=antenna_names(first, ants),
        telescope_name=first.header.telescope_name,
        meta=meta_out,
    )
    logger.info(
        "read %d file(s): antennas %s, pols %s, %d times, %d channels",
        len(used),
        ants,
        ",".join(obs.pols),
        obs.ntime,
        obs.nfreq,
    )
    return obs


def _provenance(first: FileMeta, used: list[FileMeta]) -> dict[str, Any]:
    """``meta`` of an observation read from the files ``used`` (``first``: the first scanned).

    One history when the files share it, else each file's under its name; extra keywords
    merged (:func:`_merge_keywords`).
    """
    histories = [m.header.history or "" for m in used]
    if all(h == histories[0] for h in histories):
        history = histories[0]
    else:
        history = "\n".join(
            f"[{m.name}]\n{h.rstrip()}" for m, h in zip(used, histories, strict=True)
        )
    files = [str(m.path) for m in used]
    return {
        "source": "uvh5",
        "files": files,
        "sha256": {f: file_checksum(f) for f in files},
        "history": history,
        "extra_keywords": _merge_keywords(used),
        "vis_units": first.header.vis_units,
        "x_orientation": first.x_orientation,
    }
