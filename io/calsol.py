"""Calibration solutions as pyuvdata ``UVCal`` files: reference gains in, autocal gains out.

Reading
-------
:func:`read_reference_gains` loads the per-antenna complex gains of cross-correlation
calibration (hera_cal redcal/omnical/abscal) from calfits or calh5 files -- one file or
several consecutive files joined in time -- into a :class:`ReferenceGains`.

* Files are read with :meth:`pyuvdata.UVCal.from_file`; the file type is recognised from
  the file's *content* (FITS or HDF5 signature), so names such as
  ``*.calfits_36x_only`` work.
* Old H1C calfits files (JD 2458099, 2458101) fail pyuvdata's checks (no antenna
  positions): a file that cannot be read with checks is read again with
  ``run_check=False`` and the fact is logged and recorded in ``meta``.
* Jones codes are named with the file's feed orientation: codes -5/-6 with the x feed
  pointing east are ``"ee"``/``"nn"`` (``ee`` = east-west dipole); without an orientation
  they stay ``"xx"``/``"yy"``.
* Several files are joined along time (sorted, duplicate times dropped); they must agree
  in antennas, polarisations, channels and gain convention.

Absolute or relative?
---------------------
Redundant calibration (redcal/omnical) fixes the overall amplitude degeneracy at about
unity, so its gains are *relative*: ``|g| ~ 1``. Absolute calibration (abscal) scales
raw correlator units to Jy: H1C abscal gains have ``|g| ~ 0.027``. The classification
(``ReferenceGains.absolute``) is, in order:

1. the ``absolute`` argument, when given;
2. absolute if the file states a ``gain_scale`` (e.g. ``"Jy"``, or ``"K"`` for files
   written by :func:`write_calh5`);
3. absolute if the median unflagged ``|g|`` (divide convention) is outside
   ``[1/3, 3]`` (:data:`UNITY_RANGE`), relative otherwise.

The file name (an ``abs`` token as in ``*.abs.calfits``) is recorded as supporting
evidence only: ``zen.2458043.40141.xx.HH.XRAA.abs.calfits`` is named ``abs`` but holds
redcal-derived gains with median ``|g| = 0.93`` and is classified relative. The reason
is stored in ``meta["kind_reason"]``. Absolute gains without a stated scale are taken
to be Jy-referenced (HERA abscal: ``raw / |g|^2`` is in Jy).

Writing
-------
:func:`write_calh5` / :func:`write_calfits` write an autocal
:class:`~autocal.fit.lsq.Solution` as a genuine ``UVCal`` (``cal_type="gain"``,
``cal_style="sky"``) through pyuvdata:

* autocal fits ``R = G (Tsky + Trxr)`` with ``G = |g|^2`` in raw units per kelvin. The
  gain written is ``g = |g| = sqrt(G)``: real and positive (the phase of an
  auto-correlation is zero, so no phase is determined);
* ``gain_convention = "divide"``: as hera_cal applies gains to visibilities,
  ``V_cal = V_raw / (g_i g_j^*)``, so an auto becomes ``R / |g|^2 = Tsky + Trxr`` in
  kelvin. This is the same convention as the H1C abscal files (whose ``R / |g|^2`` is
  in Jy);
* ``gain_scale = "K"``: calibrated data are antenna temperatures in kelvin;
* polarisations ``ee``/``nn`` are Jones codes -5/-6 with the x feed pointing east
  (pyuvdata's HERA telescope has exactly these feeds); ``xx``/``yy`` names are written
  with the same codes and, for a non-HERA telescope, the same east-pointing x feed;
* one solution per antenna/polarisation/channel: ``Ntimes = 1`` with a ``time_range``
  spanning the fitted integrations (the time-averaged ``G`` of the solution), or, with
  ``per_time=True``, the time model ``G(t)`` evaluated at every fitted integration;
* ``flag_array`` is the solution's channel flags (failed fits, non-positive ``G``);
  flagged gains are written as 1 (never NaN);
* ``quality_array`` holds the total 1-sigma uncertainty of the written gain amplitude
  ``|g|`` (:attr:`autocal.fit.lsq.Solution.sigma_abs_g`: statistical, jackknife and drift
  terms, :mod:`autocal.fit.uncertainty`; with ``per_time=True`` the statistical error of
  ``|g(t)|`` scaled by the channel's total-to-statistical ratio of the time-averaged
  ``|g|``), 0 where undefined; ``total_quality_array`` the pooled ``sum chi^2 / sum dof``
  over antennas (``chi^2 / dof`` per antenna is in the HDF5 product);
* the telescope is pyuvdata's known HERA telescope (all antennas and positions) when the
  solution's telescope is HERA (or unknown and every antenna number exists in HERA);
  otherwise a minimal telescope at the solution's site with its antennas at zero
  positions;
* ``sky_catalog`` / ``diffuse_model`` describe the Tsky model, ``ref_antenna_name`` is
  ``"none"`` (amplitude-only calibration), the history records autocal's version, the
  model and the inputs. Uncertainties do not fit in a UVCal: they are in the HDF5
  product (:mod:`autocal.io.products`).

Files are written atomically (temporary file in the same folder, then rename) and
existing files are replaced only with ``overwrite=True``.
"""

from __future__ import annotations

import json
import logging
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from autocal.core.files import atomic_path, file_checksum
from autocal.errors import AutocalError
from autocal.io.pyuvdata_helpers import warnings_to_log
from autocal.io.pyuvdata_helpers import x_orientation as feed_orientation

if TYPE_CHECKING:
    from autocal.fit.lsq import Solution

logger = logging.getLogger(__name__)

#: Median ``|g|`` range (divide convention) taken as "normalised to unity" (relative).
UNITY_RANGE = (1.0 / 3.0, 3.0)

#: Gain scale written by autocal: calibrated autos are antenna temperatures in kelvin.
GAIN_SCALE = "K"

#: Gain convention written by autocal (``V_cal = V_raw / (g_i g_j^*)``).
GAIN_CONVENTION = "divide"

_FITS_MAGIC = b"SIMPLE  ="
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


class CalsolFormatError(AutocalError):
    """A file is missing, corrupt, truncated, not a calibration file, or cannot be joined."""


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------
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
    from pyuvdata import utils as uvutils

    orient = x_orientation if x_orientation in ("east", "north") else None
    names = np.atleast_1d(uvutils.jnum2str([int(c) for c in codes], x_orientation=orient))
    return [str(n).lower().removeprefix("j") for n in names]


def _sniff(path: Path) -> str:
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
    from astropy.io import fits

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
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            root = set(h5.keys())
            header = h5.get("Header")
            keys = set(header.keys()) if isinstance(header, h5py.Group) else set()
            fmt = h5.attrs.get("format")
    except OSError as err:
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


def _abs_token(name: str) -> bool:
    """Whether a file name carries an ``abs`` token (``*.abs.calfits``, ``*_abs.*``)."""
    return any(tok in {"abs", "abscal"} for tok in re.split(r"[._\-]", name.lower()))


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ReferenceGains:
    """Antenna gains from cross-correlation calibration.

    Parameters
    ----------
    gains
        ``(Nant, Npol, Ntime, Nfreq)`` complex gains as stored (see ``gain_convention``).
    flags
        Like ``gains``; ``True`` = bad (also set where a gain is zero or non-finite).
    freqs
        ``(Nfreq,)`` Hz, increasing.
    jds
        ``(Ntime,)`` Julian dates of the solutions (centres of time ranges), increasing.
    lsts
        ``(Ntime,)`` LSTs in hours, or ``None`` if the files have none.
    antennas
        ``(Nant,)`` antenna numbers.
    pols
        Polarisation names (``"ee"``, ``"nn"``; ``"xx"``/``"yy"`` without orientation).
    gain_convention
        ``"divide"`` (``V_cal = V_raw / (g_i g_j^*)``) or ``"multiply"``.
    absolute
        Whether the gains carry an absolute scale (see the module notes).
    gain_scale
        The calibrated data's unit for absolute gains (``"Jy"``, ``"K"``), else ``None``.
    cal_style
        pyuvdata's ``cal_style`` (``"redundant"``, ``"sky"``).
    meta
        Provenance: ``files``, ``sha256``, ``history``, ``telescope``,
        ``x_orientation``, ``kind_reason``, ``unchecked_files`` (read with
        ``run_check=False``), ``time_ranges``.
    """

    gains: np.ndarray
    flags: np.ndarray
    freqs: np.ndarray
    jds: np.ndarray
    lsts: np.ndarray | None
    antennas: np.ndarray
    pols: tuple[str, ...]
    gain_convention: str
    absolute: bool
    gain_scale: str | None = None
    cal_style: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        from autocal.core.reprs import compact_repr

        return compact_repr(self)

    def __post_init__(self) -> None:
        shape = (len(self.antennas), len(self.pols), len(self.jds), len(self.freqs))
        if self.gains.shape != shape or self.flags.shape != shape:
            raise CalsolFormatError(
                f"gains {self.gains.shape} / flags {self.flags.shape} do not match "
                f"(Nant, Npol, Ntime, Nfreq) = {shape}"
            )
        if self.gain_convention not in ("divide", "multiply"):
            raise CalsolFormatError(f"unknown gain convention {self.gain_convention!r}")

    @property
    def nant(self) -> int:
        """Number of antennas."""
        return len(self.antennas)

    @property
    def ntime(self) -> int:
        """Number of solution times."""
        return len(self.jds)

    @property
    def nfreq(self) -> int:
        """Number of channels."""
        return len(self.freqs)

    @property
    def abs_g(self) -> np.ndarray:
        """Gain amplitude in the divide convention: ``V_cal = V_raw / |g|^2`` for autos.

        ``|g|`` for ``"divide"`` files, ``1 / |g|`` for ``"multiply"`` files; NaN where
        flagged.
        """
        amp = np.abs(self.gains)
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.gain_convention == "multiply":
                amp = 1.0 / amp
        return np.where(self.flags, np.nan, amp)

    def describe(self) -> dict[str, Any]:
        """Return a JSON-serialisable summary."""
        amp = self.abs_g
        good = np.isfinite(amp)
        return {
            "files": [str(f) for f in self.meta.get("files", [])],
            "antennas": self.antennas.tolist(),
            "pols": list(self.pols),
            "nfreq": self.nfreq,
            "freq_range_Hz": [float(self.freqs[0]), float(self.freqs[-1])],
            "ntime": self.ntime,
            "jd_range": [float(self.jds[0]), float(self.jds[-1])],
            "gain_convention": self.gain_convention,
            "absolute": self.absolute,
            "gain_scale": self.gain_scale,
            "kind_reason": self.meta.get("kind_reason"),
            "median_abs_g": float(np.median(amp[good])) if good.any() else None,
            "flagged_fraction": float(np.mean(self.flags)),
        }


@dataclass
class _CalFile:
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
    from pyuvdata import UVCal

    file_type = _sniff(path)
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


def _load_file(path: Path) -> _CalFile:
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
    scale = getattr(uvc, "gain_scale", None)
    return _CalFile(
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


def _check_joinable(first: _CalFile, other: _CalFile) -> None:
    def fail(what: str) -> None:
        raise CalsolFormatError(
            f"{other.path} cannot be joined to {first.path}: {what}. Pass consecutive files "
            "of one calibration run."
        )

    if other.freqs.shape != first.freqs.shape or not np.allclose(
        other.freqs, first.freqs, rtol=0, atol=1.0
    ):
        fail(f"its {other.freqs.size} channels differ from the first file's {first.freqs.size}")
    if not np.array_equal(np.sort(other.antennas), np.sort(first.antennas)):
        fail(f"it has antennas {other.antennas.tolist()}, the first {first.antennas.tolist()}")
    if other.pols != first.pols:
        fail(f"it has polarisations {other.pols}, the first {first.pols}")
    if other.gain_convention != first.gain_convention:
        fail(f"its gain convention is {other.gain_convention}, not {first.gain_convention}")
    if other.gain_scale != first.gain_scale:
        fail(f"its gain scale is {other.gain_scale}, not {first.gain_scale}")


def _classify(files: list[_CalFile], amp: np.ndarray, absolute: bool | None) -> tuple[bool, str]:
    named = any(_abs_token(f.path.name) for f in files)
    good = amp[np.isfinite(amp) & (amp > 0)]
    median = float(np.median(good)) if good.size else float("nan")
    scale = files[0].gain_scale
    if absolute is not None:
        return bool(absolute), f"given by the caller (median |g| {median:.4g})"
    if scale:
        return True, f"the file states gain_scale {scale!r}"
    if not np.isfinite(median):
        return False, "no unflagged gains; assumed relative"
    lo, hi = UNITY_RANGE
    if lo <= median <= hi:
        note = (
            " although the file name says 'abs' (redcal-derived gains keep |g| ~ 1)"
            if named
            else ""
        )
        return False, f"median |g| {median:.4g} is near unity: relative{note}"
    note = "; the file name says 'abs'" if named else "; note: the file name does not say 'abs'"
    return True, f"median |g| {median:.4g} is far from unity: absolute{note}"


def read_reference_gains(
    paths: str | Path | Sequence[str | Path],
    *,
    antennas: Sequence[int] | None = None,
    pols: Sequence[str] | None = None,
    freq_range: tuple[float, float] | None = None,
    absolute: bool | None = None,
    gain_scale: str | None = None,
) -> ReferenceGains:
    """Read calibration gains from calfits or calh5 files through pyuvdata.

    Parameters
    ----------
    paths
        One file, or several consecutive files of one calibration run (joined in time).
    antennas
        Antenna numbers to keep (default all).
    pols
        Polarisations to keep, e.g. ``["ee"]`` (``"xx"`` is accepted for ``"ee"`` when
        the x feed points east).
    freq_range
        ``(low, high)`` in Hz, inclusive.
    absolute
        Override the absolute/relative classification (see the module notes).
    gain_scale
        Override the scale of absolute gains (default: the file's, else ``"Jy"``).

    Returns
    -------
    ReferenceGains
        Gains ``(Nant, Npol, Ntime, Nfreq)``.

    Raises
    ------
    CalsolFormatError
        For missing, corrupt, truncated or non-calibration files, files that cannot be
        joined, and selections of antennas, polarisations or channels that the files
        do not hold (the message lists what is available).
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise CalsolFormatError("no calibration files given")
    files = [_load_file(p) for p in paths]
    first = files[0]
    for other in files[1:]:
        _check_joinable(first, other)

    # Antennas: the first file's order; others are reordered onto it.
    ant_list = first.antennas.tolist()
    if antennas is not None:
        wanted = [int(a) for a in np.atleast_1d(antennas)]
        missing = [a for a in wanted if a not in ant_list]
        if missing:
            raise CalsolFormatError(
                f"antenna(s) {missing} are not in {first.path.name}; available antennas: "
                f"{sorted(ant_list)}"
            )
        if len(set(wanted)) != len(wanted):
            raise CalsolFormatError(f"antennas {wanted} repeat an antenna")
        ant_list = wanted
    pol_idx = list(range(len(first.pols)))
    if pols is not None:
        pol_idx = _pol_indices(first, [pols] if isinstance(pols, str) else list(pols))
    chans = np.arange(first.freqs.size)
    if freq_range is not None:
        lo, hi = sorted(float(f) for f in freq_range)
        chans = np.flatnonzero((first.freqs >= lo) & (first.freqs <= hi))
        if chans.size == 0:
            raise CalsolFormatError(
                f"no channels in {lo:.6g}-{hi:.6g} Hz; the gains cover "
                f"{first.freqs[0]:.6g}-{first.freqs[-1]:.6g} Hz (give the range in Hz)"
            )

    gains, flags, jds, lsts, ranges = [], [], [], [], []
    for f in files:
        ia = [int(np.flatnonzero(f.antennas == a)[0]) for a in ant_list]
        index = np.ix_(ia, pol_idx, np.arange(f.jds.size), chans)
        gains.append(f.gains[index])
        flags.append(f.flags[index])
        jds.append(f.jds)
        lsts.append(f.lsts)
        ranges.append(f.time_ranges)
    jd_all = np.concatenate(jds)
    order = np.argsort(jd_all, kind="stable")
    jd_sorted = jd_all[order]
    keep = np.ones(order.size, bool)
    keep[1:] = np.diff(jd_sorted) > 1e-8
    if not keep.all():
        logger.warning("dropping %d duplicate solution time(s)", int((~keep).sum()))
    order = order[keep]
    gain_arr = np.concatenate(gains, axis=2)[:, :, order]
    flag_arr = np.concatenate(flags, axis=2)[:, :, order]
    lst_arr = None if any(x is None for x in lsts) else np.concatenate(lsts)[order]
    range_arr = None if any(r is None for r in ranges) else np.concatenate(ranges)[order].tolist()

    kind, reason = _classify(
        files, _divide_amp(gain_arr, flag_arr, first.gain_convention), absolute
    )
    scale = gain_scale or first.gain_scale or ("Jy" if kind else None)
    unchecked = [str(f.path) for f in files if not f.checked]
    meta = {
        "files": [str(f.path) for f in files],
        "sha256": [file_checksum(f.path) for f in files],
        "history": first.history,
        "telescope": first.telescope,
        "x_orientation": first.x_orientation,
        "jones": [first.pol_codes[i] for i in pol_idx],
        "kind_reason": reason,
        "gain_scale_in_file": first.gain_scale,
        "unchecked_files": unchecked,
        "time_ranges": range_arr,
    }
    logger.info(
        "read %d calibration file(s): %d antennas, pols %s, %d times, %d channels; %s",
        len(files),
        len(ant_list),
        [first.pols[i] for i in pol_idx],
        order.size,
        chans.size,
        reason,
    )
    return ReferenceGains(
        gains=gain_arr,
        flags=flag_arr,
        freqs=first.freqs[chans],
        jds=jd_all[order],
        lsts=lst_arr,
        antennas=np.asarray(ant_list, dtype=np.int64),
        pols=tuple(first.pols[i] for i in pol_idx),
        gain_convention=first.gain_convention,
        absolute=kind,
        gain_scale=scale if kind else None,
        cal_style=first.cal_style,
        meta=meta,
    )


def _divide_amp(gains: np.ndarray, flags: np.ndarray, convention: str) -> np.ndarray:
    amp = np.abs(gains)
    with np.errstate(divide="ignore"):
        if convention == "multiply":
            amp = 1.0 / amp
    return np.where(flags, np.nan, amp)


def _pol_indices(first: _CalFile, pols: list[str]) -> list[int]:
    from pyuvdata import utils as uvutils

    orient = first.x_orientation if first.x_orientation in ("east", "north") else None
    out = []
    for pol in pols:
        name = str(pol).lower()
        if name in first.pols:
            out.append(first.pols.index(name))
            continue
        try:
            code = int(uvutils.jstr2num(name, x_orientation=orient))
        except (KeyError, ValueError):
            code = None
        if code is None or code not in first.pol_codes:
            raise CalsolFormatError(
                f"polarisation {pol!r} is not in {first.path.name}; available: {first.pols}"
            )
        out.append(first.pol_codes.index(code))
    if len(set(out)) != len(out):
        raise CalsolFormatError(f"polarisations {pols} repeat a polarisation")
    return out


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------
#: Sub-dictionaries of ``Solution.config`` searched after its top level (the pipeline
#: stores ``{"calibration": <settings>, "provenance": <resolved conventions>}``).
CONFIG_SECTIONS = ("provenance", "calibration")


def config_sources(config: dict[str, Any] | None) -> list[dict[str, Any]]:
    """Return ``config`` and its ``provenance``/``calibration`` sections, in lookup order."""
    config = config or {}
    sources = [config]
    sources += [config[k] for k in CONFIG_SECTIONS if isinstance(config.get(k), dict)]
    return sources


def _config_value(config: dict[str, Any], *keys: str) -> Any:
    for source in config_sources(config):
        for key in keys:
            if key in source and source[key] not in (None, ""):
                return source[key]
    return None


def _resolve_site(site: Any, config: dict[str, Any]) -> Any:
    from autocal.core.sites import HERA, Site, get_site

    spec = site if site is not None else _config_value(config, "site")
    if spec is None:
        return None
    if isinstance(spec, Site):
        return spec
    if isinstance(spec, dict) and {"lat_deg", "lon_deg"} <= set(spec):
        return Site(
            str(spec.get("name", "site")),
            float(spec["lat_deg"]),
            float(spec["lon_deg"]),
            float(spec.get("alt_m", 0.0)),
        )
    if isinstance(spec, dict) and "name" in spec:
        spec = spec["name"]
    try:
        return get_site(str(spec))
    except ValueError:
        logger.warning("site %r not understood; using HERA's location", spec)
        return HERA


def _telescope_for(solution: Solution, telescope: str | None, site: Any) -> tuple[Any, bool]:
    """Return ``(pyuvdata Telescope, is_known_hera)`` for a solution."""
    from pyuvdata import Telescope

    from autocal.core.sites import HERA

    config = solution.config or {}
    name = telescope or _config_value(config, "telescope", "telescope_name")
    resolved_site = _resolve_site(site, config)
    ants = [int(a) for a in solution.antennas]
    hera = Telescope.from_known_telescopes("HERA")
    known = set(int(a) for a in hera.antenna_numbers)
    fits_hera = set(ants) <= known
    site_is_hera = resolved_site is None or resolved_site.name.lower() == "hera"
    want_hera = (
        str(name).strip().upper() == "HERA" if name is not None else (site_is_hera and fits_hera)
    )
    if want_hera and fits_hera:
        if not hera.instrument:
            hera.instrument = hera.name
        return hera, True
    if want_hera:
        logger.warning(
            "antenna number(s) %s do not exist in HERA; writing a minimal telescope",
            sorted(set(ants) - known),
        )
    location_site = resolved_site or HERA
    if resolved_site is None:
        logger.warning("the solution records no site; using HERA's location")
    names = list(solution.antenna_names) or [f"ant{a}" for a in ants]
    if name is not None:
        tel_name = str(name)
    else:
        tel_name = resolved_site.name if resolved_site is not None else "unknown"
    with _warnings_to_log("building the telescope"):
        tel = Telescope.new(
            name=tel_name,
            location=location_site.location,
            antenna_positions=np.zeros((len(ants), 3)),
            antenna_names=names,
            antenna_numbers=ants,
            instrument=tel_name,
            mount_type="fixed",
            update_from_known=False,
        )
    return tel, False


def _jones_codes(pols: Sequence[str]) -> tuple[list[int], str | None]:
    from pyuvdata import utils as uvutils

    names = [str(p).lower() for p in pols]
    compass = [p for p in names if set(p) <= {"e", "n"}]
    if compass and len(compass) != len(names):
        raise CalsolFormatError(f"cannot mix e/n and x/y polarisation names: {names}")
    orient = "east" if compass else None
    try:
        codes = [int(c) for c in np.atleast_1d(uvutils.jstr2num(names, x_orientation=orient))]
    except (KeyError, ValueError) as err:
        raise CalsolFormatError(f"polarisations {names} have no Jones code: {err}") from err
    return codes, orient


def _describe_sky(config: dict[str, Any]) -> str:
    value = _config_value(config, "sky", "model_sky", "sky_model")
    if value is None:
        return "autocal Tsky model (unspecified)"
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True, default=str)
    return str(value)


def _history(solution: Solution, extra: str) -> str:
    from autocal import __version__

    config = solution.config or {}
    lines = [
        f"autocal {__version__}: gains |g| = sqrt(G) fitted to auto-correlations "
        "R = G (Tsky + Trxr) + noise; gain_convention divide, gain_scale K "
        "(R / |g|^2 is the antenna temperature in kelvin); phases are zero.",
        f"autocal model: {json.dumps(solution.model.describe(), sort_keys=True)}",
        f"autocal fitted {len(solution.jds)} integrations, JD "
        f"{float(np.min(solution.jds)):.6f}-{float(np.max(solution.jds)):.6f}"
        if len(solution.jds)
        else "autocal fitted no integrations",
    ]
    for key in ("sky", "model_sky", "beam", "site", "tgnd", "tgnd_K", "cmb", "inputs", "files"):
        value = _config_value(config, key)
        if value is not None:
            lines.append(f"autocal {key}: {json.dumps(value, sort_keys=True, default=str)}")
    lines.append(
        "autocal: uncertainties, covariances and the time model are in the autocal HDF5 "
        "product (autocal.io.products)."
    )
    if extra:
        lines.append(extra.rstrip())
    return "\n".join(lines) + "\n"


def solution_to_uvcal(
    solution: Solution,
    *,
    time_range: tuple[float, float] | None = None,
    per_time: bool = False,
    telescope: str | None = None,
    site: Any = None,
    history: str = "",
) -> Any:
    """Build a pyuvdata ``UVCal`` from an autocal solution (see the module notes).

    Parameters
    ----------
    solution
        An :class:`autocal.fit.lsq.Solution`.
    time_range
        ``(start, stop)`` JD of the single solution interval (default: the fitted
        integrations, padded by half the median integration spacing at each end).
    per_time
        Write ``G(t)`` of the time model at every fitted integration instead of one
        time-averaged solution.
    telescope
        Telescope name (default: ``"telescope"`` in ``solution.config`` or its
        ``provenance``/``calibration`` sections; else HERA when the site is HERA or unknown
        and every antenna exists in HERA; else the site's name).
    site
        Site of a non-HERA telescope: a :class:`~autocal.core.sites.Site`, a name or a
        ``describe()`` dict (default: ``"site"`` in ``solution.config`` or its sections).
    history
        Text appended to the history.

    Returns
    -------
    pyuvdata.UVCal
        The calibration object (checked).

    Raises
    ------
    CalsolFormatError
        If the solution cannot be represented (no integrations, bad time range,
        polarisations without Jones codes).
    """
    from pyuvdata import UVCal

    jds = np.asarray(solution.jds, dtype=np.float64)
    if jds.size == 0:
        raise CalsolFormatError("the solution has no fitted integrations (no JDs)")
    freqs = np.asarray(solution.freqs, dtype=np.float64)
    codes, orient = _jones_codes(solution.pols)
    tel, _ = _telescope_for(solution, telescope, site)
    if orient is not None:
        tel.set_feeds_from_x_orientation(orient, feeds=["x", "y"], polarization_array=codes)
    elif tel.feed_array is None:
        tel.set_feeds_from_x_orientation("east", feeds=["x", "y"], polarization_array=codes)

    nant, npol, nfreq = len(solution.antennas), len(solution.pols), freqs.size
    flags = np.asarray(solution.flags, dtype=bool)  # (A, P, F)
    sigma_amp = np.asarray(solution.sigma_abs_g, dtype=np.float64)  # (A, P, F), total
    chi2 = np.where(np.isfinite(solution.chi2) & ~flags, solution.chi2, 0.0)
    dof = np.where(~flags, np.asarray(solution.dof, dtype=np.float64), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        total = np.where(dof.sum(0) > 0, chi2.sum(0) / dof.sum(0), 0.0)  # (P, F)

    kwargs: dict[str, Any] = {}
    if per_time:
        ev = solution.evaluate()
        big_g = ev["G"]  # (A, P, T, F)
        ntime = jds.size
        if ntime > 1 and np.any(np.diff(jds) <= 0):
            raise CalsolFormatError("per_time needs strictly increasing JDs")
        steps = np.diff(jds)
        tint = np.full(ntime, np.median(steps) * 86400.0 if steps.size else 1.0)
        kwargs["time_array"] = jds
        kwargs["integration_time"] = tint
        gain_g = big_g
        flag4 = np.broadcast_to(flags[:, :, None, :], big_g.shape)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = sigma_amp / np.asarray(solution.sigma_abs_g_stat, dtype=np.float64)
            sig4 = ev["sigma_G"] / (2 * np.sqrt(big_g)) * ratio[:, :, None, :]
    else:
        if time_range is None:
            pad = 0.5 * float(np.median(np.diff(np.sort(jds)))) if jds.size > 1 else 0.5 / 86400
            start, stop = float(jds.min()) - pad, float(jds.max()) + pad
        else:
            start, stop = (float(t) for t in time_range)
        if not (np.isfinite(start) and np.isfinite(stop) and stop > start):
            raise CalsolFormatError(
                f"time_range ({start}, {stop}) must be finite and increasing (Julian dates)"
            )
        if jds.min() < start - 1e-9 or jds.max() > stop + 1e-9:
            logger.warning(
                "time_range %.6f-%.6f does not cover the fitted JDs %.6f-%.6f",
                start,
                stop,
                jds.min(),
                jds.max(),
            )
        kwargs["time_range"] = np.array([[start, stop]])
        kwargs["integration_time"] = np.array([(stop - start) * 86400.0])
        gain_g = np.asarray(solution.G, dtype=np.float64)[:, :, None, :]
        flag4 = flags[:, :, None, :]
        sig4 = sigma_amp[:, :, None, :]
    with np.errstate(invalid="ignore"):
        amp = np.sqrt(gain_g)
    bad = flag4 | ~np.isfinite(amp) | ~(gain_g > 0)
    amp = np.where(bad, 1.0, amp)
    ntime_out = amp.shape[2]
    # autocal (A, P, T, F) -> pyuvdata (A, F, T, J)
    to_uvc = (0, 3, 2, 1)
    gain_array = np.ascontiguousarray(amp.transpose(to_uvc)).astype(np.complex128)
    flag_array = np.ascontiguousarray(bad.transpose(to_uvc))
    quality = np.where(bad | ~np.isfinite(sig4), 0.0, sig4)
    quality_array = np.ascontiguousarray(
        np.broadcast_to(quality, (nant, npol, ntime_out, nfreq)).transpose(to_uvc)
    )
    total_quality = np.ascontiguousarray(
        np.broadcast_to(total[:, None, :], (npol, ntime_out, nfreq)).transpose(2, 1, 0)
    )
    steps = np.diff(freqs)
    width = np.full(nfreq, float(np.median(steps)) if steps.size else 1.0)
    config = solution.config or {}
    sky = _describe_sky(config)
    with _warnings_to_log("building UVCal"):
        uvc = UVCal.new(
            cal_style="sky",
            gain_convention=GAIN_CONVENTION,
            jones_array=np.asarray(codes),
            telescope=tel,
            freq_array=freqs,
            channel_width=width,
            ant_array=np.asarray(solution.antennas, dtype=np.int64),
            ref_antenna_name="none",
            sky_catalog=sky,
            data={
                "gain_array": gain_array,
                "flag_array": flag_array,
                "quality_array": quality_array,
                "total_quality_array": total_quality,
            },
            history=_history(solution, history),
            gain_scale=GAIN_SCALE,
            **kwargs,
        )
        uvc.diffuse_model = sky
        uvc.extra_keywords = {
            "AUTOCAL": True,
            "ACMODEL": str(solution.model.kind),
            "ACORDER": int(solution.model.order),
            "ACGAIN": "|g|=sqrt(G); R/|g|^2 in K",
        }
        uvc.check()
    return uvc


def _write(
    solution: Solution, path: str | Path, file_type: str, overwrite: bool, **kwargs: Any
) -> Path:
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    uvc = solution_to_uvcal(solution, **kwargs)
    with atomic_path(path) as tmp, _warnings_to_log(f"writing {path.name}"):
        tmp.unlink()  # pyuvdata writes a new file
        try:
            if file_type == "calh5":
                uvc.write_calh5(str(tmp))
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
    per_time: bool = False,
    telescope: str | None = None,
    site: Any = None,
    history: str = "",
) -> Path:
    """Write a solution's gains ``|g| = sqrt(G)`` as a calh5 file (atomically).

    Parameters
    ----------
    solution
        An :class:`autocal.fit.lsq.Solution`.
    path
        Output file.
    overwrite
        Replace an existing file.
    time_range, per_time, telescope, site, history
        See :func:`solution_to_uvcal`.

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
    per_time: bool = False,
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
