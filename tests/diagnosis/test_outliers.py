"""Outlier flagging: the running median, and flags recomputed each round."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.ndimage import median_filter

from autocal.diagnosis.extended_fit import fit_extended, radiometer_weights
from autocal.diagnosis.outliers import flag_outliers, running_median
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
    accumulated = flag_outliers(flagged_before, refit)
    assert accumulated[0, 0, 30, 40] and accumulated[0, 0, 10, 20]
    recomputed = flag_outliers(flagged_before, refit, base_flags=own)
    assert recomputed[0, 0, 10, 20]
    assert not recomputed[0, 0, 30, 40]
    assert not np.any(recomputed & ~accumulated)
