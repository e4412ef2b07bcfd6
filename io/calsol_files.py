"""UVCal calibration files on disk: the format check and one file read through pyuvdata.

:func:`load_cal_file` reads one calfits or calh5 file of gain solutions into a
:class:`CalFile` record on autocal's axes ``(Nant, Npol, Ntime, Nfreq)``, channels in
increasing frequency; :func:`autocal.io.calsol_read.read_reference_gains` joins such
records into :class:`~autocal.io.calsol_read.ReferenceGains`.

* The file type is recognised from the file's *content* (FITS or HDF5 signature,
  :func:`sniff_cal_file`), so names such as ``*.calfits_36x_only`` work; FITS files
  without ``CALTYPE`` and HDF5 files without ``Header/cal_type`` are refused with a
  message saying what they look like.
* Files are read with :meth:`pyuvdata.UVCal.from_file`. Old H1C calfits files (JD
  2458099, 2458101) fail pyuvdata's checks (no antenna positions): a file that cannot
  be read with checks is read again with ``run_check=False``, logged, and recorded
  (``CalFile.checked``).
* Jones codes are named with the file's feed orientation (:func:`jones_names`): codes
  -5/-6 with the x feed pointing east are ``"ee"``/``"nn"`` (``ee`` = east-west dipole);
  without an orientation they stay ``"xx"``/``"yy"``.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from astropy.io import fits
from pyuvdata import UVCal
from pyuvdata import utils as uvutils

from autocal.errors import AutocalError
from autocal.io.pyuvdata_helpers import warnings_to_log
from autocal.io.pyuvdata_helpers import x_orientation as feed_orientation

logger = logging.getLogger(__name__)


_FITS_MAGIC = b"SIMPLE  ="
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


class CalsolFormatError(AutocalError):
    """A file is missing, corrupt, truncated, not a calibration file, or cannot be joined."""


def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.DEBUG)


def jones_names(codes: Sequence[int], x_orientation: str | None) -> list[str]:
    """Name pyuvdata Jones codes: ``ee``/``nn`` when the x feed's orientation is known.

    Parameters
    ----------
    codes
        Jones codes (-5 = xx, -6 = yy, -7 = xy, -8 = yx, -1..-4 circular).
    x_orientation
        ``"east"``, ``"north"`` or ``None``.

    Returns
    -------
    list of str
        Lower-case names without the ``J`` prefix, e.g. ``["ee", "nn"]``.
    """
    orient = x_orientation if x_orientation in ("east", "north") else None
    names = np.atleast_1d(uvutils.jnum2str([int(c) for c in codes], x_orientation=orient))
    return [str(n).lower().removeprefix("j") for n in names]


def sniff_cal_file(path: Path) -> str:
    """Return ``"calfits"`` or ``"calh5"`` from the file content, or raise."""
    if not path.exists():
        raise CalsolFormatError(f"{path} does not exist: check the path")
    if path.is_dir():
        raise CalsolFormatError(f"{path} is a directory, not a calfits or calh5 calibration file")
    with open(path, "rb") as handle:
        head = handle.read(16)
    if head.startswith(_FITS_MAGIC):
        _check_calfits_header(path)
        return "calfits"
    if head.startswith(_HDF5_MAGIC):
        _check_calh5_header(path)
        return "calh5"
    if not head:
        raise CalsolFormatError(f"{path} is empty, not a calibration file")
    raise CalsolFormatError(
        f"{path} is neither FITS nor HDF5, so not a calfits or calh5 calibration file"
    )


def _check_calfits_header(path: Path) -> None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            header = fits.getheader(path, 0)
    except Exception as err:
        raise CalsolFormatError(
            f"{path} starts like a FITS file but its header cannot be read "
            f"({type(err).__name__}: {err}); the file is corrupt or truncated"
        ) from err
    if "CALTYPE" not in header:
        raise CalsolFormatError(
            f"{path} is a FITS file but not calfits (no CALTYPE keyword; a beamfits or "
            "image file?): pass a UVCal calibration file"
        )


def _check_calh5_header(path: Path) -> None:
    try:
        with h5py.File(path, "r") as h5:
            root = set(h5.keys())
            header = h5.get("Header")
            keys = set(header.keys()) if isinstance(header, h5py.Group) else set()
            fmt = h5.attrs.get("format")
    except (OSError, RuntimeError) as err:  # h5py raises both for a damaged file
        raise CalsolFormatError(
            f"{path} is truncated or corrupt (HDF5 error: {err}); copy or download it again"
        ) from err
    if "cal_type" in keys:
        return
    if isinstance(fmt, str) and fmt.startswith("autocal"):
        what = f"; it is an autocal product ({fmt})"
    elif {"Header", "Data"} <= root:
        what = "; it looks like a UVH5 visibility file"
    else:
        what = ""
    raise CalsolFormatError(
        f"{path} is an HDF5 file but not calh5 (no Header/cal_type{what}): pass a UVCal "
        "calibration file"
    )


@dataclass
class CalFile:
    """One calibration file's gain solutions on autocal's axes (:func:`load_cal_file`).

    ``gains`` and ``flags`` are ``(Nant, Npol, Ntime, Nfreq)``, channels in increasing
    frequency, flags also set where a gain is zero or not finite; ``lsts`` in hours (or
    None); ``time_ranges`` ``(Ntime, 2)`` JDs when the file stores ranges, not times;
    ``checked`` is False when pyuvdata's checks had to be skipped.
    """

    path: Path
    gains: np.ndarray  # (Nant, Npol, Ntime, Nfreq)
    flags: np.ndarray
    freqs: np.ndarray
    jds: np.ndarray
    lsts: np.ndarray | None
    time_ranges: np.ndarray | None
    antennas: np.ndarray
    pols: list[str]
    pol_codes: list[int]
    x_orientation: str | None
    gain_convention: str
    gain_scale: str | None
    cal_style: str
    telescope: str
    history: str
    checked: bool


def _read_uvcal(path: Path) -> tuple[Any, bool]:
    """Read a UVCal with checks, falling back to ``run_check=False``."""
    file_type = sniff_cal_file(path)
    try:
        with _warnings_to_log(f"reading {path.name}"):
            return UVCal.from_file(str(path), file_type=file_type), True
    except Exception as first:  # pyuvdata raises many types for odd files
        try:
            with _warnings_to_log(f"reading {path.name} without checks"):
                uvc = UVCal.from_file(str(path), file_type=file_type, run_check=False)
        except Exception as err:
            raise CalsolFormatError(
                f"pyuvdata cannot read {path} as {file_type}: {type(first).__name__}: "
                f"{first}; the file is corrupt, truncated or not a UVCal file"
            ) from err
        logger.warning(
            "%s fails pyuvdata's checks (%s); read with run_check=False", path.name, first
        )
        return uvc, False


def _gain_scale(uvc: Any) -> str | None:
    """Return a file's gain scale; ``"K"`` for autocal's own files (labelled ``"K str"``).

    autocal writes ``gain_scale = "K str"`` (pyuvdata's temperature unit) for gains whose
    calibrated autos are antenna temperatures in kelvin (:mod:`autocal.io.calsol_uvcal`).
    """
    scale = getattr(uvc, "gain_scale", None)
    extra = getattr(uvc, "extra_keywords", None) or {}
    autocal_file = str(extra.get("AUTOCAL", "")).lower() in ("true", "1", "t")
    if autocal_file and str(scale).strip().lower() == "k str":
        return "K"
    return str(scale) if scale else None


def load_cal_file(path: Path) -> CalFile:
    """Read one calfits or calh5 file of per-channel gain solutions into a :class:`CalFile`.

    Raises :class:`CalsolFormatError` for a file that is not a readable UVCal file of
    per-channel gains.
    """
    uvc, checked = _read_uvcal(path)
    if uvc.cal_type != "gain":
        raise CalsolFormatError(
            f"{path} holds {uvc.cal_type} calibration solutions; only gain solutions are supported"
        )
    if getattr(uvc, "wide_band", False):
        raise CalsolFormatError(f"{path} holds wide-band gains; per-channel gains are needed")
    gains = getattr(uvc, "gain_array", None)
    if gains is None:
        raise CalsolFormatError(f"{path} has no gain array (metadata-only file?)")
    _, nfreq, ntime, _ = gains.shape
    freqs = np.asarray(uvc.freq_array, dtype=np.float64).ravel()
    if freqs.size != nfreq:
        raise CalsolFormatError(f"{path}: {freqs.size} frequencies for {nfreq} channels")
    flags = np.asarray(uvc.flag_array, dtype=bool)
    if flags.shape != gains.shape:
        flags = np.broadcast_to(flags, gains.shape)
    time_ranges = None
    if uvc.time_array is not None:
        jds = np.asarray(uvc.time_array, dtype=np.float64).ravel()
    elif uvc.time_range is not None:
        time_ranges = np.asarray(uvc.time_range, dtype=np.float64).reshape(-1, 2)
        jds = time_ranges.mean(axis=1)
    else:
        raise CalsolFormatError(f"{path} has neither a time array nor time ranges")
    lsts: np.ndarray | None = None
    if getattr(uvc, "lst_array", None) is not None:
        lsts = np.mod(np.asarray(uvc.lst_array, dtype=np.float64).ravel() * 12.0 / np.pi, 24.0)
    elif getattr(uvc, "lst_range", None) is not None:
        rng = np.asarray(uvc.lst_range, dtype=np.float64).reshape(-1, 2)
        rng = np.unwrap(rng, axis=1)
        lsts = np.mod(rng.mean(axis=1) * 12.0 / np.pi, 24.0)
    if jds.size != ntime or (lsts is not None and lsts.size != ntime):
        raise CalsolFormatError(f"{path}: time axis lengths disagree")
    codes = [int(c) for c in np.asarray(uvc.jones_array).ravel()]
    orient = feed_orientation(uvc.telescope)
    gains = np.asarray(gains).transpose(0, 3, 2, 1)
    flags = np.asarray(flags).transpose(0, 3, 2, 1)
    order = np.argsort(freqs, kind="stable")
    gains, flags, freqs = gains[..., order], flags[..., order], freqs[order]
    bad = ~np.isfinite(gains) | (gains == 0)
    scale = _gain_scale(uvc)
    return CalFile(
        path=path,
        gains=gains.astype(np.complex128),
        flags=flags | bad,
        freqs=freqs,
        jds=jds,
        lsts=lsts,
        time_ranges=time_ranges,
        antennas=np.asarray(uvc.ant_array, dtype=np.int64).ravel(),
        pols=jones_names(codes, orient),
        pol_codes=codes,
        x_orientation=orient,
        gain_convention=str(uvc.gain_convention),
        gain_scale=str(scale) if scale else None,
        cal_style=str(getattr(uvc, "cal_style", "") or ""),
        telescope=str(uvc.telescope.name),
        history=str(uvc.history or ""),
        checked=checked,
    )
