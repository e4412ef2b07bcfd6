"""Delay spectra (autocal.compare.delay)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.compare.delay import DelayError, delay_spectrum

FREQS = np.linspace(110e6, 190e6, 321)


@pytest.mark.parametrize(("tau_ns", "amp"), [(150.0, 1e-3), (400.0, 1e-2)])
def test_ripple_appears_at_its_delay_with_half_its_amplitude(tau_ns: float, amp: float) -> None:
    gain = 1.0 + amp * np.cos(2 * np.pi * FREQS * tau_ns * 1e-9 + 0.3)
    ds = delay_spectrum(gain, FREQS)
    far = ds.delays_ns > 60
    peak = np.flatnonzero(far)[np.argmax(ds.amplitude[far])]
    assert abs(ds.delays_ns[peak] - tau_ns) <= ds.delays_ns[1]
    assert ds.amplitude[peak] == pytest.approx(amp / 2, rel=0.1)
    assert ds.amplitude[0] == 1.0


def test_smooth_spectrum_stays_at_low_delay_and_flags_are_ignored() -> None:
    smooth = (FREQS / 150e6) ** -2.5
    corrupted = smooth.copy()
    corrupted[100] = 1e6
    flags = np.zeros(FREQS.size, bool)
    flags[100] = True
    ds = delay_spectrum(np.stack([smooth, corrupted]), FREQS, flags=np.stack([flags * 0, flags]))
    assert np.max(ds.amplitude[0, ds.delays_ns > 150]) < 1e-4
    assert np.max(ds.amplitude[1, ds.delays_ns > 300]) < 1e-2


def test_bad_frequency_grids_are_refused() -> None:
    with pytest.raises(DelayError, match="uniformly"):
        delay_spectrum(np.ones(5), np.array([1e8, 1.1e8, 1.3e8, 1.4e8, 1.5e8]))
    with pytest.raises(DelayError, match="values for"):
        delay_spectrum(np.ones(4), FREQS)
    with pytest.raises(DelayError, match="flagged"):
        delay_spectrum(np.full(FREQS.size, np.nan), FREQS)
