"""The compiled auto power equals the reader's numpy steps (imaginary test, transposed copy)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.io.power_kernel import auto_power_into
from autocal.io.uvh5_blocks import _auto_power

NT, NANT, NCHAN, NPOL = 3, 4, 11, 4


def _values(rng: np.random.Generator) -> np.ndarray:
    shape = (NT * NANT, NCHAN, NPOL)
    real = rng.standard_normal(shape).astype(np.float32)
    real.flat[rng.choice(real.size, 5, replace=False)] = [np.nan, np.inf, -np.inf, -0.0, 0.0]
    values = real.astype(np.complex64)
    values.imag[..., 2:] = rng.standard_normal((*shape[:2], 2))  # cross pols: imaginary parts
    return values


def _numpy(values, fidx, pidx, same_feed):
    arr = _auto_power(values[:, fidx][:, :, pidx], same_feed)
    return arr.reshape(NT, NANT, fidx.size, pidx.size).transpose(1, 3, 0, 2).astype(np.float64)


SELECTIONS = {
    "whole band, all pols": (np.arange(NCHAN), np.arange(NPOL)),
    "a range of channels": (np.arange(3, 9), np.arange(NPOL)),
    "every other channel, two pols": (np.arange(0, NCHAN, 2), np.array([1, 3])),
    "channels out of order, one pol": (np.array([7, 2, 5]), np.array([2])),
}


@pytest.mark.parametrize("name", SELECTIONS)
def test_the_power_is_numpys_bit_for_bit(name) -> None:
    fidx, pidx = SELECTIONS[name]
    values = _values(np.random.default_rng(len(name)))
    same_feed = pidx < 2  # ee, nn same-feed; en, ne cross
    out = np.full((NANT, pidx.size, NT, fidx.size), 7.0)
    assert auto_power_into(values, out, fidx, pidx, same_feed)
    expected = _numpy(values, fidx, pidx, same_feed)
    assert out.view(np.uint64).tolist() == expected.view(np.uint64).tolist()  # NaN, -0.0 too


@pytest.mark.parametrize("imag", [1e-3, np.nan, -np.inf])
def test_a_same_feed_imaginary_part_is_left_to_numpy(imag) -> None:
    values = _values(np.random.default_rng(3))
    values.imag[5, 4, 1] = imag  # nn of antenna 1 at integration 1
    fidx, pidx = np.arange(NCHAN), np.arange(NPOL)
    out = np.empty((NANT, NPOL, NT, NCHAN))
    assert not auto_power_into(values, out, fidx, pidx, pidx < 2)
    # the same value in a cross pol, or a negative zero, is a real part as it is
    values.imag[5, 4, 1] = -0.0
    values.imag[6, 4, 3] = imag
    assert auto_power_into(values, out, fidx, pidx, pidx < 2)
    np.testing.assert_array_equal(out, _numpy(values, fidx, pidx, pidx < 2))


def test_shapes_that_do_not_match_are_refused() -> None:
    values = np.zeros((NT * NANT, NCHAN, NPOL), np.complex64)
    pidx, same = np.arange(NPOL), np.ones(NPOL, bool)
    with pytest.raises(ValueError, match="auto power of complex64"):
        auto_power_into(values, np.empty((NANT + 1, NPOL, NT, NCHAN)), np.arange(NCHAN), pidx, same)
    with pytest.raises(ValueError, match=r"channels 5\.\.11 of 11"):
        auto_power_into(values, np.empty((NANT, NPOL, NT, 7)), np.arange(5, 12), pidx, same)
    with pytest.raises(ValueError, match="auto power of complex128"):
        auto_power_into(
            values.astype(np.complex128), np.empty((NANT, NPOL, NT, NCHAN)), np.arange(NCHAN),
            pidx, same,
        )  # fmt: skip
