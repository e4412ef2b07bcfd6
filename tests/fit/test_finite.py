"""The trailing-element finiteness test against numpy's reduction."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.fit.finite import finite_trailing


@pytest.mark.parametrize(
    ("shape", "ndim"),
    [((5, 7, 2), 1), ((3, 4, 2, 2), 2), ((6, 3), 1), ((0, 2), 1), ((4, 0), 1), ((2, 3, 1), 1)],
)
def test_finite_trailing_is_numpys_all_of_isfinite(shape: tuple[int, ...], ndim: int) -> None:
    rng = np.random.default_rng(5)
    values = rng.standard_normal(shape)
    bad = rng.random(shape) < 0.2
    values[bad] = rng.choice([np.nan, np.inf, -np.inf], size=int(bad.sum()))
    expected = np.all(np.isfinite(values), axis=tuple(range(-ndim, 0)))
    got = finite_trailing(values, ndim)
    assert got.dtype == bool and got.shape == expected.shape
    np.testing.assert_array_equal(got, expected)
    if expected.size > 4:  # elements that pass and elements that fail: the test can tell
        assert expected.any() and not expected.all()


def test_more_trailing_dimensions_than_the_array_has_are_refused() -> None:
    with pytest.raises(ValueError, match="3 trailing dimensions of a 2-d array"):
        finite_trailing(np.zeros((2, 2)), 3)
