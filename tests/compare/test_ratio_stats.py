"""The broadband offset and its block-bootstrap error (autocal.compare.ratio_stats)."""

from __future__ import annotations

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.compare.comparison import compare
from autocal.compare.ratio_stats import block_bootstrap_error
from tests.compare.helpers import drifting, reference_for
from tests.io.test_calsol import make_solution


def test_block_bootstrap_of_white_noise_matches_the_standard_error():
    rng = np.random.default_rng(0)
    x = rng.standard_normal(2000)
    freqs = 100e6 + 0.1e6 * np.arange(2000)
    err, info = block_bootstrap_error(x, freqs)
    assert info["block_channels"] == 50 and info["resamples"] == 1000
    assert err == pytest.approx(1 / np.sqrt(2000), rel=0.15)
    again, _ = block_bootstrap_error(x, freqs)
    assert again == err  # seeded
    assert np.isnan(block_bootstrap_error(x[:1], freqs[:1])[0])


def test_offset_error_respects_correlations_across_channels():
    from scipy.ndimage import gaussian_filter1d

    freqs = np.linspace(110e6, 190e6, 401)  # 0.2 MHz channels
    eps = 0.004  # per-channel noise of |g|
    base = make_solution(antennas=(0,), pols=("ee",), freqs=freqs, flagged=(), rel_sigma=2 * eps)
    ref = reference_for(base, 1.0, gain_scale="K", ntime=3)
    g_ref = np.sqrt(base.G[0, 0])
    true = 0.05
    s = 2.0 / 0.2 / 2.355  # a smooth perturbation with a 2 MHz FWHM correlation
    covered, ratio_boot = [], []
    for seed in range(200):
        rng = np.random.default_rng(seed)
        smooth = gaussian_filter1d(rng.standard_normal(freqs.size), s)
        smooth *= 0.02 * np.sqrt(2 * np.sqrt(np.pi) * s)  # 2 % rms
        r = (1 + true) * (1 + smooth) + eps * rng.standard_normal(freqs.size)
        sol = make_solution(
            antennas=(0,),
            pols=("ee",),
            freqs=freqs,
            flagged=(),
            rel_sigma=2 * eps,
            gain=(r * g_ref) ** 2,
        )
        row = compare(sol, ref).summary["per_antenna_pol"][0]
        assert row["offset"] == pytest.approx(row["ratio_mean"] - 1)
        assert row["offset_error_reference_common"] == 0.0
        covered.append(abs(row["offset"] - true) < 2 * row["offset_error"])
        ratio_boot.append(row["offset_error"] / row["offset_error_independent"])
    assert np.median(ratio_boot) > 3  # correlated channels: far above sqrt(sum s^2) / N
    assert 0.9 <= np.mean(covered) <= 0.99


def test_reference_scatter_common_to_all_channels_enters_the_offset_error():
    sol = make_solution(rel_sigma=1e-4, flagged=(), ntime=20)
    ref = drifting(reference_for(sol, 1.0, gain_scale="K", ntime=20), 0.5)
    row = compare(sol, ref).summary["per_antenna_pol"][0]
    amp = np.sqrt(1 + 0.5 * np.linspace(0, 1, 20))
    level = amp / np.sqrt(np.mean(amp**2))
    assert row["offset_error_reference_common"] == pytest.approx(
        row["ratio_mean"] * np.std(level, ddof=1), rel=1e-6
    )
    assert row["offset_error"] >= row["offset_error_reference_common"]
