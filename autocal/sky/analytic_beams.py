"""Analytic beams: Gaussian dipole, Airy dish, any function, and the paper's error model.

:class:`PerturbedBeam` wraps any beam in the paper's beam error model, whose width ``s1``
comes from :func:`s1_airy` (dishes) or :func:`s1_dipole` (dipoles). Conventions in
:mod:`autocal.sky.beam_base`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.special import j1

from autocal.sky.beam_base import C_LIGHT, Beam, BeamError, BeamEvaluator, check_pol


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
        object.__setattr__(self, "pol", check_pol(self.pol))

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
        object.__setattr__(self, "pol", check_pol(self.pol))
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
