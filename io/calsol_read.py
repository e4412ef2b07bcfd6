"""Reference gains: antenna gains of cross-correlation calibration, read from UVCal files.

:func:`read_reference_gains` loads the per-antenna complex gains of cross-correlation
calibration (hera_cal redcal/omnical/abscal) from calfits or calh5 files -- one file or
several consecutive files joined in time -- into a :class:`ReferenceGains`. Each file is
read by :func:`autocal.io.calsol_files.load_cal_file` (format recognised by content,
pyuvdata's checks skipped for old H1C files that fail them, Jones codes named
``ee``/``nn`` when the x feed's orientation is known).

* Several files are joined along time (sorted, duplicate times dropped); they must agree
  in antennas, polarisations, channels and gain convention.
* Files read with ``run_check=False`` are listed in ``meta["unchecked_files"]``.

Absolute or relative?
---------------------
Redundant calibration (redcal/omnical) fixes the overall amplitude degeneracy at about
unity, so its gains are *relative*: ``|g| ~ 1``. Absolute calibration (abscal) scales
raw correlator units to Jy: H1C abscal gains have ``|g| ~ 0.027``. The classification
(``ReferenceGains.absolute``) is, in order:

1. the ``absolute`` argument, when given;
2. absolute if the file states a ``gain_scale`` (e.g. ``"Jy"``, or ``"K"`` for files
   written by :func:`autocal.io.calsol_write.write_calh5`);
3. absolute if the median unflagged ``|g|`` (divide convention) is outside
   ``[1/3, 3]`` (:data:`UNITY_RANGE`), relative otherwise.

The file name (an ``abs`` token as in ``*.abs.calfits``) is recorded as supporting
evidence only: ``zen.2458043.40141.xx.HH.XRAA.abs.calfits`` is named ``abs`` but holds
redcal-derived gains with median ``|g| = 0.93`` and is classified relative. The reason
is stored in ``meta["kind_reason"]``. Absolute gains without a stated scale are taken
to be Jy-referenced (HERA abscal: ``raw / |g|^2`` is in Jy).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pyuvdata import utils as uvutils

from autocal.core.files import file_checksum
from autocal.core.reprs import compact_repr
from autocal.io.calsol_files import CalFile, CalsolFormatError, load_cal_file

logger = logging.getLogger(__name__)

#: Median ``|g|`` range (divide convention) taken as "normalised to unity" (relative).
UNITY_RANGE = (1.0 / 3.0, 3.0)


def _abs_token(name: str) -> bool:
    """Whether a file name carries an ``abs`` token (``*.abs.calfits``, ``*_abs.*``)."""
    return any(tok in {"abs", "abscal"} for tok in re.split(r"[._\-]", name.lower()))


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


def _check_joinable(first: CalFile, other: CalFile) -> None:
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


def _classify(files: list[CalFile], amp: np.ndarray, absolute: bool | None) -> tuple[bool, str]:
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
    files = [load_cal_file(p) for p in paths]
    first = files[0]
    for other in files[1:]:
        _check_joinable(first, other)

    # Antennas: the first file's order; others are reordered onto it.
    ant_list = _antenna_list(first, antennas)
    pol_idx = list(range(len(first.pols)))
    if pols is not None:
        pol_idx = _pol_indices(first, [pols] if isinstance(pols, str) else list(pols))
    chans = _channels(first, freq_range)
    joined = _join_in_time(files, ant_list, pol_idx, chans)

    kind, reason = _classify(
        files, _divide_amp(joined.gains, joined.flags, first.gain_convention), absolute
    )
    scale = gain_scale or first.gain_scale or ("Jy" if kind else None)
    meta = _provenance(files, pol_idx, reason, joined.time_ranges)
    logger.info(
        "read %d calibration file(s): %d antennas, pols %s, %d times, %d channels; %s",
        len(files),
        len(ant_list),
        [first.pols[i] for i in pol_idx],
        joined.jds.size,
        chans.size,
        reason,
    )
    return ReferenceGains(
        gains=joined.gains,
        flags=joined.flags,
        freqs=first.freqs[chans],
        jds=joined.jds,
        lsts=joined.lsts,
        antennas=np.asarray(ant_list, dtype=np.int64),
        pols=tuple(first.pols[i] for i in pol_idx),
        gain_convention=first.gain_convention,
        absolute=kind,
        gain_scale=scale if kind else None,
        cal_style=first.cal_style,
        meta=meta,
    )


def _provenance(
    files: list[CalFile], pol_idx: list[int], reason: str, time_ranges: list | None
) -> dict[str, Any]:
    """Return the ``meta`` of reference gains read from ``files`` (see :class:`ReferenceGains`)."""
    first = files[0]
    unchecked = [str(f.path) for f in files if not f.checked]
    return {
        "files": [str(f.path) for f in files],
        "sha256": [file_checksum(f.path) for f in files],
        "history": first.history,
        "telescope": first.telescope,
        "x_orientation": first.x_orientation,
        "jones": [first.pol_codes[i] for i in pol_idx],
        "kind_reason": reason,
        "gain_scale_in_file": first.gain_scale,
        "unchecked_files": unchecked,
        "time_ranges": time_ranges,
    }


def _antenna_list(first: CalFile, antennas: Sequence[int] | None) -> list[int]:
    """Return the antennas to keep: ``antennas`` (checked) or the first file's, in order."""
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
    return ant_list


def _channels(first: CalFile, freq_range: tuple[float, float] | None) -> np.ndarray:
    """Return the indices of the channels in ``freq_range`` (Hz, inclusive; default all)."""
    chans = np.arange(first.freqs.size)
    if freq_range is not None:
        lo, hi = sorted(float(f) for f in freq_range)
        chans = np.flatnonzero((first.freqs >= lo) & (first.freqs <= hi))
        if chans.size == 0:
            raise CalsolFormatError(
                f"no channels in {lo:.6g}-{hi:.6g} Hz; the gains cover "
                f"{first.freqs[0]:.6g}-{first.freqs[-1]:.6g} Hz (give the range in Hz)"
            )
    return chans


@dataclass(frozen=True, eq=False)
class _Joined:
    """The selected gains of several files along time, sorted, duplicate times dropped."""

    gains: np.ndarray
    flags: np.ndarray
    jds: np.ndarray
    lsts: np.ndarray | None
    time_ranges: list | None


def _join_in_time(
    files: list[CalFile], ant_list: list[int], pol_idx: list[int], chans: np.ndarray
) -> _Joined:
    """Select antennas, polarisations and channels of every file and join them in time."""
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
    return _Joined(
        gains=np.concatenate(gains, axis=2)[:, :, order],
        flags=np.concatenate(flags, axis=2)[:, :, order],
        jds=jd_all[order],
        lsts=None if any(x is None for x in lsts) else np.concatenate(lsts)[order],
        time_ranges=(
            None if any(r is None for r in ranges) else np.concatenate(ranges)[order].tolist()
        ),
    )


def _divide_amp(gains: np.ndarray, flags: np.ndarray, convention: str) -> np.ndarray:
    amp = np.abs(gains)
    with np.errstate(divide="ignore"):
        if convention == "multiply":
            amp = 1.0 / amp
    return np.where(flags, np.nan, amp)


def _pol_indices(first: CalFile, pols: list[str]) -> list[int]:
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
