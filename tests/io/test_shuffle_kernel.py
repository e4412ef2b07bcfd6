"""The compiled unshuffle equals numpy's transpose of the byte planes."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.io.shuffle_kernel import unshuffle


@pytest.mark.parametrize("itemsize", [1, 2, 4, 8, 16, 3])
def test_unshuffle_is_the_byte_planes_transposed(itemsize):
    rng = np.random.default_rng(itemsize)
    n = 1001
    values = rng.integers(0, 256, size=(n, itemsize), dtype=np.uint8)
    planes = np.ascontiguousarray(values.T).ravel()  # as HDF5's shuffle filter stores them
    out = unshuffle(planes, itemsize, np.empty(planes.size, np.uint8))
    np.testing.assert_array_equal(out, values.ravel())


def test_sizes_that_do_not_match_are_refused():
    with pytest.raises(ValueError, match="10 shuffled bytes for 8"):
        unshuffle(np.zeros(10, np.uint8), 2, np.zeros(8, np.uint8))
