"""Reference times, smoothing and averaging (autocal.compare.reference)."""

from __future__ import annotations

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.compare.comparison import compare
from autocal.compare.errors import CompareError
from autocal.compare.reference import smooth_frequency, time_average
from tests.compare.helpers import reference_for
from tests.io.test_calsol import make_solution


def test_smoothing_kernel():
    freqs = np.linspace(100e6, 200e6, 201)
    linear = 1 + 0.01 * (freqs / 1e6 - 150)
    out, sig = smooth_frequency(freqs, linear[None], np.full((1, 201), 0.1), 2.0)
    np.testing.assert_allclose(out[0, 20:-20], linear[20:-20], rtol=1e-9)
    # noise is averaged down by ~sqrt(number of channels in the kernel)
    assert np.all(sig[0, 20:-20] < 0.1 / np.sqrt(3))
    rng = np.random.default_rng(1)
    noisy = linear + 0.01 * rng.standard_normal(201)
    noisy[50] = np.nan  # flagged channels stay flagged and do not contaminate
    sm, _ = smooth_frequency(freqs, noisy[None], np.full((1, 201), 0.01), 3.0)
    assert np.isnan(sm[0, 50]) and np.isfinite(sm[0, 49])
    assert np.nanstd(sm[0] - linear) < 0.5 * np.nanstd(noisy - linear)
    with pytest.raises(CompareError, match="positive"):
        smooth_frequency(freqs, linear[None], linear[None], 0.0)


def test_non_overlapping_times_use_the_nearest_reference_time():
    sol = make_solution()
    ref = reference_for(sol, 0.5, gain_scale="K", jds=sol.jds.max() + np.array([1.0, 2.0]))
    result = compare(sol, ref)
    info = result.summary["time_match"]
    assert info["match"] == "nearest" and info["ntimes"] == 1
    assert info["offset_days"] == pytest.approx(1.0 + 0.5 * np.ptp(sol.jds) * 1, rel=1e-6)
    assert not result.summary["per_antenna_pol"][0]["reference_sigma_available"]
    np.testing.assert_allclose(result.ratio[result.valid], 2.0)


def test_sigma_reference_is_the_scatter_over_time():
    sol = make_solution(rel_sigma=1e-4, flagged=())
    ref = reference_for(sol, 0.5, gain_scale="K", ntime=40, scatter=0.05, seed=3)
    result = compare(sol, ref)
    amp = ref.abs_g  # (A, P, T, F), the same channels: no interpolation
    expected = np.std(amp, axis=2, ddof=1)
    ok = result.valid
    np.testing.assert_allclose(result.sigma_reference[ok], expected[ok], rtol=1e-9)
    rel = result.sigma_reference[ok] / result.reference[ok]
    assert np.median(rel) == pytest.approx(0.05, rel=0.15)  # not 0.05 / sqrt(40)
    assert result.summary["per_antenna_pol"][0]["sigma_reference_rel_median"] == pytest.approx(
        np.median(rel[: ok[0, 0].sum()]), rel=1e-9
    )
    _, sem, count = time_average(amp, error="sem")
    np.testing.assert_allclose(sem, expected / np.sqrt(count))
    with pytest.raises(CompareError, match="scatter"):
        time_average(amp, error="bogus")
