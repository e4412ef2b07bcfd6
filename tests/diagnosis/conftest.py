"""The simulated observations the diagnosis tests share (computed once per test process)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from autocal.core.coords import night_epoch
from autocal.core.observation import Observation
from autocal.diagnosis.effects import SkyTemplates, sky_templates
from autocal.simulate.mock import SimulationConfig, gain_profile, mock_autos, simulate
from tests.diagnosis.simulated import BT, SKY


@pytest.fixture(scope="package")
def setup() -> tuple[Observation, SkyTemplates]:
    """The default simulated day (dipole beam, 10 min cadence) and its Tsky templates."""
    cfg = SimulationConfig(
        sky=SKY,
        beam="dipole",
        channel_width_khz=1000,
        cadence_s=600,
        nside=32,
        noise_dnu_hz=BT,
    )
    obs, truth = simulate(cfg)
    tpl = sky_templates(
        SKY,
        "dipole",
        "hera",
        obs.freqs,
        obs.lsts,
        nside=32,
        epoch=night_epoch(obs.jds, obs.site.lon_deg),
    )
    np.testing.assert_allclose(tpl.total, truth.tsky, rtol=1e-10)
    return obs, tpl


@pytest.fixture(scope="package")
def several() -> tuple[Observation, SkyTemplates]:
    """Four antennas, two of them with RFI-like flags, a gain drift and a sky-index error."""
    cfg = SimulationConfig(
        sky=SKY, beam="dipole", channel_width_khz=2000, cadence_s=1200, nside=16, noise_dnu_hz=BT
    )
    obs, _ = simulate(cfg)
    tpl = sky_templates(
        SKY,
        "dipole",
        "hera",
        obs.freqs,
        obs.lsts,
        nside=16,
        epoch=night_epoch(obs.jds, obs.site.lon_deg),
    )
    rng = np.random.default_rng(4)
    tsky = tpl.total + tpl.galactic * ((obs.freqs / tpl.nu0) ** 0.05 - 1)
    gain = gain_profile("a", obs.lsts)
    data = np.concatenate(
        [
            mock_autos(tsky, gain * (1 + 0.1 * i), 150.0 + 10 * i, bandwidth_time=BT, rng=rng)
            for i in range(4)
        ]
    )
    flags = np.zeros(data.shape, bool)
    flags[1, 0, :, 3] = True  # a whole channel
    flags[2, 0, 5:9, :] = True  # a few integrations
    data[2, 0, 6, 7] = np.nan  # a non-finite sample, flagged
    four = dataclasses.replace(
        obs, data=data, flags=flags, antennas=np.arange(4), antenna_names=(), nsamples=None
    )
    return four, tpl
