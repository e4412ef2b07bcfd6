"""Raw EDGES three-position-switch spectra: the container, native grid and channel bins.

An EDGES receiver cycles a three-position switch and records one power spectrum per
position: ``p0`` the antenna, ``p1`` the internal ambient load, ``p2`` the load plus the
noise source. :class:`EdgesSpectra` holds them (``(Ntime, Nfreq)`` each) with their
channels, cycle times and provenance, and turns them into an
:class:`autocal.core.observation.Observation` whose auto-correlation ``R`` is

- ``"q"``: the partially calibrated ratio ``Q = (p0 - p1) / (p2 - p1)`` (default), or
- ``"p0"``: the raw antenna power.

The spectrometer (FASTSPEC) writes *ACQ* files (:mod:`autocal.io.edges_acq`); autocal
also keeps spectra in an HDF5 layout (:mod:`autocal.io.edges_hdf5`);
:func:`autocal.io.edges_read.read_edges` reads either. The native grid is 32768 channels
over 0-200 MHz (channel ``k`` at ``k * 200 MHz / 32768``, :func:`native_freqs`).

Frequency selection and binning: ``freq_range`` selects native channels (inclusive),
then ``bin_factor`` consecutive channels are averaged (linear power; a last incomplete
bin is dropped; :func:`channel_bins`). ``Q`` is formed from the binned powers. Channels
below 1 MHz are never put in an :class:`Observation` (FASTSPEC blanks them, and
frequencies must be >= 100 kHz).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from autocal.core.observation import Observation
from autocal.core.reprs import compact_repr
from autocal.core.sites import EDGES, Site
from autocal.errors import AutocalError
from autocal.io.edges_time import lsts_for_jds

logger = logging.getLogger(__name__)

#: Channels of a native FASTSPEC spectrum.
NATIVE_NCHAN = 32768
#: Top of the native band in Hz (channel ``k`` is at ``k * NATIVE_FMAX_HZ / NATIVE_NCHAN``).
NATIVE_FMAX_HZ = 200e6
#: Native channel spacing in Hz (6.1035 kHz).
NATIVE_DF_HZ = NATIVE_FMAX_HZ / NATIVE_NCHAN
#: Lowest frequency put into an :class:`Observation`, Hz.
MIN_OBS_FREQ_HZ = 1e6
#: What each switch position sees.
SWITCH_POSITIONS = ("p0: antenna", "p1: ambient load", "p2: ambient load + noise source")
#: Auto-correlation definitions :meth:`EdgesSpectra.to_observation` can produce.
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


def jsonable(value: Any) -> Any:
    """Return ``value`` as plain JSON types (anything else as its string), for provenance."""
    return json.loads(json.dumps(value, default=str))
