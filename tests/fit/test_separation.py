"""How well G and n separate, and the summary per antenna-pol (autocal.fit.separation)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.fit.blocks import accumulate_blocks, block_edges
from autocal.fit.passes import fit
from autocal.fit.separation import profile_gain, separation_summary
from autocal.fit.solve import solve_sums
from autocal.fit.sums import accumulate
from autocal.fit.total_uncertainty import total_uncertainty
from tests.fit.toy import SHORT_NF as NF
from tests.fit.toy import short_obs as make_obs
from tests.fit.toy import short_sky


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


def test_the_summary_medians_are_numpys_over_the_solved_finite_channels() -> None:
    # several antennas, flagged channels and a non-finite value: each entry's medians are
    # np.median over that antenna-pol's solved, finite channels (computed here one by one)
    rng = np.random.default_rng(4)
    lsts, tsky = short_sky(60)
    gains = np.array([0.02, 0.03, 0.05])[:, None, None, None]
    data = gains * (tsky + 150.0) * (1 + 1e-3 * rng.standard_normal((3, 2, 60, NF)))
    data[1, 0, :, 3] = 0.0  # a dead channel: flagged, left out of the medians
    sol = fit(make_obs(data, lsts), np.stack([tsky, tsky]))
    sol.total.drift_weight[2, 1, 5] = np.inf  # not finite: left out as NaN is
    summary = separation_summary(sol)
    assert len(summary) == 6 and not sol.flags[1, 0].all() and sol.flags[1, 0, 3]

    def one_by_one(arr: np.ndarray, ia: int, ip: int) -> float | None:
        vals = arr[ia, ip][~sol.flags[ia, ip]]
        vals = vals[np.isfinite(vals)]
        return float(np.median(vals)) if vals.size else None

    for e in summary:
        ia, ip = list(sol.antennas).index(e["antenna"]), sol.pols.index(e["pol"])
        assert e["channels"] == int((~sol.flags[ia, ip]).sum())
        assert e["G"] == one_by_one(sol.G, ia, ip)
        assert e["Trxr_K"] == one_by_one(sol.Trxr, ia, ip)
        assert e["drift_weight"] == one_by_one(sol.total.drift_weight, ia, ip)
        assert e["jackknife_factor"] == one_by_one(sol.total.jackknife_factor, ia, ip)
        assert e["G_halves"] == [one_by_one(sol.total.G_halves[h], ia, ip) for h in range(2)]
        for i, t in enumerate(sol.total.profile_trxr):
            assert e["G_if_trxr_K"][f"{t:g}"] == one_by_one(sol.total.profile_G[:, :, i], ia, ip)


def test_the_closed_form_drift_sensitivity_is_the_lapack_solve() -> None:
    """The constant model's Cramer's-rule solve equals numpy's batched LAPACK solve to
    rounding, and gives NaN for singular or non-finite systems and unsolved channels."""
    from autocal.fit.centring import uncentre
    from autocal.fit.separation import _drift_sensitivity_2x2

    rng = np.random.default_rng(3)
    n = 4000
    m = rng.normal(size=(n, 2, 3))
    a = m @ np.swapaxes(m, -1, -2) * rng.uniform(1e-3, 1e3, (n, 1, 1))
    rhs = rng.normal(size=(n, 2))
    c = rng.uniform(100, 1000, n)
    theta = np.stack([rng.uniform(0.5, 2.0, n), rng.uniform(100, 300, n)], -1)
    vg = np.array([1.0, 0.0])
    ok = np.ones(n, bool)
    a[:10] = 0.0  # singular
    a[10:20, 0, 1] = np.nan
    ok[20:30] = False  # unsolved channels
    got = _drift_sensitivity_2x2(a, rhs, ok, c, vg, theta)
    dx = uncentre(np.linalg.solve(a[30:], rhs[30:, :, None])[..., 0], c[30:])
    np.testing.assert_allclose(got[30:], (dx @ vg) / theta[30:, 0], rtol=1e-9)
    assert np.isnan(got[:30]).all()
