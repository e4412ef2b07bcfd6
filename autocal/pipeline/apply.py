"""Applying a calibration solution to visibilities: calibrated UVH5 through pyuvdata.

:func:`apply_solution` reads gains (an autocal ``solution.calh5``/``solution.calfits``, or
any per-channel gain calfits/calh5 pyuvdata reads) and UVH5 visibilities (the autos and
any cross-correlations present), checks that the solution covers the data, calibrates them
with pyuvdata's ``uvcalibrate`` and writes one calibrated UVH5 file.

* Coverage: every antenna of the data must have a solution, every polarisation of the
  data must have both of its feeds among the solution's Jones terms, every channel of the
  data must be a channel of the solution (pyuvdata's frequency tolerance) and, when the
  solution has a ``time_array``, every integration of the data must be one of its times.
  Anything else is an :class:`ApplyError` naming what is missing.
* Calibration: ``V_cal = V / (g_i g_j^*)`` (the solution's ``gain_convention``), flags
  propagated (``prop_flags=True``: a flagged gain flags every visibility it touches).
  With autocal's gains (``gain_scale = "K str"``) the calibrated autos are the
  beam-averaged antenna temperature in kelvin, ``Tsky + Trxr``; pyuvdata labels them
  ``vis_units = "K str"`` (:mod:`autocal.io.calsol_uvcal`), ``pol_convention = "avg"``.
* Provenance: the history gains a line with autocal's version, the solution file and its
  SHA-256, and the data files.
* Output: written atomically (nothing is left behind on failure). An existing output is
  replaced only with ``overwrite=True`` and only if it is a UVH5 file autocal wrote (its
  history holds :data:`HISTORY_MARK`); any other existing file is refused.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from pyuvdata import UVCal, UVData
from pyuvdata import utils as uvutils

from autocal import __version__
from autocal.core.files import atomic_path, file_checksum
from autocal.errors import AutocalError
from autocal.io.calsol_files import sniff_cal_file
from autocal.io.pyuvdata_helpers import warnings_to_log

logger = logging.getLogger(__name__)

#: Marks a UVH5 file written by :func:`apply_solution` (in its history).
HISTORY_MARK = "autocal apply:"

#: Frequency tolerance (Hz) for a data channel to match a solution channel.
FREQ_TOLERANCE_HZ = 1.0

#: Time tolerance (days) for a data integration to match a solution time (0.1 s).
TIME_TOLERANCE_DAYS = 0.1 / 86400.0


class ApplyError(AutocalError):
    """A solution that does not cover the data, unreadable inputs, or a refused output."""


@dataclass(frozen=True)
class ApplyResult:
    """What :func:`apply_solution` wrote.

    Parameters
    ----------
    path
        The calibrated UVH5 file.
    nbls
        Number of baselines calibrated (autos and crosses).
    ntimes
        Number of integrations.
    nfreqs
        Number of channels.
    pols
        Polarisations of the data.
    vis_units
        Units of the calibrated data (pyuvdata's ``vis_units``).
    flagged_fraction
        Fraction of the output samples flagged.
    """

    path: Path
    nbls: int
    ntimes: int
    nfreqs: int
    pols: tuple[str, ...]
    vis_units: str
    flagged_fraction: float


def _log_warnings(context: str) -> Any:
    return warnings_to_log(context, logger, logging.DEBUG)


def read_gains(path: str | Path) -> Any:
    """Read a calfits/calh5 gain solution as a checked pyuvdata ``UVCal``.

    Raises
    ------
    ApplyError
        If the file is missing, corrupt, not a gain solution or fails pyuvdata's checks.
    """
    path = Path(path)
    file_type = sniff_cal_file(path)  # CalsolFormatError (an AutocalError) for bad files
    try:
        with _log_warnings(f"reading {path.name}"):
            uvc = UVCal.from_file(str(path), file_type=file_type)
    except Exception as err:  # pyuvdata raises many types for damaged files
        raise ApplyError(
            f"pyuvdata cannot read the solution {path} ({type(err).__name__}: {err}); "
            "the file is corrupt or truncated: write it again with autocal calibrate"
        ) from err
    if uvc.cal_type != "gain" or getattr(uvc, "wide_band", False):
        raise ApplyError(f"{path} does not hold per-channel gains; give a gain solution")
    return uvc


def read_visibilities(paths: Sequence[str | Path], antennas: Sequence[int] | None = None) -> Any:
    """Read UVH5 files (autos and any cross-correlations) into one pyuvdata ``UVData``.

    Parameters
    ----------
    paths
        The files.
    antennas
        Keep only the baselines between these antennas (``None``: all).

    Raises
    ------
    ApplyError
        If no file is given, a file is missing, the antenna selection keeps nothing, or
        pyuvdata cannot read or join them.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise ApplyError("no data files given: name one or more UVH5 files")
    for path in paths:
        if path.is_dir():
            raise ApplyError(
                f"data file {path} is a folder: apply reads UVH5 files (convert a Miriad data "
                "set with pyuvdata first)"
            )
        if not path.is_file():
            raise ApplyError(f"data file {path} does not exist: check the path")
    select = {} if antennas is None else {"antenna_nums": [int(a) for a in antennas]}
    try:
        with _log_warnings("reading the data"):
            return UVData.from_file(
                [str(p) for p in paths] if len(paths) > 1 else str(paths[0]), **select
            )
    except ValueError as err:
        if antennas is not None:
            raise ApplyError(
                f"the antenna selection {list(antennas)} keeps no data ({err}); give "
                "antennas the data have"
            ) from err
        raise ApplyError(
            f"pyuvdata cannot read the data (ValueError: {err}); give UVH5 files of one observation"
        ) from err
    except Exception as err:  # pyuvdata raises many types for odd files
        raise ApplyError(
            f"pyuvdata cannot read the data ({type(err).__name__}: {err}); give UVH5 "
            "files of one observation"
        ) from err


def _missing_channels(uvd: Any, uvc: Any) -> np.ndarray:
    data_f = np.asarray(uvd.freq_array, dtype=np.float64).ravel()
    cal_f = np.sort(np.asarray(uvc.freq_array, dtype=np.float64).ravel())
    idx = np.clip(np.searchsorted(cal_f, data_f), 1, max(cal_f.size - 1, 1))
    near = np.minimum(np.abs(cal_f[idx - 1] - data_f), np.abs(cal_f[idx] - data_f))
    return data_f[near > FREQ_TOLERANCE_HZ]


def _missing_times(uvd: Any, uvc: Any) -> np.ndarray:
    if uvc.time_array is None:  # one solution over a time range: pyuvdata checks the range
        return np.array([])
    cal_t = np.asarray(uvc.time_array, dtype=np.float64)
    data_t = np.unique(uvd.time_array)
    near = np.min(np.abs(data_t[:, None] - cal_t[None, :]), axis=1)
    return data_t[near > TIME_TOLERANCE_DAYS]


def check_coverage(uvd: Any, uvc: Any) -> None:
    """Raise :class:`ApplyError` unless the solution covers the data.

    The data's antennas, polarisations (both feeds), channels and, for a solution with a
    ``time_array``, integrations must all be in the solution.
    """
    ants = np.union1d(uvd.ant_1_array, uvd.ant_2_array)
    missing = np.setdiff1d(ants, uvc.ant_array)
    if missing.size:
        raise ApplyError(
            f"the solution has no gains for antenna(s) {missing.tolist()} of the data "
            f"(it has {sorted(int(a) for a in uvc.ant_array)}): select antennas with --antennas "
            "the data or calibrate them"
        )
    orient = uvc.telescope.get_x_orientation_from_feeds()
    feeds = {uvutils.JONES_NUM2STR_DICT.get(int(j), "")[-1:].lower() for j in uvc.jones_array}
    jones = {uvutils.jnum2str(int(j), x_orientation=orient).lower() for j in uvc.jones_array}
    feeds |= {name[-1] for name in jones}
    data_pols = list(uvd.get_pols())
    lacking = [p for p in data_pols if not set(p.lower()) <= feeds]
    if lacking:
        raise ApplyError(
            f"the solution's Jones terms {sorted(jones)} do not cover the data's "
            f"polarisation(s) {lacking}: calibrate those polarisations"
        )
    channels = _missing_channels(uvd, uvc)
    if channels.size:
        raise ApplyError(
            f"{channels.size} data channel(s) ({channels.min() / 1e6:.3f}-"
            f"{channels.max() / 1e6:.3f} MHz) are not channels of the solution "
            f"({float(np.min(uvc.freq_array)) / 1e6:.3f}-{float(np.max(uvc.freq_array)) / 1e6:.3f}"
            " MHz): calibrate the data's band, or apply to the solution's band with "
            "--freq-range (freq_range_mhz)"
        )
    times = _missing_times(uvd, uvc)
    if times.size:
        raise ApplyError(
            f"{times.size} integration(s) of the data (JD {times.min():.6f}-{times.max():.6f}) "
            "are not times of the solution: apply the solution of the same observation"
        )


def select_band(uvd: Any, freq_range_mhz: tuple[float, float]) -> None:
    """Keep the data's channels within ``(low, high)`` MHz, in place.

    Raises
    ------
    ApplyError
        If the range is not ``0 < low < high`` or keeps no channel (the data's band named).
    """
    lo, hi = (float(v) for v in freq_range_mhz)
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
        raise ApplyError(f"--freq-range must be LOW:HIGH MHz with 0 < LOW < HIGH, got {lo}:{hi}")
    freqs = np.asarray(uvd.freq_array, dtype=np.float64).ravel()
    keep = freqs[(freqs >= lo * 1e6) & (freqs <= hi * 1e6)]
    if keep.size == 0:
        raise ApplyError(
            f"--freq-range {lo:g}:{hi:g} MHz keeps no channel of the data "
            f"({freqs.min() / 1e6:.3f}-{freqs.max() / 1e6:.3f} MHz)"
        )
    with _log_warnings("selecting channels"):
        uvd.select(frequencies=keep)


def check_output(path: Path, overwrite: bool) -> None:
    """Refuse an existing output unless ``overwrite`` and it is a calibrated UVH5 of autocal's."""
    if not path.exists():
        return
    if path.is_dir():
        raise ApplyError(f"the output {path} is a directory: give a file name")
    try:
        with h5py.File(path, "r") as handle:
            history = handle["Header/history"][()]
        history = history.decode() if isinstance(history, bytes) else str(history)
    except (OSError, KeyError) as err:
        raise ApplyError(
            f"the output {path} exists and is not a UVH5 file autocal wrote: choose "
            "another output name (autocal does not replace other files)"
        ) from err
    if HISTORY_MARK not in history:
        raise ApplyError(
            f"the output {path} exists and was not written by autocal apply: choose another "
            "output name (autocal does not replace other files)"
        )
    if not overwrite:
        raise ApplyError(f"the output {path} exists: pass --overwrite to replace it")


def _flag_non_finite(uvd: Any) -> None:
    """Flag the data's NaN and infinite samples and store them as 0 (in place).

    A UVH5 file's autos must be real, and pyuvdata refuses to write a NaN; such samples
    carry no measurement, so they are flagged (``calibrate`` leaves them out of the fit the
    same way) and written as 0, with a warning saying how many.
    """
    bad = ~np.isfinite(uvd.data_array)
    if not bad.any():
        return
    uvd.flag_array |= bad
    uvd.data_array[bad] = 0.0
    logger.warning(
        "%d non-finite (NaN or infinite) samples of the data flagged and written as 0",
        int(bad.sum()),
    )


def _history_line(solution: Path, data: Sequence[Path]) -> str:
    names = ", ".join(str(p) for p in data)
    return (
        f"{HISTORY_MARK} autocal {__version__} calibrated these data with {solution} "
        f"(sha256 {file_checksum(solution)}), flags propagated; data files: {names}.\n"
    )


def apply_solution(
    solution: str | Path,
    data: Sequence[str | Path],
    out: str | Path,
    *,
    antennas: Sequence[int] | None = None,
    freq_range_mhz: tuple[float, float] | None = None,
    overwrite: bool = False,
) -> ApplyResult:
    """Calibrate UVH5 visibilities with a gain solution and write a calibrated UVH5 file.

    Parameters
    ----------
    solution
        A calfits or calh5 gain solution (``solution.calh5`` / ``solution.calfits`` of
        ``autocal calibrate``).
    data
        UVH5 files of one observation (autos and any cross-correlations).
    out
        The calibrated UVH5 file to write.
    antennas
        Calibrate only the baselines between these antennas (``None``: every antenna of
        the data, each of which the solution must cover).
    freq_range_mhz
        Calibrate only the data's channels within ``(low, high)`` MHz, e.g. the band a
        solution covers when it covers only part of the data's; the output holds those
        channels only (``None``: every channel, each of which the solution must cover).
    overwrite
        Replace ``out`` if it is a calibrated UVH5 file autocal wrote.

    Returns
    -------
    ApplyResult
        The file written and what it holds.

    Raises
    ------
    ApplyError
        Unreadable inputs, a solution that does not cover the data, or a refused output
        (see the module notes); nothing is written then.
    """
    solution, out = Path(solution), Path(out)
    data_paths = [Path(p) for p in data]
    check_output(out, overwrite)
    uvc = read_gains(solution)
    uvd = read_visibilities(data_paths, antennas)
    if str(uvd.vis_units).strip().lower() != "uncalib":
        raise ApplyError(
            f"the data are already calibrated (vis_units {uvd.vis_units!r}): give the raw, "
            "uncalibrated visibilities (vis_units 'uncalib'), or they would be calibrated twice"
        )
    if freq_range_mhz is not None:
        select_band(uvd, freq_range_mhz)
    check_coverage(uvd, uvc)
    _flag_non_finite(uvd)
    try:
        with _log_warnings("calibrating"):
            uvutils.uvcalibrate(uvd, uvc, inplace=True, prop_flags=True)
    except ValueError as err:
        raise ApplyError(f"pyuvdata cannot apply {solution} to the data: {err}") from err
    if np.all(uvd.flag_array):
        raise ApplyError(
            f"{solution} flags every channel the data have (or the data flag every sample): "
            "the calibrated file would hold no usable sample; check the solution's "
            "summary.json 'quality' (autocal info) or select other channels or antennas"
        )
    separator = "" if uvd.history.endswith("\n") else "\n"
    uvd.history += separator + _history_line(solution, data_paths)
    with atomic_path(out) as tmp, _log_warnings(f"writing {out.name}"):
        tmp.unlink()  # pyuvdata writes a new file
        try:
            uvd.write_uvh5(str(tmp))
        except ValueError as err:
            raise ApplyError(f"pyuvdata cannot write the calibrated data: {err}") from err
    result = ApplyResult(
        path=out,
        nbls=int(uvd.Nbls),
        ntimes=int(uvd.Ntimes),
        nfreqs=int(uvd.Nfreqs),
        pols=tuple(uvd.get_pols()),
        vis_units=str(uvd.vis_units),
        flagged_fraction=float(np.mean(uvd.flag_array)),
    )
    logger.info("wrote %s: %s", out, result)
    return result
