"""Antenna power beams in topocentric coordinates.

Convention: a beam is evaluated at directions given by the azimuth ``az`` measured from
north through east (astropy's convention) and the zenith angle ``za`` in ``[0, pi]``,
both in radians, and returns the power pattern ``A(nu, az, za)`` (any normalisation:
Tsky divides by the beam integral). Directions with ``za > pi/2`` are below the horizon;
their beam weight sees the ground.

Polarisations: ``ee`` is the east-west dipole (the "XX" of older HERA papers), ``nn`` the
north-south one. An east-west dipole's pattern is wider along north-south (its H-plane).

A dish fed by a dipole behaves the other way round in its main lobe: the feed's narrower
E-plane pattern under-illuminates the dish along the dipole, so the HERA ``ee`` primary
beam is *wider* east-west near zenith (tested against the Fagnoni file).

pyuvdata's UVBeam measures azimuth from east through north, so ``az_uvbeam = pi/2 - az``;
EDGES FEKO files measure azimuth from the antenna's excitation axis, rotated to true
azimuth by ``rotation_from_north`` (edges-analysis default: 90 deg).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import healpy as hp
import numpy as np
from scipy.interpolate import CubicSpline
from scipy.special import j1

from autocal.core.files import file_checksum
from autocal.errors import AutocalError

logger = logging.getLogger(__name__)

C_LIGHT = 299792458.0
POLS = ("ee", "nn")


class BeamError(AutocalError):
    """A beam cannot be built or evaluated as asked."""


class BeamEvaluator:
    """A beam bound to a fixed set of directions, evaluated frequency by frequency.

    Returned by :meth:`Beam.on`; file beams precompute their spatial interpolation here
    so that evaluating many frequency chunks costs one frequency interpolation each.
    """

    #: True if values can never be negative (NaN may still appear): the Tsky engine then
    #: skips its per-value sign check and relies on the beam integrals being finite.
    nonnegative: bool = False

    def __init__(self, beam: Beam, az: np.ndarray, za: np.ndarray) -> None:
        self.beam = beam
        self.az = np.asarray(az, dtype=np.float64)
        self.za = np.asarray(za, dtype=np.float64)

    def __call__(self, freqs: np.ndarray) -> np.ndarray:
        """Return ``(Nfreq, Ndir)`` beam values at ``freqs`` (Hz)."""
        return self.beam.power(freqs, self.az, self.za)

    def by_direction(self, freqs: np.ndarray, rows: slice | None = None) -> np.ndarray:
        """Return the values direction-major: C-contiguous ``(Nrows, Nfreq)``.

        Parameters
        ----------
        freqs
            Frequencies in Hz.
        rows
            The directions to evaluate (a slice of the bound ones; ``None``: all).

        Notes
        -----
        The Tsky engine evaluates the beam block by block of directions, with the
        frequencies as the fastest axis (it Fourier-transforms along HEALPix rings).
        Evaluators that can produce this layout directly override this method.
        It may be called from several threads at once.
        """
        rows = slice(None) if rows is None else rows
        return np.ascontiguousarray(self.beam.power(freqs, self.az[rows], self.za[rows]).T)


class Beam(ABC):
    """A frequency-dependent power beam."""

    name: str = "beam"
    pol: str = "ee"

    @property
    def freq_range(self) -> tuple[float, float] | None:
        """Range of valid frequencies in Hz, or ``None`` if unbounded."""
        return None

    def check_freqs(self, freqs: np.ndarray) -> np.ndarray:
        """Validate a frequency array (Hz) against this beam, returning it as float64."""
        freqs = np.atleast_1d(np.asarray(freqs, dtype=np.float64))
        if freqs.size == 0:
            raise BeamError("the frequency grid is empty: give at least one frequency")
        if not np.all(np.isfinite(freqs)) or np.any(freqs <= 0):
            raise BeamError("frequencies must be finite and positive (Hz)")
        rng = self.freq_range
        if rng is not None:
            lo, hi = rng
            tol = 1e-6 * hi
            if freqs.min() < lo - tol or freqs.max() > hi + tol:
                raise BeamError(
                    f"frequencies {freqs.min() / 1e6:.3f}-{freqs.max() / 1e6:.3f} MHz are "
                    f"outside the {self.name} beam's range {lo / 1e6:.3f}-{hi / 1e6:.3f} MHz"
                )
        return freqs

    @abstractmethod
    def power(self, freqs: np.ndarray, az: np.ndarray, za: np.ndarray) -> np.ndarray:
        """Return the power beam ``(Nfreq, Ndir)`` at ``freqs`` (Hz) and directions (rad)."""

    def on(self, az: np.ndarray, za: np.ndarray) -> BeamEvaluator:
        """Bind the beam to fixed directions (see :class:`BeamEvaluator`)."""
        return BeamEvaluator(self, az, za)

    @abstractmethod
    def describe(self) -> dict[str, Any]:
        """Return a JSON-serialisable description (provenance and cache keys)."""


def _check_pol(pol: str) -> str:
    pol = pol.lower()
    if pol not in POLS:
        raise BeamError(f"polarisation {pol!r} not supported: use one of {POLS}")
    return pol


@dataclass(frozen=True)
class GaussianDipoleBeam(Beam):
    """Gaussian dipole beam with the elliptical azimuth factor of the paper.

    ``A = exp(-(theta/theta0)^2) / (sqrt(pi) theta0) * (cos^2 phi + sin^2 phi cos theta)^2``
    with ``theta0 = FWHM / (2 sqrt(ln 2))``, ``FWHM = fwhm_ref (nu / nu_ref)^-1`` and ``phi``
    the azimuth from the dipole's H-plane: from north for ``ee`` (so the beam is wider
    north-south), from east for ``nn``.
    """

    pol: str = "ee"
    fwhm_ref_deg: float = 72.0
    nu_ref: float = 140e6
    name: str = "dipole"

    def __post_init__(self) -> None:
        object.__setattr__(self, "pol", _check_pol(self.pol))

    def fwhm(self, freqs: np.ndarray) -> np.ndarray:
        """FWHM in radians at ``freqs`` (Hz)."""
        return np.radians(self.fwhm_ref_deg) * (np.asarray(freqs) / self.nu_ref) ** -1

    def power(self, freqs, az, za):  # noqa: D102
        freqs = self.check_freqs(freqs)
        az, za = np.asarray(az), np.asarray(za)
        theta0 = self.fwhm(freqs)[:, None] / (2 * np.sqrt(np.log(2)))
        radial = np.exp(-((za[None, :] / theta0) ** 2)) / (np.sqrt(np.pi) * theta0)
        phi = az if self.pol == "ee" else az - np.pi / 2
        azfac = (np.cos(phi) ** 2 + np.sin(phi) ** 2 * np.cos(za)) ** 2
        return radial * azfac[None, :]

    def describe(self):  # noqa: D102
        return {
            "beam": "gaussian_dipole",
            "pol": self.pol,
            "fwhm_ref_deg": self.fwhm_ref_deg,
            "nu_ref_Hz": self.nu_ref,
        }


@dataclass(frozen=True)
class AiryBeam(Beam):
    """Airy pattern of a uniformly illuminated dish: ``[2 J1(x) / x]^2``.

    ``x = pi D sin(theta) / lambda``. A dish has no back lobe: the pattern is zero below
    the horizon, reached through a smoothstep over the ``horizon_taper_deg`` above it
    (a hard edge in the beam would add pixelisation noise to Tsky; the sidelobes there
    are ~1e-4 of the peak). Polarisation-independent.
    """

    diameter: float = 14.0
    pol: str = "ee"
    horizon_taper_deg: float = 2.0
    name: str = "airy"

    def __post_init__(self) -> None:
        object.__setattr__(self, "pol", _check_pol(self.pol))
        if not self.diameter > 0:
            raise BeamError("dish diameter must be positive (metres)")

    def power(self, freqs, az, za):  # noqa: D102
        freqs = self.check_freqs(freqs)
        za = np.asarray(za)
        lam = C_LIGHT / freqs
        x = np.pi * self.diameter * np.sin(za)[None, :] / lam[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(x == 0, 1.0, (2 * j1(x) / np.where(x == 0, 1.0, x)) ** 2)
        if self.horizon_taper_deg > 0:
            t = np.clip((np.pi / 2 - za) / np.radians(self.horizon_taper_deg), 0.0, 1.0)
            taper = t * t * (3 - 2 * t)
        else:
            taper = (za <= np.pi / 2).astype(np.float64)
        return out * taper[None, :]

    def describe(self):  # noqa: D102
        return {
            "beam": "airy",
            "diameter_m": self.diameter,
            "horizon_taper_deg": self.horizon_taper_deg,
        }


@dataclass(frozen=True)
class FunctionBeam(Beam):
    """A beam from any callable ``func(freqs, az, za) -> (Nfreq, Ndir)``.

    ``key`` identifies the function in descriptions and cache keys.
    """

    func: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] = field(compare=False)
    key: str = "function"
    pol: str = "ee"
    name: str = "function"

    def power(self, freqs, az, za):  # noqa: D102
        freqs = self.check_freqs(freqs)
        out = np.asarray(self.func(freqs, np.asarray(az), np.asarray(za)), dtype=np.float64)
        return np.broadcast_to(out, (freqs.size, np.size(az))).copy()

    def describe(self):  # noqa: D102
        return {"beam": "function", "key": self.key, "pol": self.pol}


# error model ----------------------------------------------------------------------------


def s1_airy(freqs: np.ndarray, diameter: float = 14.0) -> np.ndarray:
    """``s1 = 7.0156 lambda / (pi D)``: sine of the Airy pattern's second null."""
    return 7.0156 * (C_LIGHT / np.asarray(freqs)) / (np.pi * diameter)


def s1_dipole(freqs: np.ndarray, beam: GaussianDipoleBeam | None = None) -> np.ndarray:
    """``s1 = sin(FWHM / 2)`` of the Gaussian dipole."""
    beam = beam or GaussianDipoleBeam()
    return np.sin(beam.fwhm(freqs) / 2)


@dataclass(frozen=True)
class PerturbedBeam(Beam):
    """The paper's beam error model around any beam: ``A_E = A_0 (1 + f(theta))^2``.

    ``f = 1 - (1 - e_z) exp(-sin^2(theta) / (2 sigma_e^2))`` for ``|sin theta| < s1``,
    constant (its value at ``s1``) beyond, and below the horizon; ``sigma_e =
    sigma_scale * s1``. ``s1`` depends on frequency: :func:`s1_airy` for dishes,
    :func:`s1_dipole` for dipoles.
    """

    base: Beam = field(default_factory=GaussianDipoleBeam)
    s1: Callable[[np.ndarray], np.ndarray] = field(default=s1_dipole, compare=False)
    s1_kind: str = "dipole"
    e_z: float = 0.06
    sigma_scale: float = 1.5
    name: str = "perturbed"

    @property
    def pol(self) -> str:  # type: ignore[override]
        """Polarisation of the underlying beam."""
        return self.base.pol

    @property
    def freq_range(self):  # noqa: D102
        return self.base.freq_range

    def factor(self, freqs: np.ndarray, za: np.ndarray) -> np.ndarray:
        """Return ``(1 + f)^2`` as ``(Nfreq, Ndir)``."""
        s1 = np.asarray(self.s1(np.asarray(freqs)))[:, None]
        sig = self.sigma_scale * s1
        sin_t = np.where(np.asarray(za) <= np.pi / 2, np.sin(za), np.inf)[None, :]
        s_eff = np.minimum(np.abs(sin_t), s1)
        f = 1 - (1 - self.e_z) * np.exp(-(s_eff**2) / (2 * sig**2))
        return (1 + f) ** 2

    def power(self, freqs, az, za):  # noqa: D102
        freqs = self.check_freqs(freqs)
        return self.base.power(freqs, az, za) * self.factor(freqs, za)

    def on(self, az, za):  # noqa: D102
        inner = self.base.on(az, za)
        outer = self

        class _Eval(BeamEvaluator):
            def __call__(self, freqs):
                freqs = outer.check_freqs(freqs)
                return inner(freqs) * outer.factor(freqs, self.za)

            def by_direction(self, freqs, rows=None):
                freqs = outer.check_freqs(freqs)
                rows = slice(None) if rows is None else rows
                return inner.by_direction(freqs, rows) * outer.factor(freqs, self.za[rows]).T

        return _Eval(self, az, za)

    def describe(self):  # noqa: D102
        return {
            "beam": "perturbed",
            "base": self.base.describe(),
            "s1": self.s1_kind,
            "e_z": self.e_z,
            "sigma_scale": self.sigma_scale,
        }


# file beams -----------------------------------------------------------------------------


class _GriddedFileBeam(Beam):
    """Common frequency interpolation of beams tabulated at native frequencies.

    A cubic spline in frequency (scipy's ``CubicSpline``, not-a-knot ends) through the
    tabulated values ``y_j``, clipped at zero. It is evaluated in its local form: on the
    interval ``[x_i, x_i+1]`` (width ``h``, ``a = (x_i+1 - x) / h``, ``b = 1 - a``)

        S(x) = a y_i + b y_i+1 + [(a^3 - a) M_i + (b^3 - b) M_i+1] h^2 / 6

    with the knot second derivatives ``M = Q y`` (``Q`` from the spline of the identity).
    So every frequency needs four tabulated rows and a band of neighbouring frequencies a
    handful, whatever the number of native frequencies.
    """

    native_freqs: np.ndarray

    @property
    def freq_range(self):
        return float(self.native_freqs[0]), float(self.native_freqs[-1])

    @abstractmethod
    def _spatial(self, az: np.ndarray, za: np.ndarray) -> np.ndarray:
        """Beam at native frequencies ``(Nnative, Ndir)``."""

    def _spatial_t(self, az: np.ndarray, za: np.ndarray) -> np.ndarray:
        """Beam at native frequencies, direction-major ``(Ndir, Nnative)`` float64."""
        return np.ascontiguousarray(self._spatial(az, za).T)

    def _knots(self, native_t: np.ndarray) -> np.ndarray:
        """Interleave values and second derivatives: ``(Ndir, 2 Nnative)`` = y0 M0 y1 M1..."""
        nat = self.native_freqs.size
        out = np.empty((native_t.shape[0], 2 * nat))
        out[:, 0::2] = native_t
        out[:, 1::2] = native_t @ self._curvature.T
        return out

    @cached_property
    def _curvature(self) -> np.ndarray:
        """``(Nnative, Nnative)`` matrix ``Q``: knot second derivatives ``M = Q y``."""
        nat = self.native_freqs.size
        if nat < 3:  # constant or linear: no curvature
            return np.zeros((nat, nat))
        spline = CubicSpline(self.native_freqs, np.eye(nat), axis=0)
        return spline.derivative(2)(self.native_freqs)  # (knot, basis)

    def _local_weights(self, freqs: np.ndarray) -> tuple[slice, np.ndarray]:
        """Rows of :meth:`_knots` used by ``freqs`` and their ``(Nrows, Nfreq)`` weights."""
        x = self.native_freqs
        if x.size == 1:
            return slice(0, 1), np.ones((1, freqs.size))
        f = np.clip(freqs, *self.freq_range)
        i = np.clip(np.searchsorted(x, f, side="right") - 1, 0, x.size - 2)
        h = x[i + 1] - x[i]
        a = (x[i + 1] - f) / h
        b = 1.0 - a
        first = 2 * int(i.min())
        rows = 2 * int(i.max()) + 4 - first
        weights = np.zeros((rows, f.size))
        cols = np.arange(f.size)
        r = 2 * i - first
        weights[r, cols] = a
        weights[r + 1, cols] = (a**3 - a) * h**2 / 6
        weights[r + 2, cols] = b
        weights[r + 3, cols] = (b**3 - b) * h**2 / 6
        return slice(first, first + rows), weights

    def _interp_freq(self, native: np.ndarray, freqs: np.ndarray) -> np.ndarray:
        rows, weights = self._local_weights(freqs)
        out = weights.T @ self._knots(native.T)[:, rows].T
        return np.maximum(out, 0.0, out=out)

    def power(self, freqs, az, za):
        freqs = self.check_freqs(freqs)
        return self._interp_freq(self._spatial(np.asarray(az), np.asarray(za)), freqs)

    def on(self, az, za):
        return _GriddedEvaluator(self, az, za)


class _GriddedEvaluator(BeamEvaluator):
    """A gridded file beam bound to directions, with its spline knots precomputed.

    Holds the ``(Ndir, 2 Nnative)`` knot table (values and second derivatives in
    frequency, see :class:`_GriddedFileBeam`); a chunk of frequencies costs one thin
    matrix product with the few knot columns it needs, then the clip at zero.
    """

    #: Largest ``rows x Nfreq`` of one matrix product in :meth:`by_direction`: such small
    #: products run single-threaded in OpenBLAS, which avoids its thread hand-offs (they
    #: dominate for these thin memory-bound products, badly so on a busy machine).
    _BLOCK = 16384
    nonnegative = True  # clipped at zero

    def __init__(self, beam: _GriddedFileBeam, az: np.ndarray, za: np.ndarray) -> None:
        super().__init__(beam, az, za)
        self.beam: _GriddedFileBeam = beam
        self._table = beam._knots(beam._spatial_t(self.az, self.za))
        self._memo: dict[bytes, tuple[slice, np.ndarray]] = {}

    def _weights(self, freqs: np.ndarray) -> tuple[slice, np.ndarray]:
        """Return the checked local spline weights (memoised for recent ``freqs``).

        The engine asks for the same frequency chunk block after block of directions.
        """
        freqs = np.asarray(freqs, dtype=np.float64)
        key = freqs.tobytes()
        hit = self._memo.get(key)
        if hit is None:
            hit = self.beam._local_weights(self.beam.check_freqs(freqs))
            if len(self._memo) >= 16:
                self._memo.clear()
            self._memo[key] = hit
        return hit

    def __call__(self, freqs: np.ndarray) -> np.ndarray:
        """Return ``(Nfreq, Ndir)`` beam values at ``freqs`` (Hz)."""
        rows, weights = self._weights(freqs)
        out = weights.T @ self._table[:, rows].T
        return np.maximum(out, 0.0, out=out)

    def by_direction(self, freqs: np.ndarray, rows: slice | None = None) -> np.ndarray:
        """Return ``(Nrows, Nfreq)`` beam values (see :meth:`BeamEvaluator.by_direction`)."""
        cols, weights = self._weights(freqs)
        table = self._table[:, cols] if rows is None else self._table[rows, cols]
        nf = weights.shape[1]
        out = np.empty((table.shape[0], nf))
        step = max(16, self._BLOCK // nf)
        for start in range(0, table.shape[0], step):
            np.matmul(table[start : start + step], weights, out=out[start : start + step])
        return np.maximum(out, 0.0, out=out)


def _upsampled(path: str, pol: str, nside_out: int, mtime: int, maps: np.ndarray) -> np.ndarray:
    """Harmonic upsampling of beam maps, memoised per file, pol and resolution.

    Returns the direction-major ``(Npix_out, Nfreq)`` float32 maps (bilinear
    interpolation then reads each neighbour's spectrum contiguously).
    """
    key = (path, pol, nside_out, mtime)
    if key not in _UPSAMPLED:
        nside = hp.npix2nside(maps.shape[1])
        lmax = 3 * nside - 1
        fine = np.empty((hp.nside2npix(nside_out), maps.shape[0]), dtype=np.float32)
        for i, m in enumerate(maps):
            fine[:, i] = hp.alm2map(hp.map2alm(m, lmax=lmax, iter=3), nside_out, lmax=lmax)
        _UPSAMPLED.clear()  # keep one beam's maps (~330 MB at nside 512 for 26 freqs)
        _UPSAMPLED[key] = np.maximum(fine, 0.0, out=fine)
    return _UPSAMPLED[key]


_UPSAMPLED: dict[tuple, np.ndarray] = {}


class HealpixFileBeam(_GriddedFileBeam):
    """A HEALPix power beam read with pyuvdata (e.g. the HERA Fagnoni beamfits).

    The stored maps (zenith at the pole, pyuvdata azimuth from east through north) are
    upsampled once, on first evaluation, by spherical-harmonic interpolation (band limit
    ``3 nside - 1`` of the file) to ``upsample_nside`` (stored as float32), then
    interpolated bilinearly: the beam is smooth, so evaluating it on rotated grids does
    not add pixel-scale noise. A cubic spline interpolates in frequency.
    """

    def __init__(self, path: str | Path, pol: str = "ee", upsample_nside: int = 512) -> None:
        from autocal.io.beamfits import read_healpix_power_beam

        self.path = Path(path)
        self.pol = _check_pol(pol)
        self.data = read_healpix_power_beam(self.path, self.pol)
        self.native_freqs = self.data.freqs
        self.name = self.path.name
        nside = self.data.nside
        full = np.zeros((self.data.freqs.size, hp.nside2npix(nside)))
        pix = self.data.pixels
        if self.data.nest:
            pix = hp.nest2ring(nside, pix)
        full[:, pix] = self.data.data
        if pix.size != hp.nside2npix(nside):
            logger.warning(
                "%s covers %d of %d pixels; missing ones are zero",
                self.path,
                pix.size,
                hp.nside2npix(nside),
            )
        self.upsample_nside = max(int(upsample_nside), nside)
        self._native_maps = full

    @cached_property
    def _maps_t(self) -> np.ndarray:
        """Direction-major ``(Npix, Nfreq)`` maps, upsampled on first evaluation.

        Not at construction: naming the beam (:meth:`describe`, the Tsky cache key) and
        checking frequencies need only the file, so a Tsky cache hit skips the harmonic
        upsampling (~1.7 s and ~330 MB per polarisation for the HERA beam).
        """
        nside = hp.npix2nside(self._native_maps.shape[1])
        if self.upsample_nside > nside:
            return _upsampled(
                str(self.path.resolve()),
                self.pol,
                self.upsample_nside,
                self.path.stat().st_mtime_ns,
                self._native_maps,
            )
        return np.ascontiguousarray(self._native_maps.T)  # (Npix, Nfreq)

    def _spatial(self, az, za):
        return self._spatial_t(az, za).T

    def _spatial_t(self, az, za):
        phi = np.mod(np.pi / 2 - np.asarray(az), 2 * np.pi)  # pyuvdata: east to north
        theta = np.clip(za, 0.0, np.pi)
        theta, phi = np.atleast_1d(theta).ravel(), np.atleast_1d(phi).ravel()
        # healpy's bilinear interpolation (as hp.get_interp_val), with the neighbours and
        # weights found once for all native frequencies
        nside = hp.npix2nside(self._maps_t.shape[0])
        pix, wgt = hp.get_interp_weights(nside, theta, phi)
        out = self._maps_t[pix[0]] * wgt[0][:, None]
        for k in range(1, 4):
            out += self._maps_t[pix[k]] * wgt[k][:, None]
        return out

    def describe(self):  # noqa: D102
        return {
            "beam": "uvbeam_healpix",
            "file": str(self.path),
            "pol": self.pol,
            "upsample_nside": self.upsample_nside,
            "sha256": file_checksum(self.path),
        }


class FekoFileBeam(_GriddedFileBeam):
    """An EDGES FEKO beam (gain on a 1-degree azimuth x elevation grid above the horizon).

    The file's azimuth is measured from the antenna excitation axis; true azimuth (east of
    north) = file azimuth + ``rotation_from_north``. The pattern is bilinear in azimuth
    and elevation, cubic in frequency, and zero below the horizon (the files do not cover
    it). Polarisation: the single excitation of the file (``pol`` is recorded only).
    """

    def __init__(
        self, path: str | Path, rotation_from_north: float = 90.0, pol: str = "ee"
    ) -> None:
        from autocal.io.feko import read_feko_beam

        self.path = Path(path)
        self.pol = _check_pol(pol)
        self.rotation_from_north = float(rotation_from_north)
        self.data = read_feko_beam(self.path)
        self.native_freqs = self.data.freqs
        self.name = f"feko:{self.path.parent.name}/{self.path.name}"

    def _spatial(self, az, za):
        gain = self.data.gain  # (Nf, 360, 91)
        file_az = np.mod(np.degrees(az) - self.rotation_from_north, 360.0)
        el = 90.0 - np.degrees(za)
        above = el >= 0
        el_c = np.clip(el, 0.0, 90.0)
        i0 = np.floor(file_az).astype(int) % 360
        i1 = (i0 + 1) % 360
        wa = file_az - np.floor(file_az)
        j0 = np.minimum(np.floor(el_c).astype(int), 89)
        wb = el_c - j0
        out = (
            (1 - wa) * (1 - wb) * gain[:, i0, j0]
            + wa * (1 - wb) * gain[:, i1, j0]
            + (1 - wa) * wb * gain[:, i0, j0 + 1]
            + wa * wb * gain[:, i1, j0 + 1]
        )
        return np.where(above[None, :], out, 0.0)

    def describe(self):  # noqa: D102
        return {
            "beam": "feko",
            "file": str(self.path),
            "pol": self.pol,
            "rotation_from_north_deg": self.rotation_from_north,
            "sha256": file_checksum(self.path),
        }


_BEAM_HELP = (
    "beams: dipole, airy, hera (the Fagnoni beamfits in the data folder), edges-low, "
    "edges-low-45deg, edges-mid, edges-high (FEKO files in the data folder), or a path to a "
    "UVBeam file (.beamfits, .fits, .h5) or an EDGES FEKO .txt file"
)


def get_beam(spec: str | Beam, pol: str = "ee") -> Beam:
    """Resolve a beam specification.

    Parameters
    ----------
    spec
        A :class:`Beam`, a name (see ``_BEAM_HELP``) or a file path.
    pol
        ``"ee"`` or ``"nn"``.

    Returns
    -------
    Beam
        The beam.

    Raises
    ------
    BeamError
        For unknown names or unreadable files.
    """
    from autocal.io.datasets import EDGES_BEAM_FILES, HERA_BEAM_FILE, data_file
    from autocal.io.feko import BeamFileError

    if isinstance(spec, Beam):
        return spec
    pol = _check_pol(pol)
    key = str(spec).strip()
    low = key.lower()
    try:
        if low == "dipole":
            return GaussianDipoleBeam(pol=pol)
        if low == "airy":
            return AiryBeam(pol=pol)
        if low == "hera":
            return HealpixFileBeam(data_file(HERA_BEAM_FILE, "HERA Fagnoni beam"), pol)
        if low in EDGES_BEAM_FILES:
            return FekoFileBeam(data_file(EDGES_BEAM_FILES[low], f"EDGES {low} beam"), pol=pol)
        path = Path(key).expanduser()
        if path.suffix.lower() == ".txt":
            return FekoFileBeam(path, pol=pol)
        if path.suffix.lower() in {".beamfits", ".fits", ".h5", ".uvbeam"} or path.exists():
            return HealpixFileBeam(path, pol)
    except (BeamFileError, FileNotFoundError) as err:
        raise BeamError(str(err)) from err
    raise BeamError(f"unknown beam {spec!r}; {_BEAM_HELP}")
