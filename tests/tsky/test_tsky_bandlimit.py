"""The band-limited sky given to the Tsky engine (autocal.tsky.bandlimit)."""

from __future__ import annotations

import healpy as hp
import numpy as np

from autocal.sky.models import UniformSky
from autocal.tsky.bandlimit import band_limit_maps, band_limited_components


def _random_alm(lmax: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = hp.Alm.getsize(lmax)
    alm = rng.normal(size=n) + 1j * rng.normal(size=n)
    ell, m = hp.Alm.getlm(lmax)
    alm[m == 0] = alm[m == 0].real
    return alm / (1.0 + ell)


def test_band_limited_map_is_kept_and_finer_structure_removed():
    nside, fine = 16, 64
    low = _random_alm(2 * nside, 0)
    smooth = hp.alm2map(low, fine, lmax=2 * nside)
    # structure above the band limit (l = 60..90) must not leak into the coarse map
    high = np.zeros(hp.Alm.getsize(90), dtype=complex)
    ell, _ = hp.Alm.getlm(90)
    high[ell >= 60] = _random_alm(90, 1)[ell >= 60] * 50
    rough = smooth + hp.alm2map(high, fine, lmax=90)
    out = band_limit_maps(np.vstack([smooth, rough, np.full(smooth.size, 3.0)]), nside)
    expected = hp.alm2map(low, nside, lmax=2 * nside)
    scale = np.abs(expected).max()
    assert np.abs(out[0] - expected).max() < 1e-3 * scale
    assert np.abs(out[1] - expected).max() < 2e-2 * scale
    # averaging the rough map over the coarse pixels (ud_grade) leaves the fine structure in
    assert np.abs(hp.ud_grade(rough, nside) - expected).max() > 0.1 * scale
    np.testing.assert_array_equal(out[2], 3.0)


def test_components_are_read_only_memoised_and_keep_constants():
    sky = UniformSky(10.0)
    freqs = np.array([100e6, 150e6])
    comps = band_limited_components(sky, freqs, 8)
    assert comps.nside == 8 and comps.maps.shape == (1, hp.nside2npix(8))
    np.testing.assert_array_equal(comps.maps, 1.0)
    assert not comps.maps.flags.writeable
    assert band_limited_components(sky, freqs, 8) is comps
