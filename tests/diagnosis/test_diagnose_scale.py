"""The diagnosis at scale: antennas streamed in chunks, candidates screened by their score."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import autocal.diagnosis.search as dg
from autocal.core.coords import night_epoch
from autocal.core.observation import Observation
from autocal.diagnosis.effects import SkyTemplates, catalogue, sky_templates
from autocal.simulate.mock import SimulationConfig, gain_profile, mock_autos, simulate

SKY = "powerlaw:gsm2008@408:-2.55"
BT = 1e6


@pytest.fixture(scope="module")
def several() -> tuple[Observation, SkyTemplates]:
    """Four antennas, two of them with RFI-like flags, a gain drift and a sky-index error."""
    cfg = SimulationConfig(
        sky=SKY, beam="dipole", channel_width_khz=2000, cadence_s=1200, nside=16, noise_dnu_hz=BT
    )
    obs, _ = simulate(cfg)
    tpl = sky_templates(
        SKY,
        "dipole",
        "hera",
        obs.freqs,
        obs.lsts,
        nside=16,
        epoch=night_epoch(obs.jds, obs.site.lon_deg),
    )
    rng = np.random.default_rng(4)
    tsky = tpl.total + tpl.galactic * ((obs.freqs / tpl.nu0) ** 0.05 - 1)
    gain = gain_profile("a", obs.lsts)
    data = np.concatenate(
        [
            mock_autos(tsky, gain * (1 + 0.1 * i), 150.0 + 10 * i, bandwidth_time=BT, rng=rng)
            for i in range(4)
        ]
    )
    flags = np.zeros(data.shape, bool)
    flags[1, 0, :, 3] = True  # a whole channel
    flags[2, 0, 5:9, :] = True  # a few integrations
    data[2, 0, 6, 7] = np.nan  # a non-finite sample, flagged
    four = dataclasses.replace(
        obs, data=data, flags=flags, antennas=np.arange(4), antenna_names=(), nsamples=None
    )
    return four, tpl


@pytest.mark.parametrize("prior", [None, 150.0])
def test_chunked_fit_equals_the_unchunked_fit(several, prior) -> None:
    """One antenna per chunk gives the fit of all antennas at once."""
    obs, tpl = several
    effects = {(e.name, e.basis, e.order): e for e in catalogue(ntime=obs.ntime)}
    chosen = [
        effects["gain_drift", "legendre", 1],
        effects["noise_drift", "legendre", 2],
        effects["beam_width", "legendre", 0],
    ]
    if prior is not None:  # identifiable only with a receiver prior
        chosen.append(effects["sky_spectral_index", "legendre", 0])
    w = dg.radiometer_weights(obs, obs.data)
    kw = {"weights": w, "trxr_prior": prior, "trxr_prior_sigma": 0.1}
    whole = dg.fit_extended(obs, tpl, chosen, chunk_antennas=obs.nant, **kw)
    single = dg.fit_extended(obs, tpl, chosen, chunk_antennas=1, **kw)
    assert len(dg.antenna_chunks(obs.shape, 1)) == obs.nant
    assert single.chi2 == pytest.approx(whole.chi2, rel=1e-12)
    assert single.ndata == whole.ndata and single.nparam == whole.nparam
    np.testing.assert_allclose(single.G, whole.G, rtol=1e-11)
    np.testing.assert_allclose(single.n, whole.n, rtol=1e-11)
    np.testing.assert_allclose(single.sigma_G, whole.sigma_G, rtol=1e-11)
    for name, value in whole.params.items():
        np.testing.assert_allclose(
            single.params[name], value, rtol=0, atol=1e-9 * whole.sigmas[name].max()
        )
        np.testing.assert_allclose(single.sigmas[name], whole.sigmas[name], rtol=1e-9)
    assert single.identifiable == pytest.approx(whole.identifiable, rel=1e-9)
    assert all(np.isfinite(s).all() for s in whole.sigmas.values()), whole.identifiable
    np.testing.assert_allclose(single.residuals, whole.residuals, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(single.model, whole.model, rtol=1e-12)
    assert np.isnan(whole.residuals[2, 0, 6, 7]) and np.all(np.isnan(whole.residuals[1, 0, :, 3]))
    # the residuals are computed from the fit's inputs, on demand, until it is detached
    assert whole.residuals_of(3, 0).shape == (obs.ntime, obs.nfreq)
    with pytest.raises(dg.DiagnoseError, match="detached"):
        _ = whole.detached().residuals


def test_fast_normal_equations_equal_the_reference_sums(several) -> None:
    """The template-by-template contractions give :func:`projected_normal_equations`'s sums
    (itself checked against the dense projected Jacobian in test_diagnose.py)."""
    obs, tpl = several
    effects = {(e.name, e.basis, e.order): e for e in catalogue(ntime=obs.ntime)}
    chosen = (
        effects["gain_jitter", "integration", 1],
        effects["noise_drift", "legendre", 2],
        effects["beam_width", "legendre", 0],
        effects["sky_scale", "legendre", 0],
    )
    w = dg.radiometer_weights(obs, obs.data)
    prob = dg._Problem(obs, tpl, chosen, w, 150.0, 0.1, None, 1)
    rng = np.random.default_rng(2)
    p = rng.normal(scale=1e-3, size=prob.nfree)
    st = prob.evaluate(p)
    h, grad, raw = prob.normal_equations(p, st)
    # the reference: the factorised Jacobian J = X Y in the (A, P, F, T) layout
    tt = np.swapaxes(st.tt, 1, 2)[None]
    g, nn = st.g[..., None], st.nn[..., None]
    factors = []
    for eff, sl in prob.blocks:
        if eff.kind == "tsky":
            factors.append((sl, g * st.gfac, np.swapaxes(eff.jacobian(p[sl], tpl), 1, 2)))
        else:
            x = g * tt + nn * st.nfac if eff.kind == "gain" else nn * st.gfac
            factors.append((sl, x, prob.bases[eff.basis, eff.order].T[None, None]))
    wt = np.swapaxes(np.stack([prob.chunk_arrays(slice(a, a + 1))[0][0] for a in range(4)]), 2, 3)
    yt = np.swapaxes(np.where(np.isfinite(obs.data), obs.data, 0.0), 2, 3)
    a1 = np.broadcast_to(np.swapaxes(st.a1, 1, 2)[None], wt.shape)
    a2 = np.broadcast_to(st.a2, wt.shape)
    r = np.where(wt > 0, yt - (st.g[..., None] * a1 + st.nn[..., None] * a2), 0.0)
    q1 = (wt * a1 * r).sum(-1) - prob.wp * prob.t0 * st.rp
    q2 = (wt * a2 * r).sum(-1) + prob.wp * st.rp
    h_ref, grad_ref, raw_ref = dg.projected_normal_equations(
        factors, wt, wt * a1, wt * a2, st.inv, r, q1, q2, prob.nfree
    )
    np.testing.assert_allclose(h, h_ref, rtol=1e-9, atol=1e-9 * np.abs(h_ref).max())
    np.testing.assert_allclose(grad, grad_ref, rtol=1e-7, atol=1e-7 * np.abs(grad_ref).max())
    np.testing.assert_allclose(raw, raw_ref, rtol=1e-12)


def test_score_screening_predicts_the_full_fits(several) -> None:
    """One Gauss-Newton step from the current model predicts each candidate's Delta chi^2:
    within 1 % for the effects in the data, and it ranks the data's effect first."""
    obs, tpl = several
    w = dg.radiometer_weights(obs, obs.data)
    current = dg.fit_extended(obs, tpl, [], weights=w)
    w = dg.radiometer_weights(obs, current)
    current = dg.fit_extended(obs, tpl, [], weights=w)
    cands = [c for c in catalogue(ntime=obs.ntime) if c.kind != "bandpass"]
    scores = dg.screen_candidates(obs, tpl, [], current, cands, weights=w)
    full = {}
    for cand, score in zip(cands, scores, strict=True):
        fit = dg.fit_extended(obs, tpl, [cand], weights=w)
        assert score.identifiable == pytest.approx(fit.identifiable[cand.name], rel=1e-9)
        if score.identifiable >= dg.MIN_IDENTIFIABLE:
            full[cand.name, cand.basis, cand.order] = (score.delta_chi2, current.chi2 - fit.chi2)
    assert full["gain_drift", "legendre", 1][0] == pytest.approx(
        full["gain_drift", "legendre", 1][1], rel=0.01
    )
    assert max(full, key=lambda k: full[k][0])[0] in ("gain_drift", "gain_jitter")


def test_large_path_reaches_the_same_diagnosis(several, monkeypatch) -> None:
    """Screening, warm starts and float32 weights (the path of observations above
    LARGE_SAMPLES) name the same effects as the exact search."""
    obs, tpl = several
    exact = dg.diagnose(obs, tpl, max_steps=2)
    monkeypatch.setattr(dg, "LARGE_SAMPLES", 0)
    assert dg.radiometer_weights(obs, obs.data).dtype == np.float32
    screened = dg.diagnose(obs, tpl, max_steps=2)
    assert screened.effects == exact.effects and exact.effects
    assert [s["name"] for s in screened.steps] == [s["name"] for s in exact.steps]
    assert "screening" in screened.config and "screening" not in exact.config
    first = screened.config["screening"][0]
    assert first["fitted"] and set(first["fitted"]).isdisjoint(first["screened_out"])
    for a, b in zip(screened.steps, exact.steps, strict=True):
        for par, value in b["parameters"].items():
            assert a["parameters"][par]["value"] == pytest.approx(
                value["value"], abs=0.05 * value["sigma"]
            )


def test_running_median_is_scipys_median_filter() -> None:
    """The sorting network of the outlier flagging gives median_filter's values exactly."""
    from scipy.ndimage import median_filter

    rng = np.random.default_rng(5)
    x = rng.normal(size=(2, 2, 30, 40))
    x[..., ::7] = 0.0  # ties
    for axis, window in ((2, 9), (3, 9), (3, 5), (2, 31)):
        size = [1, 1, 1, 1]
        size[axis] = window
        expected = median_filter(x, size=tuple(size), mode="mirror")
        np.testing.assert_array_equal(dg._running_median(x, window, axis), expected)
