"""Outlier flagging's running median."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter

from autocal.diagnosis.outliers import running_median


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
