"""Total uncertainties (autocal.fit.uncertainty): algebra, limits and behaviour on toy data.

Coverage on observations written by an independent simulator is in
tests/fit/test_uncertainty_coverage.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from autocal.core.observation import Observation
from autocal.core.sites import HERA
from autocal.fit.lsq import FitModel, accumulate, fit, solve_sums
from autocal.fit.uncertainty import (
    MIN_BLOCKS,
    accumulate_blocks,
    base_sums,
    block_edges,
    extended_model,
    profile_gain,
    separation_summary,
    total_uncertainty,
)

NF = 24
FREQS = np.linspace(110e6, 190e6, NF)


def short_sky(nt: int, span_h: float = 0.5, lst0: float = 3.2) -> tuple[np.ndarray, np.ndarray]:
    """A sky that changes by ~1 % over half an hour, with some curvature (LSTs, Tsky)."""
    lsts = lst0 + np.linspace(0.0, span_h, nt)
    x = (lsts - lst0) / span_h
    shape = 1.0 + 0.02 * x + 0.01 * x**2
    return lsts, 250.0 * shape[:, None] * (FREQS / 150e6)[None, :] ** -2.5


def make_obs(data: np.ndarray, lsts: np.ndarray, bt: float = 1e6) -> Observation:
    nant, npol, _, nf = data.shape
    return Observation(
        data=data,
        freqs=FREQS[:nf],
        lsts=lsts,
        jds=2458116.0 + (lsts - lsts[0]) / 24.0,
        antennas=np.arange(nant),
        pols=("ee", "nn")[:npol],
        site=HERA,
        channel_width=bt,
        integration_time=1.0,
    )


def test_block_edges_cover_the_integrations_and_degrade_gracefully() -> None:
    edges = block_edges(174)
    assert edges[0] == 0 and edges[-1] == 174 and len(edges) == 11
    assert np.all(np.diff(edges) >= 17)
    assert len(block_edges(9)) == MIN_BLOCKS + 1  # 4 blocks of two or more
    np.testing.assert_array_equal(block_edges(7), [0, 7])  # too few: one block
    # memory: blocks shrink to what fits, and below MIN_BLOCKS there is one
    assert len(block_edges(1000, bytes_per_block=1 << 28)) == 5
    np.testing.assert_array_equal(block_edges(1000, bytes_per_block=1 << 29), [0, 1000])


@pytest.mark.parametrize("order", [0, 1])
def test_block_sums_add_up_to_the_ordinary_fit(order: int) -> None:
    rng = np.random.default_rng(3)
    lsts, tsky = short_sky(60)
    data = (tsky + 150.0)[None, None] * (1 + rng.standard_normal((1, 1, 60, NF)) * 1e-3)
    kind = "constant" if order == 0 else "legendre"
    model = FitModel.for_lsts(lsts, kind, order)
    blocks = accumulate_blocks(
        model, data, tsky, lsts, block_edges(60), weights="radiometer", bandwidth_time=1e6
    )
    whole = accumulate(model, data, tsky, lsts, weights="radiometer", bandwidth_time=1e6)
    base = blocks.fitted_total()
    np.testing.assert_allclose(base.ata, whole.ata, rtol=1e-12)
    np.testing.assert_allclose(base.aty, whole.aty, rtol=1e-12)
    np.testing.assert_allclose(base.yty, whole.yty, rtol=1e-12)
    np.testing.assert_array_equal(base.count, whole.count)
    # and the extended model's sums are those of the model with one more order
    ext = accumulate(
        extended_model(model), data, tsky, lsts, weights="radiometer", bandwidth_time=1e6
    )
    np.testing.assert_allclose(blocks.total().ata, ext.ata, rtol=1e-12)
    np.testing.assert_allclose(base_sums(ext, model).ata, whole.ata, rtol=1e-12)


def test_too_few_integrations_say_so_and_fall_back_to_the_statistics() -> None:
    lsts, tsky = short_sky(6)
    data = (tsky + 150.0)[None, None] * 1.0
    sol = fit(make_obs(data, lsts), tsky)
    assert sol.total is not None and sol.total.nblocks == 1
    assert any("no jackknife" in note for note in sol.total.notes)
    assert np.all(np.isnan(sol.total.jackknife_factor))


def test_profile_gain_is_the_constrained_least_squares_solution() -> None:
    rng = np.random.default_rng(5)
    lsts, tsky = short_sky(40)
    truth = 0.02 * (tsky + 180.0)
    data = (truth * (1 + 1e-3 * rng.standard_normal(truth.shape)))[None, None]
    sol = fit(make_obs(data, lsts), tsky, weights="identity")
    model = sol.model
    sums = accumulate(model, data, tsky, lsts, weights="identity")
    vg = np.r_[1.0, 0.0]
    trxr = np.array([100.0, float(np.median(sol.Trxr))])
    prof = profile_gain(sums, model, vg, trxr)
    # brute force: least squares of R = G (Tsky + Trxr) per channel
    for f in (0, NF // 2, NF - 1):
        for i, t in enumerate(trxr):
            x = tsky[:, f] + t
            g = np.dot(x, data[0, 0, :, f]) / np.dot(x, x)
            assert prof[0, 0, i, f] == pytest.approx(g, rel=1e-9)
    # at the fitted Trxr of a channel the profile gives the fitted G
    t_hat = sol.Trxr[0, 0, 3]
    at_fit = profile_gain(sums, model, vg, np.array([t_hat]))[0, 0, 0, 3]
    assert at_fit == pytest.approx(sol.G[0, 0, 3], rel=1e-7)


def test_drift_sensitivity_matches_an_injected_drift() -> None:
    """(dG/G)/delta predicted from the sums equals what a small injected drift does."""
    lsts, tsky = short_sky(80)
    clean = 0.02 * (tsky + 150.0)
    delta = 1e-4
    s = np.linspace(-1.0, 1.0, lsts.size)[:, None]
    drifted = clean * (1 + delta * s / 2)
    sol0 = fit(make_obs(clean[None, None], lsts), tsky, weights="identity")
    sol1 = fit(make_obs(drifted[None, None], lsts), tsky, weights="identity")
    measured = (sol1.G - sol0.G) / sol0.G / delta
    assert sol0.total is not None
    np.testing.assert_allclose(sol0.total.drift_sensitivity, measured, rtol=0.02)
    # the sky varies by ~1 % of Tsys here: the separation is weak
    assert np.all(np.abs(measured) > 10)
    assert sol0.total.separation().all()


def test_sky_contrast_is_the_rms_of_tsky_over_tsys() -> None:
    lsts, tsky = short_sky(50)
    data = (0.03 * (tsky + 200.0))[None, None]
    sol = fit(make_obs(data, lsts), tsky, weights="identity")
    expected = tsky.std(axis=0) / (tsky.mean(axis=0) + 200.0)
    assert sol.total is not None
    np.testing.assert_allclose(sol.total.sky_contrast[0, 0], expected, rtol=1e-6)
    noisy = data * (1 + 1e-3 * np.random.default_rng(1).standard_normal(data.shape))
    sol = fit(make_obs(noisy, lsts), tsky)
    assert sol.total is not None
    np.testing.assert_allclose(sol.total.corr_G_n, -1.0, atol=1e-3)  # weakly separated


def test_time_correlated_residuals_raise_the_jackknife_factor() -> None:
    """Broadband gain wander correlated over minutes: the jackknife sees it, the
    radiometer covariance (even inflated by chi2/dof) does not, and the total covers
    the truth where the statistical error does not."""
    rng = np.random.default_rng(11)
    nt = 200
    lsts = np.linspace(0.0, 23.9, nt)
    tsky = (
        250.0
        * (1.0 + 2.5 * np.exp(-0.5 * ((lsts - 17.5) / 3.0) ** 2))[:, None]
        * (FREQS / 150e6)[None, :] ** -2.5
    )
    inside, outside, ratios = [], [], []
    for _ in range(20):
        walk = np.cumsum(rng.standard_normal(nt)) * 2e-3  # a random-walk gain
        walk -= walk.mean()
        gain = (1.0 + walk)[:, None]
        data = gain * (tsky + 150.0) * (1 + rng.standard_normal((nt, NF)) * 1e-3)
        sol = fit(make_obs(data[None, None], lsts), tsky)
        g_true = 1.0  # the time average of the gain
        assert sol.total is not None
        ratios.append(np.nanmedian(sol.total.jackknife_factor))
        inside.append(np.abs(sol.G - g_true) < 2 * sol.sigma_G)
        outside.append(np.abs(sol.G - g_true) < 2 * sol.sigma_G_stat)
    assert np.median(ratios) > 3.0
    assert np.mean(inside) > 0.85
    assert np.mean(outside) < np.mean(inside) - 0.2


def test_the_total_matches_the_separation_summary_and_refits_without_blocks() -> None:
    rng = np.random.default_rng(2)
    lsts, tsky = short_sky(60)
    data = (0.02 * (tsky + 150.0))[None, None] * (1 + 1e-3 * rng.standard_normal((1, 2, 60, NF)))
    sol = fit(make_obs(data, lsts), np.stack([tsky, tsky]))
    summary = separation_summary(sol)
    assert [(e["antenna"], e["pol"]) for e in summary] == [(0, "ee"), (0, "nn")]
    for e in summary:
        ip = sol.pols.index(e["pol"])
        assert e["G"] == pytest.approx(float(np.nanmedian(sol.G[0, ip])))
        assert e["separation"] == "weak" and "weak separation" in e["message"]
        assert "if Trxr = 150 K" in e["message"]
    # the refits of the total use the same blocks: recomputing gives the same arrays
    model = sol.model
    blocks = accumulate_blocks(
        model,
        data,
        np.stack([tsky, tsky]),
        lsts,
        block_edges(60),
        weights="radiometer",
        bandwidth_time=1e6,
    )
    again = total_uncertainty(blocks, solve_sums(blocks.fitted_total(), scale_covariance=False))
    assert again.nblocks == sol.total.nblocks
    assert np.all(np.isfinite(again.cov[0, 0, :, 0, 0]))


def test_per_pol_weights_are_sliced_per_block() -> None:
    """Inverse variances given per pol (Npol, Ntime, Nfreq) work with the total as without."""
    rng = np.random.default_rng(4)
    lsts, tsky = short_sky(40)
    data = (0.02 * (tsky + 150.0))[None, None] * (1 + 1e-3 * rng.standard_normal((1, 2, 40, NF)))
    w = np.broadcast_to(1.0 / (1e-3 * data[0]) ** 2, (2, 40, NF)).copy()
    obs = make_obs(data, lsts)
    total = fit(obs, np.stack([tsky, tsky]), weights=w)
    stat = fit(obs, np.stack([tsky, tsky]), weights=w, uncertainty="statistical")
    np.testing.assert_allclose(total.G, stat.G, rtol=1e-9)
    assert total.total is not None and total.total.nblocks == 10


@pytest.mark.parametrize("order", [1, 2])
def test_the_jackknife_is_judged_against_what_the_model_predicts(order: int) -> None:
    """A Legendre fit's delete-a-block refits extrapolate at the ends of the span, so the raw
    jackknife variance exceeds the statistical one on clean data; the factor compares it
    with the jackknife variance the statistical model predicts instead (~1 on clean data)."""
    from tests.fit.test_fit import make_obs as day_obs
    from tests.fit.test_fit import noisy, toy_tsky

    rng = np.random.default_rng(12)
    tsky = toy_tsky()
    factors = []
    for _ in range(10):
        sol = fit(
            day_obs(noisy((tsky + 150.0)[None, None], rng)), tsky, model="legendre", order=order
        )
        assert sol.total is not None
        factors.append(sol.total.jackknife_factor)
    assert 0.7 < np.nanmedian(factors) < 1.2
