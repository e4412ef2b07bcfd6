"""Total uncertainties (autocal.fit.total_uncertainty): limits and behaviour on toy data.

Block sums are tested in tests/fit/test_blocks.py, the separation diagnostics in
tests/fit/test_separation.py; coverage on observations written by an independent simulator
is in tests/fit/test_total_uncertainty_coverage.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from autocal.fit.blocks import BlockSums, accumulate_blocks, block_edges, subtract_sums
from autocal.fit.model import FitModel
from autocal.fit.passes import fit
from autocal.fit.solve import solve_sums
from autocal.fit.sums import NormalSums
from autocal.fit.total_uncertainty import total_uncertainty
from tests.fit.toy import SHORT_FREQS as FREQS
from tests.fit.toy import SHORT_NF as NF
from tests.fit.toy import make_obs as day_obs
from tests.fit.toy import noisy, short_sky, toy_tsky
from tests.fit.toy import short_obs as make_obs


def test_too_few_integrations_say_so_and_fall_back_to_the_statistics() -> None:
    lsts, tsky = short_sky(6)
    data = (tsky + 150.0)[None, None] * 1.0
    sol = fit(make_obs(data, lsts), tsky)
    assert sol.total is not None and sol.total.nblocks == 1
    assert any("no jackknife" in note for note in sol.total.notes)
    assert np.all(np.isnan(sol.total.jackknife_factor))


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


@pytest.mark.parametrize("order", [1, 2])
def test_the_jackknife_is_judged_against_what_the_model_predicts(order: int) -> None:
    """A Legendre fit's delete-a-block refits extrapolate at the ends of the span, so the raw
    jackknife variance exceeds the statistical one on clean data; the factor compares it
    with the jackknife variance the statistical model predicts instead (~1 on clean data)."""
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


def test_a_channel_without_a_fitted_solution_adds_nothing_to_the_drift_statistic() -> None:
    """A channel whose fit is flagged (here: non-positive gain, as solve_sums reports it)
    has no chi2 drop to the extended model, whose solution it may still have: its
    antenna-pol's joint statistic, and so every other channel's drift weight, is that of
    the same data without the channel. (The extended model's extra coefficients alone
    are not a chi2 drop: on a gain that drifts, or a channel with RFI, they made the
    joint statistic, and the weight of every channel, jump to 1.)"""
    rng = np.random.default_rng(5)
    nt = 60
    lsts, tsky = short_sky(nt)
    model = FitModel.for_lsts(lsts)
    drift = np.ones((nt, NF))
    drift[:, 5] += 0.05 * np.linspace(-0.5, 0.5, nt)  # channel 5's gain drifts by 5 %
    data = noisy((drift * (tsky + 150.0))[None, None], rng, 1e6)
    blocks = accumulate_blocks(model, data, tsky, lsts, block_edges(nt), bandwidth_time=1e6)
    solved = solve_sums(blocks.fitted_total(), scale_covariance="inflate")
    flagged = {name: value.copy() for name, value in solved.items()}
    for name in ("coeffs", "cov", "chi2"):
        flagged[name][0, 0, 5] = np.nan
    flagged["flag_reason"][0, 0, 5] = 3
    with_flag = total_uncertainty(blocks, flagged)

    def without(s: NormalSums) -> NormalSums:
        out = subtract_sums(s, s)  # zeros of the same shapes
        keep = np.arange(NF) != 5
        for name in ("ata", "aty", "yty", "count"):
            getattr(out, name)[0, 0, keep] = getattr(s, name)[0, 0, keep]
        return out

    gone = BlockSums(
        [without(b) for b in blocks.blocks],
        model,
        blocks.edges,
        blocks.lsts,
        without(blocks.extended),
    )
    reference = total_uncertainty(gone, solve_sums(gone.fitted_total(), scale_covariance="inflate"))
    others = np.arange(NF) != 5
    assert np.all(np.isfinite(reference.drift_weight[0, 0, others]))
    np.testing.assert_array_equal(
        with_flag.drift_weight[0, 0, others], reference.drift_weight[0, 0, others]
    )
    assert np.isnan(with_flag.drift_weight[0, 0, 5]) and np.isnan(with_flag.cov[0, 0, 5]).all()


def test_a_short_span_jackknife_factor_keeps_its_digits() -> None:
    """A Legendre-1 fit over ten minutes: scaling the data by 1 + 3.6e-15 or 1 - 7.1e-15
    (which leaves ``f_jk`` unchanged in exact arithmetic) moves it by < 1e-4. Its
    covariances of ``(G, n)`` have a condition number ~1e15 there; inverted in that basis,
    ``f_jk`` moved by 46 % (median) and up to x12; the basis ``(G, n + c G)`` of the
    sky-centred frame keeps it."""
    nt = 192
    lsts = 3.2 + np.linspace(0.0, 10.0 / 60.0, nt)
    x = (lsts - 3.2) / (10.0 / 60.0)
    tsky = 250.0 * (1.0 + 0.01 * x + 0.002 * x**2)[:, None] * (FREQS / 150e6)[None, :] ** -2.5
    data = noisy((tsky + 150.0)[None, None], np.random.default_rng(4), bt=1e6)
    factors = []
    for scale in (1.0, 1.0 + 2.0**-48, 1.0 - 2.0**-47):
        sol = fit(make_obs(data * scale, lsts), tsky, model="legendre", order=1)
        assert sol.total is not None
        factors.append(np.asarray(sol.total.jackknife_factor))
    assert np.isfinite(factors[0]).sum() >= 5
    for other in factors[1:]:
        np.testing.assert_allclose(other, factors[0], rtol=1e-4)


@pytest.mark.parametrize("prior_kind", [None, "per antenna", "shared"])
def test_antennas_done_in_parts_on_threads_give_the_same_bits(
    monkeypatch: pytest.MonkeyPatch, prior_kind: str | None
) -> None:
    """The total uncertainty of 13 antennas done in parts of four or eight antennas, on
    one and two threads, equals the one done whole bit for bit: every array, the profile's
    grid (from all channels) and the notes (an antenna whose gain cannot drift: counted
    once), with no prior, a prior per antenna (cut with the parts) and one shared by all.
    Fewer parts than threads: one part."""
    import autocal.fit.total_uncertainty as tu
    from autocal.fit.priors import PriorTerm

    rng = np.random.default_rng(5)
    nant, npol, nt = 13, 2, 64
    lsts = np.linspace(1.0, 9.0, nt)
    tsky = 250.0 * (1 + 0.5 * np.sin(lsts / 3.0))[:, None] * (FREQS / 150e6)[None, :] ** -2.5
    gains = rng.uniform(0.5, 2.0, (nant, npol, 1, 1))
    trxr = rng.uniform(100.0, 300.0, (nant, npol, 1, NF))
    drifting = (rng.random(nant) < 0.5)[:, None, None, None]
    drift = 1.0 + 0.02 * np.linspace(-1, 1, nt)[None, None, :, None] * drifting
    data = noisy(gains * drift * (tsky[None, None] + trxr), rng, bt=1e5)
    data[3, 1, :, :5] = 0.0  # channels that solve to nothing
    flags = np.zeros(data.shape, bool)
    flags[5, 0, 4:, 7] = True  # four samples: the fit solves, one more order does not
    model = FitModel.for_lsts(lsts)
    blocks = accumulate_blocks(
        model, data, tsky, lsts, block_edges(nt, 8), flags=flags, bandwidth_time=1e5
    )
    prior = None
    if prior_kind == "per antenna":
        prior = PriorTerm(trxr[:, :, 0], np.full((nant, npol, NF), 20.0), "inflate")
    elif prior_kind == "shared":
        prior = PriorTerm(np.full((1, npol, NF), 200.0), np.full(NF, 30.0), "inflate")
    sums = blocks.fitted_total()
    solved = solve_sums(
        sums if prior is None else prior(sums, *tu.mean_vectors(model, lsts)),
        scale_covariance="inflate",
    )
    done: list[tuple[int, int]] = []
    part = tu._total_part
    monkeypatch.setattr(tu, "_total_part", lambda *a: done.append(a[-2:]) or part(*a))
    monkeypatch.setattr(tu, "PART_SYSTEMS", 1 << 30)
    whole = tu.total_uncertainty(blocks, solved, prior=prior, threads=1)
    assert done == [(0, nant)]
    for antennas, threads, want in (
        (1, 1, [(0, 4), (4, 8), (8, 12), (12, 13)]),  # parts start at multiples of 4
        (5, 2, [(0, 8), (8, 13)]),
        (1, 8, [(0, nant)]),  # four parts for eight threads: one part
    ):
        monkeypatch.setattr(tu, "PART_SYSTEMS", antennas * npol * NF)
        done.clear()
        parts = tu.total_uncertainty(blocks, solved, prior=prior, threads=threads)
        assert sorted(done) == want
        for name in tu._PER_CHANNEL:
            np.testing.assert_array_equal(getattr(parts, name), getattr(whole, name), name)
        np.testing.assert_array_equal(parts.profile_trxr, whole.profile_trxr)
        assert parts.notes == whole.notes and parts.nblocks == whole.nblocks
    if prior is not None:  # a prior that cannot be cut by antenna: one part
        done.clear()
        plain = tu.total_uncertainty(blocks, solved, prior=lambda *a: prior(*a), threads=1)
        assert done == [(0, nant)]
        np.testing.assert_array_equal(plain.cov, whole.cov)
    assert any("could not take one more time order" in n for n in whole.notes)
    assert np.isfinite(whole.cov).any() and np.isnan(whole.cov[3, 1, :5]).all()
