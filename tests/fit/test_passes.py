"""The in-memory fit and its weighting passes (autocal.fit.passes)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.core.observation import Observation
from autocal.core.sites import HERA
from autocal.fit.model import FitError, FitModel
from autocal.fit.passes import fit
from autocal.fit.solution import Solution
from autocal.fit.sums import accumulate
from tests.fit.toy import FREQS, LSTS, NF, NT, make_obs, noisy, toy_tsky


def test_noiseless_constant_and_legendre_recover_truth() -> None:
    tsky = toy_tsky()
    s = FitModel.for_lsts(LSTS, "legendre", 2).s(LSTS)
    gain = (1.2 + 0.05 * s - 0.02 * (1.5 * s**2 - 0.5))[:, None] * np.ones(NF)
    trxr = 100.0 + 0.3 * (FREQS / 1e6 - 150.0)
    data = (gain * (tsky + trxr))[None, None]
    sol2 = fit(make_obs(data), tsky, model="legendre", order=2)
    ev = sol2.evaluate()
    np.testing.assert_allclose(ev["G"][0, 0], gain, rtol=1e-9)
    np.testing.assert_allclose(ev["Trxr"][0, 0], np.broadcast_to(trxr, (NT, NF)), rtol=1e-8)
    const = (1.3 * (tsky + trxr))[None, None]
    sol0 = fit(make_obs(const), tsky)
    np.testing.assert_allclose(sol0.G[0, 0], 1.3, rtol=1e-10)
    np.testing.assert_allclose(sol0.Trxr[0, 0], trxr, rtol=1e-9)
    np.testing.assert_allclose(sol0.abs_g, np.sqrt(1.3), rtol=1e-10)


def test_pulls_are_unit_normal_with_radiometer_weights() -> None:
    """Over many noise draws, (fit - truth) / sigma_stat has standard deviation 1 +- 0.1,
    and with the total errors (jackknife, drift model) 1 +- 0.35 on these clean data."""
    rng = np.random.default_rng(42)
    tsky = toy_tsky()
    clean = (tsky + 150.0)[None, None]
    stat: dict[str, list[np.ndarray]] = {"G": [], "n": [], "Trxr": []}
    total: dict[str, list[np.ndarray]] = {"G": [], "n": [], "Trxr": []}
    truth = {"G": 1.0, "n": 150.0, "Trxr": 150.0}
    for _ in range(60):
        sol = fit(make_obs(noisy(clean, rng)), tsky)
        assert sol.total is not None
        for name, value in truth.items():
            stat[name].append((getattr(sol, name) - value) / getattr(sol, f"sigma_{name}_stat"))
            total[name].append((getattr(sol, name) - value) / getattr(sol, f"sigma_{name}"))
    for name in truth:
        arr, tot = np.ravel(stat[name]), np.ravel(total[name])
        assert abs(np.std(arr) - 1.0) < 0.1, name
        assert abs(np.mean(arr)) < 0.1, name
        assert abs(np.std(tot) - 1.0) < 0.35, name
        assert np.all(np.abs(tot) <= np.abs(arr) + 1e-12), name  # the total never shrinks


def test_model_weights_remove_the_data_weight_bias() -> None:
    """Weights from the data bias G low by ~2/(dnu dt); the second pass removes it."""
    rng = np.random.default_rng(7)
    bt = 200.0  # strong noise makes the effect visible: expected bias -2/bt = -1 %
    tsky = toy_tsky(400)
    clean = (tsky + 150.0)[None, None]
    data = noisy(clean, rng, bt)
    one = fit(make_obs(data, bt=bt), tsky, passes=1)
    two = fit(make_obs(data, bt=bt), tsky, passes=2)
    sem = np.median(two.sigma_G) / np.sqrt(400)
    assert np.mean(one.G) - 1 < -5 * sem
    assert abs(np.mean(two.G) - 1) < 3 * sem


def test_flags_and_failures_are_reported_not_filled() -> None:
    tsky = toy_tsky()
    data = (1.0 * (tsky + 150.0))[None, None].copy()
    flags = np.zeros(data.shape, bool)
    flags[..., :10, 0] = True  # partly flagged channel
    flags[..., :, 1] = True  # fully flagged channel
    data[..., 5, 2] = np.nan  # one non-finite sample
    tsky_bad = tsky.copy()
    tsky_bad[:, 3] = 500.0  # constant sky: G and n are degenerate
    data[..., 3] = 1.0 * (500.0 + 150.0)
    data[..., 4] = -1.0 * (tsky[:, 4] + 150.0)  # negative gain
    sol = fit(make_obs(data, flags), tsky_bad, weights="identity")
    assert sol.flag_reason[0, 0, 1] == 1
    assert sol.flag_reason[0, 0, 3] == 2
    assert sol.flag_reason[0, 0, 4] == 3
    assert sol.flag_reason[0, 0, 0] == 0 and sol.flag_reason[0, 0, 2] == 0
    assert sol.count[0, 0, 0] == NT - 10 and sol.nflagged[0, 0, 0] == 10
    assert sol.nflagged[0, 0, 2] == 1
    for code in (1, 2, 3):
        j = int(np.flatnonzero(sol.flag_reason[0, 0] == code)[0])
        assert np.isnan(sol.G[0, 0, j]) and np.isnan(sol.Trxr[0, 0, j])
    assert np.all(np.isfinite(sol.G[0, 0, 5:]))


def test_identity_weights_scale_covariance_to_residual_variance() -> None:
    rng = np.random.default_rng(11)
    tsky = toy_tsky()
    clean = (tsky + 150.0)[None, None]
    pulls = []
    for _ in range(40):
        data = clean + rng.normal(0.0, 3.0, clean.shape)  # homoscedastic noise
        sol = fit(make_obs(data), tsky, weights="identity")
        pulls.append((sol.G - 1.0) / sol.sigma_G_stat)
        np.testing.assert_allclose(np.median(sol.reduced_chi2), 9.0, rtol=0.15)
    assert abs(np.std(pulls) - 1.0) < 0.1


def test_user_weights_match_radiometer_weights() -> None:
    rng = np.random.default_rng(5)
    tsky = toy_tsky()
    data = noisy((tsky + 150.0)[None, None], rng)
    obs = make_obs(data)
    radio = fit(obs, tsky, passes=1)
    user = fit(obs, tsky, weights=5e3 / data**2)
    np.testing.assert_allclose(user.coeffs, radio.coeffs, rtol=1e-12)
    np.testing.assert_allclose(user.cov, radio.cov, rtol=1e-12)


def test_residuals_are_normalised() -> None:
    rng = np.random.default_rng(2)
    tsky = toy_tsky()
    obs = make_obs(noisy((tsky + 150.0)[None, None], rng))
    sol = fit(obs, tsky, return_residuals=True)
    assert sol.residuals is not None and sol.residuals.shape == obs.shape
    assert abs(np.nanstd(sol.residuals) - 1.0) < 0.05
    pred = sol.predict(tsky)
    assert pred.shape == obs.shape


def test_bad_inputs_are_refused_with_a_reason() -> None:
    tsky = toy_tsky()
    obs = make_obs((tsky + 150.0)[None, None])
    with pytest.raises(FitError, match="Tsky has shape"):
        fit(obs, tsky[:, :5])
    with pytest.raises(FitError, match="non-finite"):
        fit(obs, np.full_like(tsky, np.nan))
    with pytest.raises(FitError, match="unknown weights"):
        fit(obs, tsky, weights="bogus")
    with pytest.raises(FitError, match="unknown model"):
        FitModel("quadratic")
    with pytest.raises(FitError, match="more than one LST"):
        FitModel.for_lsts(np.array([3.0]), "legendre", 1)
    no_width = Observation(
        data=obs.data,
        freqs=obs.freqs,
        lsts=obs.lsts,
        jds=obs.jds,
        antennas=obs.antennas,
        pols=obs.pols,
        site=HERA,
    )
    with pytest.raises(FitError, match="identity"):
        fit(no_width, tsky)
    for empty in ((1, 1, 0, NF), (0, 1, 4, NF), (1, 1, 4, 0)):
        with pytest.raises(FitError, match="nothing to fit"):
            accumulate(
                FitModel(),
                np.ones(empty),
                np.ones(empty[1:]),
                np.zeros(empty[2]),
                bandwidth_time=np.ones(empty[3]),
            )
    with pytest.raises(FitError, match="shape"):
        Solution(
            model=FitModel(),
            antennas=np.array([0]),
            pols=("ee",),
            freqs=FREQS,
            lsts=LSTS,
            jds=LSTS,
            coeffs=np.zeros((1, 1, NF, 3)),
            cov=np.zeros((1, 1, NF, 2, 2)),
            chi2=np.zeros((1, 1, NF)),
            dof=np.zeros((1, 1, NF)),
            count=np.zeros((1, 1, NF)),
            nflagged=np.zeros((1, 1, NF)),
            flag_reason=np.zeros((1, 1, NF), np.int8),
        )
