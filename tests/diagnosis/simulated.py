"""Simulated observations with someone else's hidden effect (helpers of the diagnosis tests)."""

from __future__ import annotations

import dataclasses

import numpy as np

from autocal.core.observation import Observation
from autocal.simulate.mock import mock_autos

SKY = "powerlaw:gsm2008@408:-2.55"
BT = 1e6  # dnu dt of the simulated noise (the file's nsamples record it)
PRIOR_SIGMA = 0.1  # K, receiver prior for the time-constant effects


def hidden(
    obs: Observation, tsky: np.ndarray, gain: np.ndarray | None = None, trxr=150.0, seed=1
) -> Observation:
    """Mock data from a modified truth (someone else's hidden effect)."""
    g = np.ones(obs.ntime) if gain is None else gain
    data = mock_autos(tsky, g, trxr, bandwidth_time=BT, rng=np.random.default_rng(seed))
    return dataclasses.replace(obs, data=data)


def s_of(lsts: np.ndarray) -> np.ndarray:
    """The LSTs mapped onto [-1, 1]."""
    return 2 * (lsts - lsts.min()) / (lsts.max() - lsts.min()) - 1
