"""The bandpass domain's ripple fit (:mod:`autocal.diagnosis.bandpass`).

Gains are drawn here with their own noise (numpy's generator, not autocal's simulator):
a smooth bandpass times ``1 + a cos(2 pi nu tau + phi)``.
"""

from __future__ import annotations

import numpy as np
import pytest

from autocal.diagnosis.bandpass import fit_cable_reflection

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
