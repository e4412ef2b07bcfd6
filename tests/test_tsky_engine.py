"""Tsky engine: fast ring-FFT method against the brute-force reference, analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.beams import AiryBeam, FunctionBeam, GaussianDipoleBeam, get_beam
from autocal.sites import EDGES, HERA
from autocal.sky import T_CMB, UniformSky, get_sky
from autocal.tsky import compute_tsky, horizon_weight, topocentric_at_lst0, tsky_brute, tsky_fft

FREQS = np.array([100e6, 137.5e6, 175e6, 200e6])


@pytest.fixture(scope="module")
def gsm64(data_root):
    return get_sky("gsm2008").components(FREQS, nside=64)


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.parametrize("beam_name", ["dipole", "airy", "hera"])
def test_fft_matches_brute_force(gsm64, beam_name, lst_day, data_root):
    beam = get_beam(beam_name, "ee")
    fast = tsky_fft(gsm64, beam, HERA, lst_day)
    slow = tsky_brute(gsm64, beam, HERA, lst_day)
    diff = np.abs(fast.tsky - slow.tsky)
    assert fast.tsky.shape == (lst_day.size, FREQS.size)
    assert diff.max() <= 0.01, f"{beam_name}: max |fft - brute| = {diff.max():.4f} K"
    np.testing.assert_allclose(fast.f_below, slow.f_below, atol=1e-5)


@pytest.mark.data
def test_fft_matches_brute_force_nn_and_irregular_lsts(gsm64):
    """Arbitrary (unsorted, off-grid) LSTs and the nn dipole at the EDGES site."""
    lsts = np.array([23.91, 0.013, 7.77, 13.3, 17.8, 5.5])
    beam = GaussianDipoleBeam(pol="nn")
    fast = tsky_fft(gsm64, beam, EDGES, lsts)
    slow = tsky_brute(gsm64, beam, EDGES, lsts)
    assert np.abs(fast.tsky - slow.tsky).max() <= 0.01


@pytest.mark.parametrize("tgnd", [300.0, 0.0])
def test_uniform_sky_is_exact(tgnd, lst_day):
    """A uniform sky T0 gives T0 f_above + Tgnd f_below, with f from the beam itself."""
    t0 = 1234.5
    sky = UniformSky(t0).components(FREQS, nside=32)
    beam = GaussianDipoleBeam()
    result = tsky_fft(sky, beam, HERA, lst_day, tgnd=tgnd)
    az, za = topocentric_at_lst0(32, HERA)
    a = beam.power(FREQS, az, za)
    w = horizon_weight(np.pi / 2 - za)
    f_above = (a @ w) / a.sum(axis=1)
    expected = t0 * f_above + tgnd * (1 - f_above)
    np.testing.assert_allclose(
        result.tsky, np.broadcast_to(expected, result.tsky.shape), rtol=1e-12
    )
    np.testing.assert_allclose(result.f_above, f_above, rtol=1e-12)
    assert np.all(f_above < 1) and np.all(f_above > 0.9)


def test_beam_below_horizon_gives_ground_temperature(lst_day):
    nadir = FunctionBeam(
        lambda f, az, za: np.where(za > 0.6 * np.pi, 1.0, 0.0)[None, :] * np.ones((f.size, 1)),
        key="nadir",
    )
    sky = UniformSky(5000.0).components(FREQS, nside=16)
    for method in (tsky_fft, tsky_brute):
        result = method(sky, nadir, HERA, lst_day, tgnd=287.0)
        np.testing.assert_allclose(result.tsky, 287.0, rtol=1e-12)
        np.testing.assert_allclose(result.f_below, 1.0)


def test_cmb_counted_once(lst_day):
    """A sky that is only the CMB: its maps exclude it, so autocal adds it exactly once."""
    sky = UniformSky(T_CMB, includes_cmb=True).components(FREQS, nside=16)
    no_cmb = UniformSky(0.0, includes_cmb=False).components(FREQS, nside=16)
    assert sky.labels == ("uniform",)
    assert no_cmb.labels == ("uniform", "cmb")
    np.testing.assert_allclose(no_cmb.temperature(), T_CMB)
    beam = AiryBeam()
    a = tsky_fft(sky, beam, HERA, lst_day, tgnd=0.0)
    b = tsky_fft(no_cmb, beam, HERA, lst_day, tgnd=0.0)
    np.testing.assert_allclose(a.tsky, b.tsky, rtol=1e-12)
    expected = np.broadcast_to(T_CMB * a.f_above, a.tsky.shape)
    np.testing.assert_allclose(a.tsky, expected, rtol=1e-9)


def test_cost_independent_of_lst_count():
    """Doubling the LSTs reuses the same overlaps: results agree on shared LSTs."""
    sky = UniformSky(100.0).components(FREQS, nside=16)
    beam = GaussianDipoleBeam()
    coarse = tsky_fft(sky, beam, HERA, np.arange(0, 24, 1.0))
    fine = tsky_fft(sky, beam, HERA, np.arange(0, 24, 0.5))
    np.testing.assert_allclose(coarse.tsky, fine.tsky[::2], rtol=1e-12)


@pytest.mark.data
def test_components_reconstruct_tsky(gsm64, lst_day):
    beam = GaussianDipoleBeam()
    result = tsky_fft(gsm64, beam, HERA, lst_day, keep_components=True)
    rebuilt = np.einsum("fc,lfc->lf", gsm64.spectra, result.components)
    rebuilt += 300.0 * result.f_below[None, :]
    np.testing.assert_allclose(rebuilt, result.tsky, rtol=1e-10)


@pytest.mark.data
def test_frequency_dependent_ground(gsm64, lst_day):
    beam = GaussianDipoleBeam()
    tg = np.linspace(250.0, 320.0, FREQS.size)
    var = tsky_fft(gsm64, beam, HERA, lst_day, tgnd=tg)
    for i, t in enumerate(tg):
        const = tsky_fft(gsm64, beam, HERA, lst_day, tgnd=t)
        np.testing.assert_allclose(var.tsky[:, i], const.tsky[:, i], rtol=1e-12)


def test_horizon_weight_limits():
    alt = np.radians([-10.0, -1.0, 0.0, 1.0, 10.0])
    w = horizon_weight(alt, 2.0)
    np.testing.assert_allclose(w, [0.0, 0.0, 0.5, 1.0, 1.0])
    np.testing.assert_array_equal(horizon_weight(alt, 0.0), [0, 0, 0, 1, 1])


def test_compute_tsky_uniform_end_to_end(tmp_cache):
    result = compute_tsky("uniform:500", "dipole", "hera", FREQS, [0.0, 6.0], nside=16)
    assert result.meta["sky"]["model"] == "uniform"
    assert result.meta["cmb"].startswith("included once")
    expected = np.broadcast_to(500 * result.f_above + 300 * result.f_below, result.tsky.shape)
    np.testing.assert_allclose(result.tsky, expected, rtol=1e-9)
