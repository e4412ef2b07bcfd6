"""Tsky engine: fast ring-FFT method against the brute-force reference, analytic cases."""

from __future__ import annotations

import healpy as hp
import numpy as np
import pytest

from autocal.core.sites import EDGES, HERA, Site
from autocal.sky.analytic_beams import AiryBeam, FunctionBeam, GaussianDipoleBeam, PerturbedBeam
from autocal.sky.beam_names import get_beam
from autocal.sky.file_beams import GriddedFileBeam
from autocal.sky.models import T_CMB, SkyComponents, UniformSky, get_sky
from autocal.tsky.brute import BruteForceTsky, tsky_brute
from autocal.tsky.compute import compute_tsky
from autocal.tsky.horizon import horizon_weight, topocentric_at_lst0
from autocal.tsky.result import TskyError
from autocal.tsky.ringfft import tsky_fft
from autocal.tsky.synthesis import synthesise

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


# optimised engine: chunking, threads, synthesis, vectorised brute force ------------------


def _rough_sky(nside: int, freqs: np.ndarray) -> SkyComponents:
    """A structured low-rank sky (no data files): two smooth random maps plus the CMB."""
    rng = np.random.default_rng(3)
    lmax = 3 * nside - 1
    ell, _ = hp.Alm.getlm(lmax)
    maps = []
    for _ in range(2):
        alm = rng.normal(size=ell.size) + 1j * rng.normal(size=ell.size)
        alm[: lmax + 1] = alm[: lmax + 1].real  # m = 0 terms are real
        maps.append(hp.alm2map(alm / (1.0 + ell) ** 2, nside, lmax=lmax))
    maps = np.vstack([1.0 + 0.5 * np.array(maps), np.ones((1, hp.nside2npix(nside)))])
    spectra = np.column_stack(
        [300 * (freqs / 150e6) ** -2.5, 40 * (freqs / 150e6) ** -2.1, np.full(freqs.size, T_CMB)]
    )
    return SkyComponents(maps, spectra, ("a", "b", "cmb"), freqs, nside, 2451545.0)


@pytest.mark.parametrize(
    "site", [HERA, EDGES, Site("south-pole", -90.0, 0.0), Site("arctic", 89.0, 10.0)]
)
def test_fft_matches_references_at_any_latitude(site, lst_day):
    """Sites where many rings never rise (poles) or the caps are cut by the horizon.

    Against the float64 vectorised brute force (the same band-limited rotation) the
    engine agrees to its float32 rounding; against tsky_brute (beam re-evaluated per
    LST) to the pixelisation of this coarse grid (nside 16, wide beam at 60 MHz).
    """
    freqs = np.array([60e6, 150e6])
    sky = _rough_sky(16, freqs)
    beam = GaussianDipoleBeam()
    fast = tsky_fft(sky, beam, site, lst_day)
    exact = BruteForceTsky(sky, beam, site)(lst_day)
    slow = tsky_brute(sky, beam, site, lst_day)
    scale = np.abs(slow.tsky).max()
    assert np.abs(fast.tsky - exact.tsky).max() <= 1e-6 * scale
    assert np.abs(fast.tsky - slow.tsky).max() <= 5e-4 * scale
    np.testing.assert_allclose(fast.f_below, exact.f_below, rtol=1e-12)


def test_fft_independent_of_chunks_and_threads(lst_day):
    """Frequency chunks and worker threads change nothing but the order of sums."""
    freqs = np.linspace(50e6, 200e6, 7)
    sky = _rough_sky(16, freqs)
    beam = PerturbedBeam()
    ref = tsky_fft(sky, beam, HERA, lst_day, freq_chunk=7, workers=1, keep_components=True)
    for chunk, workers in [(1, 1), (3, 2), (2, 3), (None, None)]:
        other = tsky_fft(
            sky, beam, HERA, lst_day, freq_chunk=chunk, workers=workers, keep_components=True
        )
        # the same sums in another order: equal to the float32 rounding of the FFTs
        np.testing.assert_allclose(other.tsky, ref.tsky, rtol=1e-7)
        np.testing.assert_allclose(other.components, ref.components, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(other.f_below, ref.f_below, rtol=1e-12)


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("bad", [-1.0, np.nan])
def test_bad_beam_values_are_reported(workers, bad):
    """Negative or NaN beam values raise, also from worker threads."""
    beam = FunctionBeam(
        lambda f, az, za: np.where(za > 2.0, bad, 1.0)[None, :] * np.ones((f.size, 1)),
        key=f"bad{bad}",
    )
    sky = UniformSky(100.0).components(FREQS, nside=8)
    with pytest.raises(TskyError, match="negative or non-finite"):
        tsky_fft(sky, beam, HERA, [0.0, 1.0], freq_chunk=1, workers=workers)


@pytest.mark.parametrize(
    "lsts",
    [
        np.arange(8640) * 24 / 8640,  # regular, one inverse real FFT
        np.linspace(0.0, 24.0, 49)[:-1] + 3.1,  # regular with an offset
        np.arange(0.0, 24.0, 2.0),  # fewer points per day than harmonics: aliased
        np.array([23.91, 0.013, 7.77, 13.3]),  # irregular: matrix product
        (np.arange(600) * 24 / 1200)[::-1],  # regular grid, half a day, reversed
    ],
)
def test_synthesis_paths_agree(lsts):
    rng = np.random.default_rng(0)
    coef = rng.normal(size=(33, 5)) + 1j * rng.normal(size=(33, 5))
    lst_rad = np.mod(lsts, 24.0) * 2 * np.pi / 24
    phase = np.outer(lst_rad, np.arange(33))
    direct = np.cos(phase) @ coef.real + np.sin(phase) @ coef.imag
    np.testing.assert_allclose(synthesise(coef, lst_rad), direct, rtol=0, atol=1e-11)


def test_vectorised_brute_force_matches_both_references(lst_day):
    """The benchmark's baseline agrees with the engine (same band-limited rotation) to
    rounding, and with the per-LST beam evaluation of tsky_brute to pixelisation."""
    freqs = np.array([60e6, 110e6, 180e6])
    sky = _rough_sky(32, freqs)
    beam = GaussianDipoleBeam(pol="nn")
    lsts = lst_day[::5]
    fast = tsky_fft(sky, beam, EDGES, lsts, tgnd=250.0)
    slow = tsky_brute(sky, beam, EDGES, lsts, tgnd=250.0)
    scale = np.abs(slow.tsky).max()
    # float32 products accumulate rounding over ~Npix/2 terms (the engine's m >= 1 terms
    # are float32 too, but its m = 0 term and all sums are float64)
    for dtype, tol in [(np.float64, 1e-6), (np.float32, 1e-5)]:
        brute = BruteForceTsky(sky, beam, EDGES, tgnd=250.0, dtype=dtype, freq_chunk=2)
        for batch in (1, 3):
            vec = brute(lsts, lsts_per_product=batch)
            assert np.abs(vec.tsky - fast.tsky).max() <= tol * scale
            assert np.abs(vec.tsky - slow.tsky).max() <= 1e-4 * scale
            np.testing.assert_allclose(vec.f_below, fast.f_below, rtol=1e-10)
    rotated = brute.rotated_sky(0.0)
    np.testing.assert_allclose(rotated, sky.maps, atol=1e-10)


# beam evaluation used by the engine ------------------------------------------------------


class _TableBeam(GriddedFileBeam):
    """A gridded beam from an in-memory table ``(Nnative, Ndir)`` (directions fixed)."""

    name = "table"

    def __init__(self, native_freqs: np.ndarray, table: np.ndarray) -> None:
        self.native_freqs = native_freqs
        self.table = table

    def _spatial(self, az, za):
        return self.table[:, : np.size(az)]

    def describe(self):
        return {"beam": "table"}


@pytest.mark.parametrize("nnative", [1, 2, 3, 7])
def test_gridded_beam_spline_matches_scipy(nnative):
    """The local spline form equals scipy's not-a-knot CubicSpline, clipped at zero."""
    from scipy.interpolate import CubicSpline

    rng = np.random.default_rng(nnative)
    knots = np.sort(rng.uniform(100e6, 200e6, nnative))
    knots[0], knots[-1] = 100e6, 200e6
    if nnative == 1:
        knots = np.array([150e6])
    table = rng.normal(0.5, 0.5, size=(nnative, 40))  # some negative undershoot too
    beam = _TableBeam(knots, table)
    freqs = np.sort(rng.uniform(knots[0], knots[-1], 11))
    if nnative == 1:
        freqs = knots
        expected = np.maximum(table, 0.0)
    else:
        expected = np.maximum(CubicSpline(knots, table, axis=0)(freqs), 0.0)
    az = np.zeros(40)
    np.testing.assert_allclose(beam.power(freqs, az, az), expected, rtol=1e-12, atol=1e-14)
    evaluator = beam.on(az, az)
    np.testing.assert_allclose(evaluator(freqs), expected, rtol=1e-12, atol=1e-14)
    rows = slice(5, 23)
    by_dir = evaluator.by_direction(freqs, rows)
    assert by_dir.flags.c_contiguous and by_dir.shape == (18, freqs.size)
    np.testing.assert_allclose(by_dir, expected[:, rows].T, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("beam", [GaussianDipoleBeam(pol="nn"), PerturbedBeam(base=AiryBeam())])
def test_evaluator_by_direction_matches_power(beam):
    az = np.linspace(0, 2 * np.pi, 50)
    za = np.linspace(0, np.pi, 50)
    evaluator = beam.on(az, za)
    np.testing.assert_allclose(evaluator.by_direction(FREQS), beam.power(FREQS, az, za).T)
    part = evaluator.by_direction(FREQS, slice(10, 30))
    np.testing.assert_allclose(part, beam.power(FREQS, az[10:30], za[10:30]).T)


@pytest.mark.data
def test_hera_beam_evaluator_matches_power(data_root):
    beam = get_beam("hera", "ee")
    az, za = topocentric_at_lst0(8, HERA)
    freqs = np.array([100e6, 123.4e6, 150e6, 199.9e6])
    expected = beam.power(freqs, az, za)
    evaluator = beam.on(az, za)
    np.testing.assert_allclose(evaluator(freqs), expected, rtol=1e-12, atol=1e-15)
    part = evaluator.by_direction(freqs, slice(100, 300))
    np.testing.assert_allclose(part, expected[:, 100:300].T, rtol=1e-12, atol=1e-15)


def test_constant_components_in_any_order(lst_day):
    """Constant maps (the CMB) skip the ring transforms wherever they sit in the list."""
    freqs = np.array([80e6, 160e6])
    sky = _rough_sky(16, freqs)
    order = [2, 0, 1]  # cmb first: the moving components are not a leading slice
    mixed = SkyComponents(
        sky.maps[order], sky.spectra[:, order], ("cmb", "a", "b"), freqs, 16, sky.epoch_jd
    )
    beam = GaussianDipoleBeam()
    ref = tsky_fft(sky, beam, HERA, lst_day, keep_components=True)
    got = tsky_fft(mixed, beam, HERA, lst_day, keep_components=True)
    np.testing.assert_allclose(got.tsky, ref.tsky, rtol=1e-9)
    np.testing.assert_allclose(got.components, ref.components[..., order], rtol=1e-9, atol=1e-12)


def test_nan_in_clipped_file_beam_is_reported():
    """Gridded beams skip the sign check (they are clipped at 0); NaN still raises."""
    npix = hp.nside2npix(8)
    table = np.ones((3, npix))
    table[1, 100] = np.nan
    beam = _TableBeam(np.array([100e6, 150e6, 200e6]), table)
    sky = UniformSky(100.0).components(np.array([120e6, 140e6]), nside=8)
    with pytest.raises(TskyError, match="negative or non-finite"):
        tsky_fft(sky, beam, HERA, [0.0, 1.0])
