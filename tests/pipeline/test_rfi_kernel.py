"""The compiled frequency flagger (autocal.pipeline.rfi_kernel) against its numpy reference.

The kernel sorts blocks with a comparator network and finds the width's median by a radix
select; the reference (:func:`autocal.pipeline.rfi.frequency_flags_numpy`) uses numpy's
sorts. Both must give the same flags and band levels on awkward inputs, and the network
and the select are each checked against first principles.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from autocal.pipeline.rfi import frequency_flags, frequency_flags_numpy
from autocal.pipeline.rfi_kernel import ScanSums, _median_nonnegative, level_sums, sorting_network


@pytest.mark.parametrize("n", [2, 4, 8, 16])
def test_the_network_sorts_every_binary_input(n: int) -> None:
    """The 0-1 principle: a comparator network that sorts all 2^n inputs of zeros and ones
    sorts every input."""
    inputs = np.array(list(itertools.product((0, 1), repeat=n)), dtype=np.int8)
    for i, j in sorting_network(n):
        lo, hi = np.minimum(inputs[:, i], inputs[:, j]), np.maximum(inputs[:, i], inputs[:, j])
        inputs[:, i], inputs[:, j] = lo, hi
    assert (np.diff(inputs, axis=1) >= 0).all()


def test_a_network_needs_a_power_of_two() -> None:
    with pytest.raises(ValueError, match="power of two"):
        sorting_network(12)


@pytest.mark.parametrize("size", [1, 2, 3, 4, 17, 1000, 1536])
def test_the_radix_median_is_the_median(size: int) -> None:
    """Exact, for sizes odd and even, with ties, zeros and values over many octaves."""
    rng = np.random.default_rng(size)
    for values in (
        rng.standard_normal(size) ** 2,
        np.round(rng.random(size) * 4) / 4,  # many ties, zeros
        np.exp(rng.uniform(-40, 40, size)),
    ):
        got = _median_nonnegative(values.copy(), np.empty(2049, np.int32), np.empty(size))
        assert got == np.median(values)


def _awkward(nfreq: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Autos with RFI, flags, zeros, NaN and inf, an empty block, dead spectra."""
    rng = np.random.default_rng(seed)
    shape = (3, 2, 9, nfreq)
    level = 10 + np.abs(rng.standard_normal(shape[:2] + shape[3:]))
    level[0, 0, :5] = 0.0  # zeroed edge channels
    level[1, 1, nfreq // 3] = np.nan
    drift = 1 + 0.05 * min(1.0, nfreq / 256) * np.linspace(-1, 1, nfreq)
    data = level[:, :, None, :] * drift * (1 + 1e-3 * rng.standard_normal(shape))
    data[rng.random(shape) < 0.004] *= 1.02  # spikes
    data[0, 1, 3, nfreq // 2 : nfreq // 2 + 4] *= 1.01  # a narrow-band burst
    flags = rng.random(shape) < 0.02
    if nfreq >= 64:
        flags[:, :, :, 16:32] = True  # a whole block flagged
    data[2, 0, 4, :] = 0.0  # a dead spectrum
    flags[2, 1, 5, 2:] = True  # a spectrum with two samples left
    data[1, 0, 2, 7] = np.nan
    data[1, 0, 2, 8] = np.inf
    quiet = slice(nfreq // 4, nfreq // 4 + 6)
    data[0, 0, 6, quiet] = level[0, 0, quiet]  # exactly the level: zero residuals
    return data, flags, level


@pytest.mark.parametrize(("nfreq", "seed"), [(256, 0), (1000, 1), (37, 2), (16, 3)])
def test_the_kernel_gives_the_reference_flags_and_band_levels(nfreq: int, seed: int) -> None:
    data, flags, level = _awkward(nfreq, seed)
    sums = ScanSums.zeros((data.shape[0], data.shape[1], nfreq))
    hits, scan = frequency_flags(data, flags, level, sums)
    band = scan.band
    ref_hits, ref_band = frequency_flags_numpy(data, flags, level)
    assert hits.any() and (hits == ref_hits).all()
    np.testing.assert_array_equal(band, ref_band)  # the same bits (NaN where NaN)
    assert np.isnan(band[2, 0, 4]) and np.isnan(band[2, 1, 5])  # dead, and < 3 samples
    assert not hits[2, 0, 4].any() and not hits[flags].any()
    # the scan's counts and sums, as numpy computes them from the hits
    with np.errstate(invalid="ignore", divide="ignore"):
        usable = ~flags & (data > 0) & np.isfinite(data / level[:, :, None, :])
    np.testing.assert_array_equal(scan.usable, usable.sum(axis=-1))
    np.testing.assert_array_equal(scan.hit, hits.sum(axis=-1))
    np.testing.assert_array_equal(sums.hits, hits.sum(axis=2))
    np.testing.assert_array_equal(sums.usable, usable.sum(axis=2))
    clean = usable & ~hits
    np.testing.assert_array_equal(sums.clean_count, clean.sum(axis=2))
    np.testing.assert_allclose(sums.clean_total, np.where(clean, data, 0).sum(axis=2), rtol=1e-12)


def test_float32_power_gives_the_flags_and_sums_of_the_same_values_in_float64() -> None:
    """The flagging's replayed blocks hand the kernels float32 power
    (``autocal.pipeline.decoded.ScanChunk``): each value is widened before any arithmetic,
    so the hits, band levels and every sum are those of the float64 array, bit for bit."""
    data, flags, level = _awkward(1000, 4)
    single = data.astype(np.float32)
    results = []
    for power in (single, single.astype(np.float64)):
        sums = ScanSums.zeros((3, 2, 1000))
        hits, scan = frequency_flags(power, flags, level, sums)
        total, count = np.zeros((3, 2, 1000)), np.zeros((3, 2, 1000), np.int64)
        level_sums(power, flags, total, count)
        results.append((hits, scan.band, scan.usable, scan.hit, total, count, *vars(sums).values()))
    assert results[0][0].any()
    for got, want in zip(*results, strict=True):
        np.testing.assert_array_equal(got, want)


def test_the_level_sums_add_finite_positive_unflagged_samples() -> None:
    data, flags, _ = _awkward(100, 5)
    total, count = np.zeros((3, 2, 100)), np.zeros((3, 2, 100), np.int64)
    for _ in range(2):  # added in place, block after block
        level_sums(data, flags, total, count)
    usable = ~flags & np.isfinite(data) & (data > 0)
    np.testing.assert_array_equal(count, 2 * usable.sum(axis=2))
    np.testing.assert_allclose(total, 2 * np.where(usable, data, 0).sum(axis=2), rtol=1e-12)


def test_white_noise_is_rarely_flagged_and_spikes_are_found() -> None:
    """On white radiometer noise over a smooth trend, 5-sigma runs are rare; a 1 %
    spike at 1e-3 noise (10 sigma) is always found."""
    rng = np.random.default_rng(7)
    shape = (4, 2, 50, 1024)
    level = np.ones(shape[:2] + shape[3:])
    trend = 1 + 0.1 * np.sin(np.linspace(0, 3, 1024))
    data = trend * (1 + 1e-3 * rng.standard_normal(shape))
    spikes = rng.random(shape) < 1e-3
    hits, _ = frequency_flags(data * np.where(spikes, 1.01, 1.0), np.zeros(shape, bool), level)
    assert hits[spikes].all()
    assert hits[~spikes].mean() < 2e-3  # the watershed grows a few neighbours of spikes
    clean, _ = frequency_flags(data, np.zeros(shape, bool), level)
    assert clean.mean() < 1e-4


def test_a_ratio_sloping_across_the_band_does_not_flag_its_ends() -> None:
    """Over a day the sky's spectral shape changes, so a spectrum over the time-mean one
    slopes across the band (here by 20 %); the trend is continued linearly beyond the first
    and last block centres, so the band's first and last channels are not flagged."""
    rng = np.random.default_rng(11)
    shape = (2, 2, 40, 161)
    slope = 1 + 0.2 * np.linspace(-1, 1, 161) * np.linspace(-1, 1, 40)[:, None]
    data = slope * (1 + 1e-3 * rng.standard_normal(shape))
    hits, _ = frequency_flags(data, np.zeros(shape, bool), np.ones((2, 2, 161)))
    assert not hits[..., :8].any() and not hits[..., -8:].any()
    assert hits.mean() < 1e-4
