"""Outlier flagging: the running median, and flags recomputed each round."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.ndimage import median_filter
from scipy.stats import norm

from autocal.diagnosis.extended_fit import fit_extended, radiometer_weights
from autocal.diagnosis.outliers import (
    NOISE_MAX_SIGMA,
    OUTLIER_WINDOW,
    find_outliers,
    high_pass,
    noise_outlier_limit,
    running_median,
    tail_scale,
)
from autocal.diagnosis.report import summary_text
from autocal.diagnosis.stepwise import diagnose
from tests.diagnosis.simulated import hidden


def test_running_median_is_scipys_median_filter() -> None:
    """The sorting network of the outlier flagging gives median_filter's values exactly."""
    rng = np.random.default_rng(5)
    x = rng.normal(size=(2, 2, 30, 40))
    x[..., ::7] = 0.0  # ties
    for axis, window in ((2, 9), (3, 9), (3, 5), (2, 31)):
        size = [1, 1, 1, 1]
        size[axis] = window
        expected = median_filter(x, size=tuple(size), mode="mirror")
        np.testing.assert_array_equal(running_median(x, window, axis), expected)


def test_outlier_flags_are_recomputed_not_accumulated(setup):
    """A sample flagged by an earlier round (a worse model's) is judged again on the
    latest model: clean, it is unflagged; a real spike stays flagged."""
    obs, tpl = setup
    clean = hidden(obs, tpl.total)
    spiked = dataclasses.replace(clean, data=clean.data.copy())
    spiked.data[0, 0, 10, 20] *= 1.05  # ~100 radiometer sigma at dnu dt = 1e6
    w = radiometer_weights(spiked, spiked.data)
    fit = fit_extended(spiked, tpl, [], weights=w)
    own = spiked.flags.copy()
    earlier = own.copy()
    earlier[0, 0, 30, 40] = True  # flagged by an earlier round, a clean sample
    flagged_before = dataclasses.replace(spiked, flags=earlier)
    w = radiometer_weights(flagged_before, fit)
    refit = fit_extended(flagged_before, tpl, [], weights=w)
    accumulated = find_outliers(flagged_before, refit).flags
    assert accumulated[0, 0, 30, 40] and accumulated[0, 0, 10, 20]
    recomputed = find_outliers(flagged_before, refit, base_flags=own).flags
    assert recomputed[0, 0, 10, 20]
    assert not recomputed[0, 0, 30, 40]
    assert not np.any(recomputed & ~accumulated)


def test_tail_scale_gives_the_gaussian_false_alarm_rate() -> None:
    """White Gaussian noise through the high-pass exceeds k sigma (robust sigma x
    tail_scale) at about the Gaussian rate 2 Phi(-k); the robust sigma alone (the old
    threshold) flags clean samples tens of times too often."""
    rng = np.random.default_rng(11)
    dev = np.abs(high_pass(rng.standard_normal((12, 192, 1024)), OUTLIER_WINDOW))
    robust = 1.4826 * np.median(dev)
    scale = tail_scale(OUTLIER_WINDOW)
    assert 1.2 < scale < 1.6
    for k in (3.5, 4.0, 4.5):
        expected = 2 * norm.sf(k) * dev.size
        assert 0.7 * expected < np.sum(dev > k * robust * scale) < 2.0 * expected
        assert np.sum(dev > k * robust) > 10 * expected


def test_clean_residuals_are_not_flagged(setup) -> None:
    """A clean observation (its own model times white radiometer noise drawn here, 8
    antennas) gets outlier flags at the Gaussian rate of the threshold: at 4 sigma ~1e-4 of
    its samples (the old robust-sigma threshold flagged 3e-3 at "4 robust sigma")."""
    obs, tpl = setup
    rng = np.random.default_rng(3)
    nant = 8
    model = 0.02 * (tpl.total[None] + 150.0)
    bt = obs.channel_width[None, None, None, :] * obs.integration_time[None, None, :, None]
    shape = (nant, 1, obs.ntime, obs.nfreq)
    data = model * (1 + rng.standard_normal(shape) / np.sqrt(bt))

    clean = dataclasses.replace(
        obs,
        data=data,
        flags=np.zeros(shape, bool),
        nsamples=np.ones(shape),
        antennas=np.arange(nant),
        antenna_names=(),
    )
    w = radiometer_weights(clean, clean.data)
    fit = fit_extended(clean, tpl, [], weights=w)
    flags = find_outliers(clean, fit, threshold=4.0).flags
    expected = 2 * norm.sf(4.0) * flags.size
    assert flags.sum() < 3 * expected + 3


def test_a_round_of_noise_like_outliers_does_not_search_again(setup) -> None:
    """At 3.5 sigma a clean observation's residuals give a few outliers, no more than the
    noise allows (noise_outlier_limit): reported, left unflagged, no second search. One
    strong spike (~100 radiometer sigma, a single sample: within the count the noise
    allows, but beyond NOISE_MAX_SIGMA) is RFI: flagged, and the search runs again."""
    obs, tpl = setup
    clean = hidden(obs, tpl.total, seed=8)
    usable = int(clean.flags.size - clean.flags.sum())
    limit = noise_outlier_limit(usable, 3.5)
    assert limit >= 1
    assert noise_outlier_limit(usable, 6.0) == 0  # too few samples to excuse any at 6 sigma
    assert noise_outlier_limit(100 * usable, 3.5) > limit
    assert noise_outlier_limit(10, 0.1) <= 10  # never more than the samples
    quiet = diagnose(clean, tpl, outlier_threshold=3.5)
    flagging = quiet.config["outlier_flagging"]
    assert flagging["rounds"] == 0 and flagging["samples_flagged"] == 0
    assert flagging["noise_like"] is not None  # the round found only what noise gives
    assert 1 <= flagging["noise_like"]["samples"] <= limit
    assert flagging["noise_like"]["peak_sigma"] <= NOISE_MAX_SIGMA
    assert "left unflagged, not searched again" in summary_text(quiet)
    spiked = dataclasses.replace(clean, data=clean.data.copy())
    spiked.data[0, 0, 10, 20] *= 1.1
    loud = diagnose(spiked, tpl, outlier_threshold=3.5).config["outlier_flagging"]
    assert loud["rounds"] >= 1 and loud["samples_flagged"] >= 1


def test_bad_outlier_settings_are_refused(setup) -> None:
    obs, tpl = setup
    fit = fit_extended(obs, tpl, [], weights=radiometer_weights(obs, obs.data))
    with pytest.raises(ValueError, match="positive number of sigma"):
        find_outliers(obs, fit, threshold=0.0)
    with pytest.raises(ValueError, match="at least 3"):
        find_outliers(obs, fit, window=1)
