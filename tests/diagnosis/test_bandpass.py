"""The bandpass domain's ripple fit (:mod:`autocal.diagnosis.bandpass`).

Gains are drawn here with their own noise (numpy's generator, not autocal's simulator):
a smooth bandpass times ``1 + a cos(2 pi nu tau + phi)``.
"""

from __future__ import annotations

import numpy as np
import pytest

from autocal.diagnosis.bandpass import fit_cable_reflection, ripple_halves
from autocal.diagnosis.candidate_fits import reflection_refusal
from autocal.diagnosis.trials import BIC_THRESHOLD

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
    the range, with a side minimum at 92 ns (Delta BIC 14). Scanned from one resolution
    element below 90 ns only, that minimum was a false reflection; it is refused as a side
    lobe of the better fit below the range."""
    rng = np.random.default_rng(190)
    x = (FREQS - 150e6) / 40e6
    smooth = 1.0 + 0.3 * x - 0.2 * x**2 + 0.05 * x**3
    bump = 0.02 * np.exp(-0.5 * ((FREQS - 150e6) / 2e6) ** 2)
    g = smooth * (1.0 + bump) + rng.normal(0.0, 1e-3, FREQS.size)
    sigma = np.full(FREQS.size, 1e-3)
    _, rip = fit_cable_reflection(FREQS, g, sigma)
    assert rip.shorter_tau_ns < 70.0 and rip.tau_ns < 100.0
    refusal = reflection_refusal(FREQS, g, sigma, rip)
    assert refusal is not None and "side lobe" in refusal


def test_structure_below_the_range_is_refused() -> None:
    """A ripple of 70 ns, below the 90 ns the smooth bandpass leaves alone, is shorter
    bandpass structure: it fits best below the range, and what reaches into the range is
    its slope (the refined best delay below 90 ns) or a side lobe."""
    g, s = _gains(70.0, 5e-3, seed=70)
    _, rip = fit_cable_reflection(FREQS, g, s)
    assert abs(rip.shorter_tau_ns - 70.0) < 3
    assert reflection_refusal(FREQS, g, s, rip) is not None


def test_noise_alone_finds_no_ripple() -> None:
    """Without a ripple the drop in chi^2 is that of noise (three parameters searched)."""
    g, s = _gains(200.0, 0.0, seed=3)
    null, rip = fit_cable_reflection(FREQS, g, s)
    assert null.chi2 - rip.chi2 < 30
    assert null.reduced_chi2 == pytest.approx(1.0, abs=0.35)


def _taken(g: np.ndarray, sigma: np.ndarray) -> tuple[bool, float]:
    """Whether the search takes ``g``'s best ripple for a reflection, and its delay.

    Not refused (:func:`~autocal.diagnosis.candidate_fits.reflection_refusal`) and over the
    search's Delta BIC threshold (``try_cable_reflection``'s statistic).
    """
    null, rip = fit_cable_reflection(FREQS, g, sigma)
    k = rip.nparam - null.nparam
    stat = (null.chi2 - rip.chi2) / max(1.0, rip.reduced_chi2) - k * np.log(null.nfreq)
    return reflection_refusal(FREQS, g, sigma, rip) is None and stat > BIC_THRESHOLD, rip.tau_ns


def test_false_alarms_on_localised_structure_and_reflections_found() -> None:
    """Over 324 localised features (Gaussian bumps, tanh steps and Lorentzians of 1-3 %,
    1-4 MHz wide, at 9 places across the band; noise 1e-3) none passes as a reflection,
    and every reflection of 92.5-392.5 ns (a = 0.2, 0.5 and 1 %) is found at its delay.

    The best delay in the range is refused as a side lobe when shorter structure fits
    better within 4 resolution elements (bumps at the band's centre leave minima at 90-97
    ns beside their ~64 ns ringing), and when the halves of the band disagree on the
    ripple or only one carries it (bumps and steps near the band's upper edge)."""
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


def _smooth() -> np.ndarray:
    x = (FREQS - 150e6) / 40e6
    return 1.0 + 0.3 * x - 0.2 * x**2 + 0.05 * x**3


@pytest.mark.parametrize(
    ("shorter_ns", "tau_ns"),
    [(55.0, 150.0), (55.0, 250.0), (55.0, 400.0), (85.0, 200.0), (85.0, 300.0)],
)
def test_stronger_shorter_structure_does_not_hide_a_reflection(
    shorter_ns: float, tau_ns: float
) -> None:
    """A 1 % ripple below the range (fitting better than anything in it) beside a 0.5 %
    reflection: the best minimum in the range is the reflection's, and it is taken (a scan
    judged by its deepest minimum alone refused it as structure below the range; one taking
    the lowest point in the range took the slope of an 85 ns ripple at 90 ns)."""
    rng = np.random.default_rng(int(tau_ns))
    shorter = 1 + 0.01 * np.cos(2 * np.pi * FREQS * shorter_ns * 1e-9 + 0.3)
    ripple = 1 + 0.005 * np.cos(2 * np.pi * FREQS * tau_ns * 1e-9 + 0.7)
    g = _smooth() * shorter * ripple + rng.normal(0, 1e-3, FREQS.size)
    sigma = np.full(FREQS.size, 1e-3)
    _, rip = fit_cable_reflection(FREQS, g, sigma)
    assert rip.shorter_tau_ns < 90.0  # the shorter structure fits better
    taken, best = _taken(g, sigma)
    assert taken and abs(best - tau_ns) < 3


def test_a_reflection_whose_amplitude_changes_across_the_band() -> None:
    """Real reflections are not of one amplitude: 0.75 to 1.25 times it from end to end of
    the band (1.7x) is taken at its delay here; 0.5 to 1.5 (3x) is refused, the halves
    differing by half the amplitude (not one reflection the catalogue's constant ``a``
    describes). The boundary lies near 2x: a review measured 2 of 32 refused at 1.67x and
    16 of 32 at 2.08x over other seeds."""
    x = (FREQS - 150e6) / 40e6
    sigma = np.full(FREQS.size, 1e-3)
    for slope, expected in ((0.5, True), (1.0, False)):
        for tau in (95.0, 150.0, 250.0, 400.0):
            rng = np.random.default_rng(int(tau + slope * 100 + 50))
            amp = 5e-3 * (1 + slope * x / 2)
            g = _smooth() * (1 + amp * np.cos(2 * np.pi * FREQS * tau * 1e-9 + 0.7))
            taken, best = _taken(g + rng.normal(0, 1e-3, FREQS.size), sigma)
            assert (taken and abs(best - tau) < 3) is expected, (slope, tau, best)


@pytest.mark.parametrize("understated", [1.0, 0.5])
def test_many_antenna_pols_of_one_reflection_agree(understated: float) -> None:
    """100 antenna-pols with one reflection each (a = 0.2 %, ~9 sigma each; amplitudes and
    phases their own): the halves agree, also when ``sigma_G`` understates the noise by
    2x (the ripple fit's overdispersion scales the halves' chi^2, as the search's
    statistic), and the sum of many modest differences is not read as one (the relative
    difference is net of noise)."""
    rng = np.random.default_rng(11)
    nrow = 100
    amp = rng.uniform(1.5e-3, 2.5e-3, nrow)[:, None]
    phase = rng.uniform(-np.pi, np.pi, nrow)[:, None]
    g = _smooth()[None] * (1 + amp * np.cos(2 * np.pi * FREQS * 200e-9 + phase))
    g = g + rng.normal(0, 1e-3, g.shape)
    sigma = np.full(g.shape, 1e-3 * understated)
    _, rip = fit_cable_reflection(FREQS, g, sigma)
    assert abs(rip.tau_ns - 200.0) < 2
    halves = ripple_halves(FREQS, g, sigma, rip)
    assert halves.relative_difference < 0.3
    assert reflection_refusal(FREQS, g, sigma, rip) is None
