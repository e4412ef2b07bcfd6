"""Drift statistics of the reference and the raw autos (autocal.compare.drift)."""

from __future__ import annotations

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.compare.comparison import compare
from autocal.compare.drift import auto_trend, fractional_end_change
from tests.compare.helpers import drifting, end_change, reference_for
from tests.io.test_calsol import make_solution


def test_fractional_end_change_of_a_ramp_with_flags():
    values = np.outer(1.0 + 0.5 * np.linspace(0, 1, 30), np.ones(8))
    values[0] = np.nan  # a fully flagged integration is not an end
    values[5, 2] = np.nan
    stats = fractional_end_change(values)
    ramp = 1.0 + 0.5 * np.linspace(0, 1, 30)[1:]
    assert stats["n_valid"] == 29 and stats["n_end"] == 3
    assert stats["change"] == pytest.approx(ramp[-3:].mean() / ramp[:3].mean() - 1.0)
    assert stats["rms"] == pytest.approx(np.std(ramp / ramp.mean()), rel=1e-9)
    assert np.isnan(stats["series"][0])
    np.testing.assert_allclose(stats["series"][1:], ramp / ramp.mean())
    single = fractional_end_change(values[:2])
    assert np.isnan(single["change"]) and single["n_valid"] == 1


def test_auto_trend_feeds_compare():
    sol = make_solution(antennas=(0,), pols=("ee", "nn"), ntime=20, flagged=())
    power = np.ones((1, 2, 20, sol.freqs.size)) * sol.G[:, :, None, :] * 150.0
    power = power * (1 - 0.036 * np.linspace(0, 1, 20))[None, None, :, None]
    flags = np.zeros(power.shape, bool)
    flags[0, 0, 7, :] = True
    tsky = np.full((2, 20, sol.freqs.size), 100.0)
    trend = auto_trend(power, sol.jds, [0], ["ee", "nn"], flags=flags, tsky=tsky)
    assert trend["auto_drift"][(0, "nn")] == pytest.approx(end_change(-0.036, 20, 2))
    assert trend["tsky_ends"][(0, "ee")].shape == (2, sol.freqs.size)
    ref = drifting(reference_for(sol, 1.0, gain_scale="K", ntime=20), 0.5)
    result = compare(sol, ref, **trend)
    for row in result.summary["per_antenna_pol"]:
        assert row["auto_drift"] == pytest.approx(-0.035, abs=2e-3)
        assert row["reference_stable"] is False
        assert row["reference_stability"]["tested"] == ["drift", "negative_trxr"]
    assert result.auto_series is not None and (0, "ee") in result.auto_series
