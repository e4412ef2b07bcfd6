"""Mock observations (autocal.simulate.mock)."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.time import Time
from pydantic import ValidationError

from autocal.core.sites import HERA
from autocal.simulate.mock import (
    SimulationConfig,
    SimulationError,
    gain_profile,
    hera_h1c_bandpass,
    lsts_to_jds,
    simulate,
)

FAST = {
    "beam": "dipole",
    "freq_start_mhz": 120.0,
    "freq_stop_mhz": 180.0,
    "channel_width_khz": 2000.0,
}


def test_gain_profiles_follow_their_definitions() -> None:
    t = np.array([0.0, 6.0, 12.0, 18.0])
    np.testing.assert_allclose(gain_profile("a", t), 1 - 0.1 * (t / 12 - 1))
    np.testing.assert_allclose(gain_profile("b", t), 1 + 0.1 * np.sin(2 * np.pi * t / 24))
    np.testing.assert_allclose(
        gain_profile("c", t), 1 + 0.1 * np.sin(2 * np.pi - 2 * np.pi * t / 24)
    )
    np.testing.assert_allclose(gain_profile("constant", t, g0=2.0), 2.0)
    assert gain_profile("a", t, g0=np.ones(3)).shape == (4, 3)
    with pytest.raises(SimulationError, match="unknown gain profile"):
        gain_profile("d", t)


def test_jds_reproduce_the_requested_lsts() -> None:
    lsts = (23.0 + np.arange(30) * 0.1) % 24.0
    jds = lsts_to_jds(lsts, HERA, 2458098.0)
    assert jds[0] >= 2458098.0 and jds[0] < 2458099.0
    got = Time(jds, format="jd", location=HERA.location).sidereal_time("apparent").hour
    err_s = ((got - lsts + 12) % 24 - 12) * 3600
    assert np.max(np.abs(err_s)) < 0.5


def test_noiseless_simulation_is_exactly_the_model() -> None:
    cfg = SimulationConfig(**FAST, gain="b", trxr_k=120.0, noise=False, duration_h=6.0)
    obs, truth = simulate(cfg)
    expected = truth.gain * (truth.tsky[0] + 120.0)
    np.testing.assert_allclose(obs.data[0, 0], expected, rtol=1e-12)
    assert obs.shape == (1, 1, 72, 31)
    np.testing.assert_allclose(obs.lsts, cfg.lsts())


def test_noise_level_and_recorded_bandwidth_time() -> None:
    cfg = SimulationConfig(**FAST, antennas=[0, 1, 2], pols=["ee", "nn"], duration_h=4.0, seed=3)
    obs, truth = simulate(cfg)
    clean = truth.gain[None, None] * (truth.tsky[None] + 150.0)
    rel = obs.data / clean - 1
    assert np.std(rel) == pytest.approx(1 / np.sqrt(5e3), rel=0.05)
    np.testing.assert_allclose(obs.bandwidth_time(), 5e3)
    # antennas carry independent noise; the pols see different (rotated) beams
    assert abs(np.corrcoef(rel[0].ravel(), rel[1].ravel())[0, 1]) < 0.05
    assert not np.allclose(truth.tsky[0], truth.tsky[1])


def test_config_validation() -> None:
    with pytest.raises(ValidationError, match="freq_stop_mhz"):
        SimulationConfig(freq_start_mhz=190, freq_stop_mhz=110)
    with pytest.raises(ValidationError, match="extra"):
        SimulationConfig(bogus=1)
    with pytest.raises(ValidationError, match="unique"):
        SimulationConfig(antennas=[1, 1])
    assert SimulationConfig().freqs().size == 321
    assert SimulationConfig().lsts().size == 288


def test_h1c_bandpass_is_unity_at_150_mhz(data_root) -> None:
    freqs = np.array([120e6, 150e6, 180e6])
    bp = hera_h1c_bandpass(freqs)
    assert bp[1] == pytest.approx(1.0)
    assert np.all(bp > 0)
    with pytest.raises(SimulationError, match="not positive"):
        hera_h1c_bandpass(np.array([100e6, 150e6]))
