"""The checks an Observation makes of its data and sample counts."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from autocal.core.observation import Observation, ObservationError
from autocal.core.sites import HERA


def _obs(data: np.ndarray, **kwargs) -> Observation:
    nant, npol, ntime, nfreq = data.shape
    return Observation(
        data=data,
        freqs=np.linspace(100e6, 200e6, nfreq),
        lsts=np.linspace(1.0, 2.0, ntime),
        jds=2458098.3 + np.arange(ntime) / 8640,
        antennas=np.arange(nant),
        pols=("ee", "nn")[:npol],
        site=HERA,
        **kwargs,
    )


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_samples_are_flagged_and_only_they(bad, caplog):
    data = np.full((2, 2, 3, 4), 5.0)
    data[1, 0, 2, 3] = bad
    flags = np.zeros(data.shape, bool)
    flags[0, 1, 0, 0] = True
    with caplog.at_level(logging.INFO, logger="autocal.core.observation"):
        obs = _obs(data, flags=flags)
    expected = flags.copy()
    expected[1, 0, 2, 3] = True
    np.testing.assert_array_equal(obs.flags, expected)
    assert "flagging 1 non-finite samples" in caplog.text


def test_finite_values_whose_sum_overflows_are_not_flagged():
    """The one-pass check sums the data; a sum that overflows is checked element-wise."""
    data = np.full((2, 2, 3, 4), 1e308)
    with np.errstate(over="ignore"):
        assert not np.isfinite(np.sum(data))
    obs = _obs(data)
    assert not obs.flags.any()
    data[0, 0, 0, 0] = np.nan
    assert _obs(data).flags.sum() == 1


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, -1.0])
def test_nsamples_must_be_finite_and_not_negative(bad):
    data = np.ones((2, 1, 3, 4))
    nsamples = np.ones(data.shape)
    assert _obs(data, nsamples=nsamples).nsamples.min() == 1.0
    nsamples[1, 0, 1, 2] = bad
    with pytest.raises(ObservationError, match="nsamples must be finite and >= 0"):
        _obs(data, nsamples=nsamples)
    np.testing.assert_array_equal(_obs(data, nsamples=0.0).nsamples, 0.0)
