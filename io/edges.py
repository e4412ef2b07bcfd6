"""Raw EDGES three-position-switch spectra: ACQ files and an HDF5 form of them.

An EDGES receiver cycles a three-position switch and records one power spectrum per
position: ``p0`` the antenna, ``p1`` the internal ambient load, ``p2`` the load plus the
noise source. The spectrometer (FASTSPEC) writes them to *ACQ* files, read here through
the ``read_acq`` package (``read_acq.decode_file``) and written with ``read_acq.encode``.
:func:`read_edges` turns one or more files into an
:class:`autocal.core.observation.Observation` whose auto-correlation ``R`` is

- ``"q"``: the partially calibrated ratio ``Q = (p0 - p1) / (p2 - p1)`` (default), or
- ``"p0"``: the raw antenna power.

ACQ format (what ``read_acq`` decodes; verified on every file of the data folder)
-------------------------------------------------------------------------------
* A text file. Header lines start with ``;`` (``; FASTSPEC v1.1.0``, then
  ``;--key: value`` with the acquisition settings, e.g. ``num_channels``,
  ``acquisition_rate`` (MS/s), ``samples_per_accumulation``, ``switch_delay``).
* Then, per switch position, a comment line ``# swpos 0 data_drops 0 adcmax 0.29
  adcmin -0.33 temp 0 C nblk 2974 nspec 32768`` and a data line
  ``2019:335:00:00:06 0 0.000 0.006104 200.000 0.3 spectrum <4 chars per channel>``.
  Positions come in cycles 0, 1, 2; incomplete cycles are dropped by ``read_acq``.
* Each channel is 4 base64 characters (A-Z a-z 0-9 + /) holding a 24-bit integer
  ``k = -10 log10(p) * 1e5``: powers are stored in dB with 1e-5 dB steps (relative
  precision 2.3e-6, truncated towards higher power), clipped to ``1e-16.7 <= p <= 1``.
  FASTSPEC blanks the first 10 channels (they hold the floor ``10**-16.7``).
* 32768 channels over 0-200 MHz: channel ``k`` is at ``k * 200 MHz / 32768`` (the
  convention of ``read_acq`` and ``edges-cal``); ``freq_min`` must be 0 for that to hold,
  so the writer always writes the whole native band.
* Timestamps are ``YYYY:DDD:HH:MM:SS`` UTC with 1 s resolution. FASTSPEC writes the
  *same* timestamp on the three lines of a cycle (the cycle's time): that is the time
  used for the whole cycle here (and for its LST).
* Integration time per switch position: ``nblk`` spectra of ``2 num_channels`` samples at
  ``acquisition_rate``: ``t = nblk * 2 * num_channels / acquisition_rate`` (0.487 s for
  the 2019 Receiver01 lab files, 6.71 s for the EDGES-3 files). Checked against the data:
  the EDGES-3 channel scatter matches ``1 / sqrt(dnu t)`` to 1 %; the 2019 files scatter
  1.45x more (their window's noise bandwidth is about 2 channels).
  ``samples_per_accumulation`` is not used: it disagrees with the cycle timing of the
  2019 files (it would give 10.7 s per position, while their cycles last 44 s with a
  13 s switch delay per position). When the header lacks ``num_channels`` or
  ``acquisition_rate``, ``nspec`` and 400 MS/s are assumed and ``meta`` says so.

HDF5 layout (``autocal-edges-spectra-1``, written by :func:`write_edges_hdf5`)
---------------------------------------------------------------------------
Datasets ``p0``, ``p1``, ``p2`` (Ntime, Nfreq; raw linear power), ``freqs`` (Nfreq; Hz,
channel centres), ``channel_width`` (Nfreq; Hz), ``jds`` (Ntime; UTC Julian dates of the
cycles), ``integration_time`` (Ntime; s per switch position) and optional ``aux/adcmax``,
``aux/adcmin``, ``aux/data_drops`` (Ntime, 3). Root attributes: ``format``,
``telescope_name``, ``switch_positions`` (JSON), ``time_scale`` ("utc"), ``bin_factor``,
``native_channel_width_hz``, ``integration_time_source``, ``header`` (JSON of the ACQ
header), ``files`` and ``sha256`` (JSON provenance of the source files), ``history``.
Written atomically.

Frequency selection and binning: ``freq_range`` selects native channels (inclusive),
then ``bin_factor`` consecutive channels are averaged (linear power; a last incomplete
bin is dropped). ``Q`` is formed from the binned powers. Channels below 1 MHz are never
put in an :class:`Observation` (FASTSPEC blanks them, and frequencies must be >= 100 kHz).
"""

from __future__ import annotations

import json
import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from autocal.core.files import atomic_path, file_checksum
from autocal.core.observation import Observation
from autocal.core.sites import EDGES, Site
from autocal.errors import AutocalError

logger = logging.getLogger(__name__)

#: Channels of a native FASTSPEC spectrum.
NATIVE_NCHAN = 32768
#: Top of the native band in Hz (channel ``k`` is at ``k * NATIVE_FMAX_HZ / NATIVE_NCHAN``).
NATIVE_FMAX_HZ = 200e6
#: Native channel spacing in Hz (6.1035 kHz).
NATIVE_DF_HZ = NATIVE_FMAX_HZ / NATIVE_NCHAN
#: ADC sample rate assumed when an ACQ header does not give ``acquisition_rate``.
DEFAULT_ADC_RATE_HZ = 400e6
#: Smallest power an ACQ file can hold (-167 dB); FASTSPEC writes it in blank channels.
ACQ_FLOOR = 10.0 ** (-16.7)
#: Largest power an ACQ file can hold (0 dB); larger values are clipped by the encoder.
ACQ_MAX = 1.0
#: Lowest frequency put into an :class:`Observation`, Hz.
MIN_OBS_FREQ_HZ = 1e6
#: Format tag of the HDF5 form.
HDF5_FORMAT = "autocal-edges-spectra-1"
#: What each switch position sees.
SWITCH_POSITIONS = ("p0: antenna", "p1: ambient load", "p2: ambient load + noise source")
#: Auto-correlation definitions :func:`read_edges` can produce.
R_KINDS = ("q", "p0")
R_DEFINITIONS = {
    "q": "Q = (p0 - p1) / (p2 - p1) (three-position-switch ratio, dimensionless)",
    "p0": "p0 (raw antenna power, arbitrary linear units)",
}

RKind = Literal["q", "p0"]


class EdgesFormatError(AutocalError):
    """A file is not a readable EDGES spectrum file (ACQ or autocal HDF5), or is corrupt."""


# ---------------------------------------------------------------------------------------
# grids and times
# ---------------------------------------------------------------------------------------
def native_freqs(nchan: int = NATIVE_NCHAN, fmax_hz: float = NATIVE_FMAX_HZ) -> np.ndarray:
    """Return the native channel centres in Hz: ``k * fmax / nchan``."""
    return np.arange(nchan) * (fmax_hz / nchan)


def channel_bins(
    freqs: np.ndarray,
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
    min_freq: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Select channels and group them into bins.

    Parameters
    ----------
    freqs
        ``(Nfreq,)`` channel centres in Hz, increasing.
    freq_range
        ``(low, high)`` in Hz, inclusive; default all channels.
    bin_factor
        Number of consecutive selected channels per bin.
    min_freq
        Channels below this frequency (Hz) are never selected.

    Returns
    -------
    index : numpy.ndarray
        ``(Nbin, bin_factor)`` indices of the channels in each bin.
    centres : numpy.ndarray
        ``(Nbin,)`` bin centres (mean of the channel centres), Hz.

    Raises
    ------
    ValueError
        If ``bin_factor`` is not a positive integer or nothing is selected.
    """
    if int(bin_factor) != bin_factor or bin_factor < 1:
        raise EdgesFormatError(f"bin_factor must be a positive integer, got {bin_factor!r}")
    bin_factor = int(bin_factor)
    freqs = np.asarray(freqs, dtype=np.float64)
    keep = freqs >= min_freq
    if freq_range is not None:
        lo, hi = sorted(float(v) for v in freq_range)
        keep &= (freqs >= lo) & (freqs <= hi)
    idx = np.flatnonzero(keep)
    nbin = idx.size // bin_factor
    if nbin == 0:
        raise EdgesFormatError(
            f"no complete bin of {bin_factor} channel(s) in {freq_range} Hz (channels "
            f"cover {freqs[0]:.6g}-{freqs[-1]:.6g} Hz): widen freq_range or lower bin_factor"
        )
    if idx.size % bin_factor:
        logger.info(
            "dropping the last %d channel(s) that do not fill a bin of %d",
            idx.size % bin_factor,
            bin_factor,
        )
    index = idx[: nbin * bin_factor].reshape(nbin, bin_factor)
    return index, freqs[index].mean(axis=1)


def acq_time_to_jd(times: Sequence[str] | np.ndarray) -> np.ndarray:
    """Convert ACQ timestamps ``YYYY:DDD:HH:MM:SS`` (UTC) to Julian dates."""
    from astropy.time import Time

    strs = [t.decode() if isinstance(t, bytes | np.bytes_) else str(t) for t in times]
    return np.asarray(Time(strs, format="yday", scale="utc").jd, dtype=np.float64)


def jd_to_acq_time(jds: np.ndarray) -> list[str]:
    """Convert UTC Julian dates to ACQ timestamps, rounded to the nearest second."""
    from astropy.time import Time

    t = Time(np.atleast_1d(np.asarray(jds, dtype=np.float64)), format="jd", scale="utc")
    whole = Time(np.round(t.unix), format="unix", scale="utc")
    return [s[:17] for s in whole.yday]


def lsts_for_jds(jds: np.ndarray, site: Site = EDGES) -> np.ndarray:
    """Local apparent sidereal times in hours (pyuvdata's computation) at ``site``."""
    from pyuvdata.utils import get_lst_for_time

    rad = get_lst_for_time(
        np.atleast_1d(np.asarray(jds, dtype=np.float64)),
        latitude=site.lat_deg,
        longitude=site.lon_deg,
        altitude=site.alt_m,
    )
    return np.mod(np.asarray(rad) * 12.0 / np.pi, 24.0)


# ---------------------------------------------------------------------------------------
# the spectra container
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class EdgesSpectra:
    """Three-position-switch power spectra of one or more EDGES files.

    Parameters
    ----------
    p0, p1, p2
        ``(Ntime, Nfreq)`` raw powers of the antenna, the ambient load and the load plus
        noise source (arbitrary linear units).
    freqs
        ``(Nfreq,)`` channel centres in Hz, increasing.
    jds
        ``(Ntime,)`` UTC Julian dates of the switch cycles.
    channel_width
        Channel width in Hz (scalar or ``(Nfreq,)``).
    integration_time
        Integration time per switch position in seconds (scalar or ``(Ntime,)``).
    aux
        Per-cycle ancillary arrays ``(Ntime, 3)``: ``adcmax``, ``adcmin``, ``data_drops``.
    meta
        Provenance: ``files``, ``sha256``, ``header`` (ACQ header of the first file),
        ``bin_factor``, ``integration_time_source`` and more.
    """

    p0: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    freqs: np.ndarray
    jds: np.ndarray
    channel_width: np.ndarray | float = NATIVE_DF_HZ
    integration_time: np.ndarray | float = 1.0
    aux: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        from autocal.core.reprs import compact_repr

        return compact_repr(self)

    def __post_init__(self) -> None:
        p = [np.atleast_2d(np.asarray(x, dtype=np.float64)) for x in (self.p0, self.p1, self.p2)]
        if not (p[0].shape == p[1].shape == p[2].shape) or p[0].ndim != 2:
            raise EdgesFormatError(
                f"p0, p1, p2 must share one (Ntime, Nfreq) shape; got {[x.shape for x in p]}"
            )
        ntime, nfreq = p[0].shape
        freqs = np.atleast_1d(np.asarray(self.freqs, dtype=np.float64))
        if freqs.shape != (nfreq,):
            raise EdgesFormatError(f"{freqs.size} frequencies for {nfreq} channels")
        if nfreq > 1 and np.any(np.diff(freqs) <= 0):
            raise EdgesFormatError("frequencies must be strictly increasing")
        jds = np.atleast_1d(np.asarray(self.jds, dtype=np.float64))
        if jds.shape != (ntime,):
            raise EdgesFormatError(f"{jds.size} times for {ntime} switch cycles")
        width = np.broadcast_to(np.asarray(self.channel_width, np.float64), (nfreq,)).copy()
        tint = np.broadcast_to(np.asarray(self.integration_time, np.float64), (ntime,)).copy()
        if np.any(~np.isfinite(width) | (width <= 0)):
            raise EdgesFormatError("channel widths must be positive")
        if np.any(~np.isfinite(tint) | (tint <= 0)):
            raise EdgesFormatError("integration times must be positive")
        aux = {}
        for key, value in self.aux.items():
            arr = np.asarray(value)
            if arr.shape[:1] != (ntime,):
                raise EdgesFormatError(
                    f"aux[{key!r}] has shape {arr.shape}; expected ({ntime}, ...)"
                )
            aux[key] = arr
        for name, value in zip(("p0", "p1", "p2"), p, strict=True):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "freqs", freqs)
        object.__setattr__(self, "jds", jds)
        object.__setattr__(self, "channel_width", width)
        object.__setattr__(self, "integration_time", tint)
        object.__setattr__(self, "aux", aux)

    @property
    def ntime(self) -> int:
        """Number of switch cycles."""
        return self.p0.shape[0]

    @property
    def nfreq(self) -> int:
        """Number of channels."""
        return self.p0.shape[1]

    @property
    def q(self) -> np.ndarray:
        """``Q = (p0 - p1) / (p2 - p1)``; NaN where ``p2 <= p1`` (no noise-source step)."""
        den = self.p2 - self.p1
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(den > 0, (self.p0 - self.p1) / den, np.nan)

    def auto(self, r: RKind = "q") -> np.ndarray:
        """Return the auto-correlation ``R`` of the chosen kind (``"q"`` or ``"p0"``)."""
        _check_r(r)
        return self.q if r == "q" else self.p0.copy()

    def variance(self, r: RKind = "q") -> np.ndarray:
        """Radiometer variance of ``R`` per sample, ``(Ntime, Nfreq)``.

        Each power has ``sigma_i = p_i / sqrt(dnu dt)``. For ``Q``, propagated:
        ``var(Q) = [s0^2 + (Q - 1)^2 s1^2 + Q^2 s2^2] / (p2 - p1)^2``.
        """
        _check_r(r)
        bt = self.channel_width[None, :] * self.integration_time[:, None]
        if r == "p0":
            return self.p0**2 / bt
        q = self.q
        den = self.p2 - self.p1
        with np.errstate(divide="ignore", invalid="ignore"):
            num = self.p0**2 + (q - 1.0) ** 2 * self.p1**2 + q**2 * self.p2**2
            return num / (bt * den**2)

    def lsts(self, site: Site = EDGES) -> np.ndarray:
        """Local apparent sidereal times (hours) of the cycles at ``site``."""
        return lsts_for_jds(self.jds, site)

    @property
    def is_native(self) -> bool:
        """Whether the channels lie on the native 0-200 MHz, 32768-channel grid."""
        k = self.freqs / NATIVE_DF_HZ
        return bool(
            np.all(np.abs(k - np.round(k)) < 1e-6)
            and np.all(np.diff(np.round(k)) == 1)
            and np.allclose(self.channel_width, NATIVE_DF_HZ)
        )

    def select(
        self, freq_range: tuple[float, float] | None = None, bin_factor: int = 1
    ) -> EdgesSpectra:
        """Select channels in ``freq_range`` (Hz, inclusive) and average ``bin_factor`` of them."""
        index, centres = channel_bins(self.freqs, freq_range, bin_factor)

        def binned(arr: np.ndarray) -> np.ndarray:
            return arr[:, index].mean(axis=2)

        return replace(
            self,
            p0=binned(self.p0),
            p1=binned(self.p1),
            p2=binned(self.p2),
            freqs=centres,
            channel_width=self.channel_width[index].sum(axis=1),
            meta={**self.meta, "bin_factor": int(self.meta.get("bin_factor", 1)) * int(bin_factor)},
        )

    def sorted(self) -> EdgesSpectra:
        """Return the spectra in time order."""
        order = np.argsort(self.jds, kind="stable")
        if np.all(order == np.arange(self.ntime)):
            return self
        return replace(
            self,
            p0=self.p0[order],
            p1=self.p1[order],
            p2=self.p2[order],
            jds=self.jds[order],
            integration_time=self.integration_time[order],
            aux={k: v[order] for k, v in self.aux.items()},
        )

    def to_observation(self, r: RKind = "q", site: Site = EDGES) -> Observation:
        """Build the :class:`Observation` of auto-correlation ``R`` (antenna 0, pol ``ee``).

        Channels below 1 MHz are left out. Samples where ``R`` is not finite (e.g. ``Q``
        where ``p2 <= p1``) are flagged.
        """
        _check_r(r)
        spec = self.sorted()
        keep = spec.freqs >= MIN_OBS_FREQ_HZ
        if not np.any(keep):
            raise EdgesFormatError("no channel at or above 1 MHz: nothing to put in an Observation")
        data = spec.auto(r)[:, keep]
        meta = {
            **spec.meta,
            "r": r,
            "r_definition": R_DEFINITIONS[r],
            "switch_positions": list(SWITCH_POSITIONS),
        }
        if r == "q":
            meta["noise_note"] = (
                "radiometer weights R/sqrt(dnu dt) do not describe Q; use "
                "EdgesSpectra.variance('q') for inverse-variance weights"
            )
        return Observation(
            data=data[None, None],
            freqs=spec.freqs[keep],
            lsts=spec.lsts(site),
            jds=spec.jds,
            antennas=np.array([0]),
            pols=("ee",),
            site=site,
            channel_width=spec.channel_width[keep],
            integration_time=spec.integration_time,
            antenna_names=("edges",),
            telescope_name="EDGES",
            meta=meta,
        )

    @classmethod
    def concatenate(cls, pieces: Sequence[EdgesSpectra]) -> EdgesSpectra:
        """Join spectra of several files in time (same channels), in time order."""
        if not pieces:
            raise EdgesFormatError("nothing to concatenate")
        first = pieces[0]
        for other in pieces[1:]:
            if other.freqs.shape != first.freqs.shape or not np.allclose(
                other.freqs, first.freqs, rtol=0, atol=1e-3
            ):
                raise EdgesFormatError(
                    f"{other.meta.get('files')} have different channels from "
                    f"{first.meta.get('files')}: read them separately"
                )
        aux_keys = set.intersection(*(set(p.aux) for p in pieces))
        files = [f for p in pieces for f in p.meta.get("files", [])]
        sha = {k: v for p in pieces for k, v in p.meta.get("sha256", {}).items()}
        joined = cls(
            p0=np.concatenate([p.p0 for p in pieces]),
            p1=np.concatenate([p.p1 for p in pieces]),
            p2=np.concatenate([p.p2 for p in pieces]),
            freqs=first.freqs,
            jds=np.concatenate([p.jds for p in pieces]),
            channel_width=first.channel_width,
            integration_time=np.concatenate([p.integration_time for p in pieces]),
            aux={k: np.concatenate([p.aux[k] for p in pieces]) for k in sorted(aux_keys)},
            meta={**first.meta, "files": files, "sha256": sha},
        )
        return joined.sorted()


def _check_r(r: str) -> None:
    if r not in R_KINDS:
        raise EdgesFormatError(f"unknown auto-correlation kind {r!r}: use one of {R_KINDS}")


# ---------------------------------------------------------------------------------------
# ACQ
# ---------------------------------------------------------------------------------------
#: read_acq warnings that only describe header lines without a value (every real file).
_HARMLESS = ("has no value",)


def acq_integration_time(header: dict[str, Any]) -> tuple[float, str]:
    """Integration time per switch position (s) from an ACQ header, and how it was found.

    ``t = nblk * 2 * num_channels / acquisition_rate`` (``acquisition_rate`` in MS/s).
    Without ``num_channels`` or ``acquisition_rate`` in the header, ``nspec`` and
    400 MS/s are used and the source says ``"estimate"``.
    """
    nblk = float(header["nblk"])
    nchan = header.get("num_channels")
    rate = header.get("acquisition_rate")
    source = "nblk * 2 * num_channels / acquisition_rate (ACQ header)"
    if not isinstance(nchan, int | float) or nchan <= 0:
        nchan = float(header.get("nfreq", NATIVE_NCHAN))
        source = "estimate: nblk * 2 * nspec / 400 MS/s (header lacks num_channels)"
    if not isinstance(rate, int | float) or rate <= 0:
        rate_hz = DEFAULT_ADC_RATE_HZ
        source = "estimate: nblk * 2 * nspec / 400 MS/s (header lacks acquisition_rate)"
    else:
        rate_hz = float(rate) * 1e6
    return nblk * 2.0 * float(nchan) / rate_hz, source


def _not_acq(path: Path, why: str) -> EdgesFormatError:
    return EdgesFormatError(
        f"{path} is not a readable EDGES ACQ file ({why}). Check that it is an ACQ "
        "spectrum file written by FASTSPEC (or autocal) and that it was copied completely; "
        "re-copy it from the archive if it is damaged."
    )


def _read_acq_package() -> Any:
    """Import ``read_acq`` with an actionable message when it is missing."""
    try:
        import read_acq
    except ImportError as exc:  # pragma: no cover - a dependency of autocal
        raise ImportError(
            "reading and writing EDGES ACQ files needs the read-acq package (Python >= 3.11): "
            "pip install read-acq"
        ) from exc
    return read_acq


def _decode_acq(path: Path, allow_partial: bool) -> tuple[np.ndarray, np.ndarray, Any]:
    """Decode one ACQ file with read_acq, turning its failures into EdgesFormatError."""
    read_acq = _read_acq_package()
    from read_acq.read_acq import ACQError

    if not path.exists():
        raise FileNotFoundError(f"ACQ file {path} does not exist")
    if path.is_dir():
        raise EdgesFormatError(f"{path} is a folder, not an ACQ file: pass the .acq files in it")
    if path.stat().st_size == 0:
        raise _not_acq(path, "the file is empty")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            _, powers, anc = read_acq.decode_file(path, progress=False)
        except (ACQError, UnicodeDecodeError, ValueError, TypeError, IndexError, KeyError) as exc:
            raise _not_acq(path, f"{type(exc).__name__}: {str(exc)[:200]}") from exc
        except SystemError as exc:
            raise _not_acq(path, f"the spectrum decoder failed: {exc}") from exc
    problems = [str(w.message) for w in caught if not any(h in str(w.message) for h in _HARMLESS)]
    p = [np.atleast_2d(np.asarray(x, dtype=np.float64)) for x in powers]
    ncycle = p[0].shape[1] if p[0].size else 0
    if problems:
        detail = problems[0].strip().splitlines()[0][:160]
        msg = (
            f"{path}: {len(problems)} damaged entr{'y' if len(problems) == 1 else 'ies'} "
            f"(first: {detail!r}); the file is truncated or corrupt"
        )
        if not allow_partial or ncycle == 0:
            raise EdgesFormatError(
                msg + ". Re-copy it from the archive, or pass allow_partial=True to keep the "
                f"{ncycle} complete switch cycle(s) that could be read."
            )
        logger.warning("%s; keeping the %d complete switch cycle(s) read", msg, ncycle)
    if ncycle == 0:
        raise _not_acq(path, "it holds no complete three-position switch cycle (0, 1, 2)")
    nspec = int(anc.meta.get("nfreq", p[0].shape[0]))
    if p[0].shape[0] != nspec:
        raise _not_acq(path, f"{p[0].shape[0]} channels decoded but nspec is {nspec}")
    times = np.asarray(anc.data["times"])
    return np.stack([x.T for x in p]), times, anc


def _acq_one(path: Path, allow_partial: bool) -> EdgesSpectra:
    powers, times, anc = _decode_acq(path, allow_partial)
    header = dict(anc.meta)
    fmin = float(header.get("freq_min", 0.0))
    fmax = float(header.get("freq_max", NATIVE_FMAX_HZ / 1e6))
    nspec = powers.shape[2]
    if fmax <= fmin:
        raise _not_acq(path, f"its band {fmin}-{fmax} MHz is empty")
    if fmin != 0.0:
        logger.warning(
            "%s: freq_min is %s MHz, not 0; channels are placed at freq_min + k (freq_max - "
            "freq_min) / nspec (read_acq would misplace them)",
            path,
            fmin,
        )
    df = (fmax - fmin) * 1e6 / nspec
    freqs = fmin * 1e6 + np.arange(nspec) * df
    # the three timestamps of a cycle are the cycle's time (FASTSPEC writes one per cycle)
    cycle_times = times[:, 0] if times.ndim == 2 else times
    jds = acq_time_to_jd(cycle_times)
    tint, source = acq_integration_time(header)
    aux = {k: np.asarray(v) for k, v in anc.data.items() if k != "times"}
    if "data_drops" in aux and np.any(aux["data_drops"] > 0):
        logger.warning(
            "%s: %d switch spectra report data drops; their integration is shorter than %.3g s",
            path,
            int(np.sum(aux["data_drops"] > 0)),
            tint,
        )
    resolved = str(path.resolve())
    return EdgesSpectra(
        p0=powers[0],
        p1=powers[1],
        p2=powers[2],
        freqs=freqs,
        jds=jds,
        channel_width=df,
        integration_time=tint,
        aux=aux,
        meta={
            "source": "acq",
            "files": [resolved],
            "sha256": {resolved: file_checksum(path)},
            "header": _jsonable(header),
            "bin_factor": 1,
            "native_channel_width_hz": df,
            "integration_time_source": source,
            "time_reference": "cycle timestamp (UTC, 1 s resolution), shared by p0, p1, p2",
        },
    )


def read_acq_spectra(
    paths: str | Path | Sequence[str | Path],
    *,
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
    allow_partial: bool = False,
) -> EdgesSpectra:
    """Read ACQ files into :class:`EdgesSpectra` (joined in time order).

    Parameters
    ----------
    paths
        One ACQ file or several (same channels).
    freq_range
        ``(low, high)`` native channel centres to keep, Hz, inclusive.
    bin_factor
        Average this many consecutive selected channels.
    allow_partial
        Keep the complete switch cycles of a truncated or corrupt file (with a logged
        warning) instead of refusing it.

    Returns
    -------
    EdgesSpectra
        Powers, frequencies (Hz), JDs, channel width, integration time, ancillary data
        (``adcmax``, ``adcmin``, ``data_drops``) and provenance.

    Raises
    ------
    FileNotFoundError
        If a file does not exist.
    EdgesFormatError
        If a file is not ACQ, holds no complete switch cycle, is truncated or corrupt
        (unless ``allow_partial``), or has different channels from the others.
    """
    plist = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    if not plist:
        raise EdgesFormatError("no ACQ files given")
    pieces = []
    for path in plist:
        spec = _acq_one(path, allow_partial)
        if freq_range is not None or bin_factor != 1:
            spec = spec.select(freq_range, bin_factor)
        pieces.append(spec)
        logger.info("%s: %d switch cycle(s), %d channel(s)", path, spec.ntime, spec.nfreq)
    return EdgesSpectra.concatenate(pieces)


def write_acq(
    path: str | Path,
    spectra: EdgesSpectra,
    *,
    header: dict[str, Any] | None = None,
    temperature: int = 0,
) -> Path:
    """Write spectra as an ACQ file (``read_acq.encode``), atomically.

    ACQ holds the native grid only (32768 channels, 0-200 MHz): ``spectra`` must be on it
    (any contiguous run of native channels); the other channels are filled with the
    nearest in-band value (the first 10 with the FASTSPEC floor). The integration time
    is stored as ``nblk`` (``nblk * 2 * 32768 / 400 MS/s``, so it is kept to 164 us).
    Times are rounded to whole seconds. Powers must lie within ``[1e-16.7, 1]``.

    Parameters
    ----------
    path
        Output file.
    spectra
        Native-grid spectra.
    header
        Extra ``;--key: value`` header entries (values must not contain ``": "``).
    temperature
        The ``temp`` field of the comment lines (C, integer).

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    ValueError
        If the spectra are not on the native grid (binned or resampled: write HDF5
        instead), powers are out of the encodable range, or the integration time varies.
    """
    read_acq = _read_acq_package()
    if not spectra.is_native:
        raise EdgesFormatError(
            "ACQ files hold the native 32768-channel 0-200 MHz grid; these spectra are "
            "binned or resampled: write them with write_edges_hdf5 instead"
        )
    powers = np.stack([spectra.p0, spectra.p1, spectra.p2])
    if (
        not np.all(np.isfinite(powers))
        or powers.min() < ACQ_FLOOR * (1 - 1e-9)
        or powers.max() > ACQ_MAX
    ):
        raise EdgesFormatError(
            f"ACQ stores powers between {ACQ_FLOOR:.3g} and {ACQ_MAX} (-167 to 0 dB); these "
            f"span {np.nanmin(powers):.3g}-{np.nanmax(powers):.3g}: rescale them"
        )
    tint = spectra.integration_time
    if np.ptp(tint) > 1e-9 * tint.max():
        raise EdgesFormatError("ACQ stores one integration time per file; write one file per value")
    nblk = max(1, round(float(tint[0]) * DEFAULT_ADC_RATE_HZ / (2 * NATIVE_NCHAN)))
    chan = np.round(spectra.freqs / NATIVE_DF_HZ).astype(int)
    full = np.empty((3, spectra.ntime, NATIVE_NCHAN))
    full[:, :, chan[0] : chan[-1] + 1] = powers
    full[:, :, : chan[0]] = powers[:, :, :1]
    full[:, :, chan[-1] + 1 :] = powers[:, :, -1:]
    full[:, :, : min(10, int(chan[0]))] = ACQ_FLOOR
    meta: dict[str, Any] = {
        "fastspec_version": "autocal",
        "site": "edges",
        "instrument": "autocal",
        "acquisition_rate": int(DEFAULT_ADC_RATE_HZ / 1e6),
        "num_channels": NATIVE_NCHAN,
        **(header or {}),
    }
    for key, value in meta.items():
        if ": " in str(value) or "\n" in str(value):
            raise EdgesFormatError(f"header value of {key!r} must not contain ': ' or a newline")
    meta.update(
        {
            "temperature": int(temperature),
            "nblk": int(nblk),
            "nfreq": NATIVE_NCHAN,
            "freq_min": 0.0,
            "freq_max": NATIVE_FMAX_HZ / 1e6,
            "freq_res": round(NATIVE_DF_HZ / 1e6, 6),
        }
    )
    ntime = spectra.ntime
    ancillary = {
        "times": np.array(jd_to_acq_time(spectra.jds)),
        "adcmax": np.asarray(spectra.aux.get("adcmax", np.full((ntime, 3), 0.25)), np.float64),
        "adcmin": np.asarray(spectra.aux.get("adcmin", np.full((ntime, 3), -0.25)), np.float64),
        "data_drops": np.asarray(
            spectra.aux.get("data_drops", np.zeros((ntime, 3), int)), dtype=np.int64
        ),
    }
    path = Path(path)
    with atomic_path(path) as tmp:
        read_acq.encode(tmp, p=list(full), meta=meta, ancillary=ancillary)
    logger.info("wrote %s: %d switch cycle(s)", path, ntime)
    return path


# ---------------------------------------------------------------------------------------
# HDF5
# ---------------------------------------------------------------------------------------
def _jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value, default=str))


def write_edges_hdf5(path: str | Path, spectra: EdgesSpectra, history: str = "") -> Path:
    """Write spectra to the autocal EDGES HDF5 layout (see the module doc), atomically.

    Parameters
    ----------
    path
        Output file.
    spectra
        The spectra (native or binned).
    history
        Free text appended to the provenance.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    import h5py

    from autocal import __version__

    path = Path(path)
    meta = spectra.meta
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        for name in ("p0", "p1", "p2"):
            h5.create_dataset(name, data=getattr(spectra, name))
        h5.create_dataset("freqs", data=spectra.freqs)
        h5.create_dataset("channel_width", data=spectra.channel_width)
        h5.create_dataset("jds", data=spectra.jds)
        h5.create_dataset("integration_time", data=spectra.integration_time)
        for key, value in spectra.aux.items():
            h5.create_dataset(f"aux/{key}", data=value)
        h5["freqs"].attrs["unit"] = "Hz"
        h5["channel_width"].attrs["unit"] = "Hz"
        h5["jds"].attrs["unit"] = "Julian date (UTC)"
        h5["integration_time"].attrs["unit"] = "s per switch position"
        attrs = h5.attrs
        attrs["format"] = HDF5_FORMAT
        attrs["telescope_name"] = "EDGES"
        attrs["switch_positions"] = json.dumps(list(SWITCH_POSITIONS))
        attrs["time_scale"] = "utc"
        attrs["bin_factor"] = int(meta.get("bin_factor", 1))
        attrs["native_channel_width_hz"] = float(meta.get("native_channel_width_hz", NATIVE_DF_HZ))
        attrs["header"] = json.dumps(_jsonable(meta.get("header", {})), sort_keys=True)
        attrs["files"] = json.dumps(list(meta.get("files", [])))
        attrs["sha256"] = json.dumps(dict(meta.get("sha256", {})), sort_keys=True)
        attrs["integration_time_source"] = str(meta.get("integration_time_source", "unknown"))
        attrs["history"] = "\n".join(
            s
            for s in (str(meta.get("history", "")), f"written by autocal {__version__}", history)
            if s
        )
    logger.info("wrote %s: %d cycle(s) x %d channel(s)", path, spectra.ntime, spectra.nfreq)
    return path


def read_edges_hdf5(
    path: str | Path,
    *,
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
) -> EdgesSpectra:
    """Read spectra written by :func:`write_edges_hdf5`.

    Parameters
    ----------
    path
        The HDF5 file.
    freq_range, bin_factor
        As for :func:`read_acq_spectra` (applied to the stored channels).

    Returns
    -------
    EdgesSpectra
        The stored spectra; ``meta["files"]`` names the HDF5 file, ``meta["parents"]``
        the files it was made from.

    Raises
    ------
    EdgesFormatError
        If the file is not HDF5, not in this layout, or damaged.
    """
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"EDGES HDF5 file {path} does not exist")
    try:
        with h5py.File(path, "r") as h5:
            fmt = h5.attrs.get("format", "")
            fmt = fmt.decode() if isinstance(fmt, bytes) else str(fmt)
            if fmt != HDF5_FORMAT:
                raise EdgesFormatError(
                    f"{path} is HDF5 but not an autocal EDGES spectra file (format "
                    f"{fmt!r}, expected {HDF5_FORMAT!r}); write it with write_edges_hdf5"
                )
            arrays = {
                k: h5[k][()]
                for k in ("p0", "p1", "p2", "freqs", "channel_width", "jds", "integration_time")
            }
            aux = {k: h5["aux"][k][()] for k in h5["aux"]} if "aux" in h5 else {}
            attrs = {k: h5.attrs[k] for k in h5.attrs}
    except EdgesFormatError:
        raise
    except (OSError, KeyError, ValueError) as exc:
        raise EdgesFormatError(
            f"{path} is not a readable autocal EDGES HDF5 file ({type(exc).__name__}: "
            f"{str(exc)[:200]}); re-create it with write_edges_hdf5 or re-copy it"
        ) from exc
    resolved = str(path.resolve())

    def text(key: str, default: str) -> str:
        v = attrs.get(key, default)
        return v.decode() if isinstance(v, bytes) else str(v)

    try:
        spec = EdgesSpectra(
            p0=arrays["p0"],
            p1=arrays["p1"],
            p2=arrays["p2"],
            freqs=arrays["freqs"],
            jds=arrays["jds"],
            channel_width=arrays["channel_width"],
            integration_time=arrays["integration_time"],
            aux=aux,
            meta={
                "source": "edges-hdf5",
                "files": [resolved],
                "sha256": {resolved: file_checksum(path)},
                "parents": json.loads(text("files", "[]")),
                "parent_sha256": json.loads(text("sha256", "{}")),
                "header": json.loads(text("header", "{}")),
                "bin_factor": int(attrs.get("bin_factor", 1)),
                "native_channel_width_hz": float(
                    attrs.get("native_channel_width_hz", NATIVE_DF_HZ)
                ),
                "integration_time_source": text("integration_time_source", "unknown"),
                "history": text("history", ""),
            },
        )
    except ValueError as exc:
        raise EdgesFormatError(f"{path}: inconsistent EDGES HDF5 contents ({exc})") from exc
    if freq_range is not None or bin_factor != 1:
        spec = spec.select(freq_range, bin_factor)
    return spec


# ---------------------------------------------------------------------------------------
# entry points
# ---------------------------------------------------------------------------------------
def _is_hdf5(path: Path) -> bool:
    try:
        with path.open("rb") as handle:
            return handle.read(8) == b"\x89HDF\r\n\x1a\n"
    except OSError:
        return False


def read_edges_spectra(
    paths: str | Path | Sequence[str | Path],
    *,
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
    allow_partial: bool = False,
) -> EdgesSpectra:
    """Read ACQ or autocal-HDF5 EDGES files (recognised by content) into one time series.

    Parameters are as for :func:`read_acq_spectra`.
    """
    plist = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    if not plist:
        raise EdgesFormatError("no EDGES files given")
    pieces = []
    for path in plist:
        if path.is_file() and _is_hdf5(path):
            pieces.append(read_edges_hdf5(path, freq_range=freq_range, bin_factor=bin_factor))
        else:
            pieces.append(
                read_acq_spectra(
                    path, freq_range=freq_range, bin_factor=bin_factor, allow_partial=allow_partial
                )
            )
    return EdgesSpectra.concatenate(pieces)


def read_edges(
    paths: str | Path | Sequence[str | Path],
    *,
    r: RKind = "q",
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
    site: Site = EDGES,
    allow_partial: bool = False,
) -> Observation:
    """Read EDGES spectra (ACQ or HDF5) into an :class:`Observation`.

    Parameters
    ----------
    paths
        One file or several of one observation (joined in time order).
    r
        ``"q"``: ``Q = (p0 - p1) / (p2 - p1)``; ``"p0"``: raw antenna power.
    freq_range
        ``(low, high)`` in Hz, inclusive (native channels); channels below 1 MHz are
        always left out.
    bin_factor
        Average this many consecutive channels (e.g. 64: 390.6 kHz channels).
    site
        Telescope site (default the EDGES site at the MRO).
    allow_partial
        Keep the complete cycles of truncated or corrupt ACQ files.

    Returns
    -------
    Observation
        ``data`` ``(1, 1, Ntime, Nfreq)`` (antenna 0, pol ``ee``), LSTs at ``site``,
        ``channel_width``, ``integration_time`` per switch position, ``telescope_name``
        "EDGES", ``meta`` with ``files``, ``sha256``, ``header``, ``r``,
        ``r_definition``, ``bin_factor``, ``integration_time_source``.

    Raises
    ------
    EdgesFormatError
        For unreadable, corrupt or inconsistent files.
    """
    spec = read_edges_spectra(
        paths, freq_range=freq_range, bin_factor=bin_factor, allow_partial=allow_partial
    )
    return spec.to_observation(r=r, site=site)
