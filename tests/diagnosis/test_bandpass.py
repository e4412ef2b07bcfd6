"""The bandpass domain's ripple fit (:mod:`autocal.diagnosis.bandpass`).

Gains are drawn here with their own noise (numpy's generator, not autocal's simulator):
a smooth bandpass times ``1 + a cos(2 pi nu tau + phi)``.
"""

from __future__ import annotations

import numpy as np
import pytest

from autocal.diagnosis.bandpass import fit_cable_reflection, ripple_halves
from autocal.diagnosis.candidate_fits import reflection_refusal

FREQS = np.linspace(110e6, 190e6, 161)


def _gains(tau_ns: float, a: float, seed: int, rel_sigma: float = 1e-3) -> tuple:
    rng = np.random.default_rng(seed)
    x = (FREQS - 150e6) / 40e6
    smooth = 1.0 + 0.3 * x - 0.2 * x**2 + 0.05 * x**3
    ripple = 1.0 + a * np.cos(2 * np.pi * FREQS * tau_ns * 1e-9 + 0.7)
    sigma = np.full(FREQS.size, rel_sigma)
    return smooth * ripple + rng.normal(0.0, rel_sigma, FREQS.size), sigma


@pytest.mark.parametrize("tau_ns", [92.0, 96.0, 101.0])
def test_reflection_at_the_ranges_lower_end_is_found(tau_ns: float) -> None:
    """A delay inside the claimed range (from 90 ns), however close to its end, is a
    minimum inside the scan, not refused as unresolved structure (it was, below 102.5 ns:
    one resolution element of the 80 MHz band)."""
    g, s = _gains(tau_ns, 5e-3, seed=int(tau_ns))
    null, rip = fit_cable_reflection(FREQS, g, s)
    assert not rip.at_edge
    assert abs(rip.tau_ns - tau_ns) < 3 * rip.sigma_tau_ns + 1.0
    assert null.chi2 - rip.chi2 > 100


def test_a_localised_bump_is_not_a_reflection() -> None:
    """A 2 % Gaussian bump 2 MHz wide at 150 MHz (RFI-like structure that survived the
    flags, or a resonance): what the smooth bandpass leaves of it rings at ~64 ns, below
    the range. Scanned from one resolution element below 90 ns only, a side minimum at 92
    ns won (Delta BIC 14): a false reflection; scanned from 45 ns it is refused."""
    rng = np.random.default_rng(190)
    x = (FREQS - 150e6) / 40e6
    smooth = 1.0 + 0.3 * x - 0.2 * x**2 + 0.05 * x**3
    bump = 0.02 * np.exp(-0.5 * ((FREQS - 150e6) / 2e6) ** 2)
    g = smooth * (1.0 + bump) + rng.normal(0.0, 1e-3, FREQS.size)
    _, rip = fit_cable_reflection(FREQS, g, np.full(FREQS.size, 1e-3))
    assert rip.at_edge and rip.tau_ns < 90.0


def test_structure_below_the_range_is_refused() -> None:
    """A ripple of 70 ns, below the 90 ns the smooth bandpass leaves alone, is unresolved
    bandpass structure: its best delay lies below the range."""
    g, s = _gains(70.0, 5e-3, seed=70)
    _, rip = fit_cable_reflection(FREQS, g, s)
    assert rip.at_edge and rip.tau_ns < 90.0


def test_noise_alone_finds_no_ripple() -> None:
    """Without a ripple the drop in chi^2 is that of noise (three parameters searched)."""
    g, s = _gains(200.0, 0.0, seed=3)
    null, rip = fit_cable_reflection(FREQS, g, s)
    assert null.chi2 - rip.chi2 < 30
    assert null.reduced_chi2 == pytest.approx(1.0, abs=0.35)


def _taken(g: np.ndarray, sigma: np.ndarray) -> tuple[bool, float]:
    """Whether the search takes ``g``'s best ripple for a reflection, and its delay.

    Not refused (:func:`~autocal.diagnosis.candidate_fits.reflection_refusal`) and over the
    search's Delta BIC threshold of 10 (``try_cable_reflection``'s statistic).
    """
    null, rip = fit_cable_reflection(FREQS, g, sigma)
    k = rip.nparam - null.nparam
    stat = (null.chi2 - rip.chi2) / max(1.0, rip.reduced_chi2) - k * np.log(null.nfreq)
    return reflection_refusal(FREQS, g, sigma, rip) is None and stat > 10, rip.tau_ns


def test_false_alarms_on_localised_structure_and_reflections_found() -> None:
    """Over 324 localised features (Gaussian bumps, tanh steps and Lorentzians of 1-3 %,
    1-4 MHz wide, at 9 places across the band; noise 1e-3) none passes as a reflection,
    and every reflection of 92.5-392.5 ns (a = 0.2, 0.5 and 1 %) is found at its delay (one
    at 90 ns exactly, the range's end, is found or refused as the noise puts its best
    delay).

    By the delay range alone 4 of the features pass (tanh steps and bumps near the band's
    upper edge, which mimic a ripple over the few channels they cover; 19 with a scan from
    77.5 ns, 5 when the range's first resolution element was refused); the halves of the
    band disagree on each of them (chi2 36 to 337 for 2)."""
    x = (FREQS - 150e6) / 40e6
    smooth = 1.0 + 0.3 * x - 0.2 * x**2 + 0.05 * x**3
    sigma = np.full(FREQS.size, 1e-3)
    shapes = {
        "gauss": lambda c, w: np.exp(-0.5 * ((FREQS - c) / w) ** 2),
        "tanh": lambda c, w: np.tanh((FREQS - c) / w),
        "lorentz": lambda c, w: 1.0 / (1.0 + ((FREQS - c) / w) ** 2),
    }
    false = []
    for kind, shape in shapes.items():
        for c in np.linspace(112e6, 188e6, 9):
            for w in (1e6, 2e6, 3e6, 4e6):
                for a in (0.01, 0.02, 0.03):
                    rng = np.random.default_rng(int(c / 1e6 + w / 1e5 + a * 1000))
                    g = smooth * (1 + a * shape(c, w)) + rng.normal(0, 1e-3, FREQS.size)
                    if _taken(g, sigma)[0]:
                        false.append((kind, c, w, a))
    missed = []
    for tau in np.arange(92.5, 400.0, 7.5):
        for a in (2e-3, 5e-3, 1e-2):
            rng = np.random.default_rng(int(tau * 10 + a * 1e4))
            ripple = 1 + a * np.cos(2 * np.pi * FREQS * tau * 1e-9 + 0.7)
            taken, best = _taken(smooth * ripple + rng.normal(0, 1e-3, FREQS.size), sigma)
            if not (taken and abs(best - tau) < 5):
                missed.append((tau, a))
    assert false == [], false
    assert missed == [], missed


def test_a_step_near_the_band_edge_is_refused_by_the_halves() -> None:
    """A 2 % step 1 MHz wide at 178.5 MHz passes the delay range as a 111 ns ripple
    (Delta BIC 22); fitted on each half of the band it is all in the upper one."""
    rng = np.random.default_rng(int(178.5 + 10 + 20))
    x = (FREQS - 150e6) / 40e6
    smooth = 1.0 + 0.3 * x - 0.2 * x**2 + 0.05 * x**3
    g = smooth * (1 + 0.02 * np.tanh((FREQS - 178.5e6) / 1e6)) + rng.normal(0, 1e-3, FREQS.size)
    sigma = np.full(FREQS.size, 1e-3)
    _, rip = fit_cable_reflection(FREQS, g, sigma)
    assert not rip.at_edge
    halves = ripple_halves(FREQS, g, sigma, rip)
    assert halves.p_value < 1e-6 and halves.relative_difference > 1.0
    assert np.hypot(*halves.upper[0]) > 3 * np.hypot(*halves.lower[0])
    refusal = reflection_refusal(FREQS, g, sigma, rip)
    assert refusal is not None and "two halves" in refusal
