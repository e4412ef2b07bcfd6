"""The discrepancy workflow finds effects hidden in simulated observations."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.core.coords import night_epoch
from autocal.core.observation import Observation
from autocal.diagnosis.effects import SkyTemplates, sky_templates
from autocal.diagnosis.hidden import (
    HiddenGenerator,
    draw_case,
    draw_effect,
    run_case,
    score,
    suite_cases,
)
from autocal.diagnosis.search import Diagnosis, diagnose, summary_text, write_diagnosis
from autocal.simulate.mock import SimulationConfig, gain_profile, mock_autos, simulate

SKY = "powerlaw:gsm2008@408:-2.55"
BT = 1e6  # dnu dt of the simulated noise (the file's nsamples record it)
PRIOR_SIGMA = 0.1  # K, receiver prior for the time-constant effects


@pytest.fixture(scope="module")
def setup() -> tuple[Observation, SkyTemplates]:
    cfg = SimulationConfig(
        sky=SKY,
        beam="dipole",
        channel_width_khz=1000,
        cadence_s=600,
        nside=32,
        noise_dnu_hz=BT,
    )
    obs, truth = simulate(cfg)
    tpl = sky_templates(
        SKY,
        "dipole",
        "hera",
        obs.freqs,
        obs.lsts,
        nside=32,
        epoch=night_epoch(obs.jds, obs.site.lon_deg),
    )
    np.testing.assert_allclose(tpl.total, truth.tsky, rtol=1e-10)
    return obs, tpl


def hidden(
    obs: Observation, tsky: np.ndarray, gain: np.ndarray | None = None, trxr=150.0, seed=1
) -> Observation:
    """Mock data from a modified truth (someone else's hidden effect)."""
    g = np.ones(obs.ntime) if gain is None else gain
    data = mock_autos(tsky, g, trxr, bandwidth_time=BT, rng=np.random.default_rng(seed))
    return dataclasses.replace(obs, data=data)


def s_of(lsts: np.ndarray) -> np.ndarray:
    return 2 * (lsts - lsts.min()) / (lsts.max() - lsts.min()) - 1


def check(diag: Diagnosis, name: str, truth: dict[str, float]) -> None:
    # named, or detected but negligible for the products (then kept in the fit, not named)
    found = [st["name"] for st in diag.steps if "dropped_in_backward_pass" not in st]
    assert found, "nothing found"
    assert found[0] == name, found
    assert set(found) == set(diag.effects) | set(diag.negligible)
    step = diag.steps[0]
    for par, value in truth.items():
        got = step["parameters"][par]
        assert abs(got["value"] - value) < 3 * got["sigma"] + 1e-12, (par, got, value)
    for st in diag.steps:
        if st["name"] != "cable_reflection":
            assert st["gap_after"]["reduced_chi2"] < st["gap_before"]["reduced_chi2"]
        else:
            assert (
                st["gap_after"]["bandpass_reduced_chi2"] < st["gap_before"]["bandpass_reduced_chi2"]
            )
    assert diag.final_gap["reduced_chi2"] < 1.1


@pytest.mark.parametrize("prior", [None, 150.0])
def test_clean_names_nothing(setup, prior):
    obs, tpl = setup
    diag = diagnose(hidden(obs, tpl.total), tpl, trxr_prior=prior, trxr_prior_sigma=PRIOR_SIGMA)
    assert diag.effects == []
    assert diag.final_gap["reduced_chi2"] < 1.1
    if prior is None:  # time-constant / pure-scale Tsky effects are absorbed by (G, n)
        for name in ("sky_offset", "ground_temperature", "missing_cmb", "sky_scale"):
            assert diag.identifiability[name] < 1e-6
        assert diag.identifiability["beam_width"] > 1e-3


def test_gain_drift(setup):
    obs, tpl = setup
    g = gain_profile("a", obs.lsts)
    # expected relative drift: least-squares projection of the true profile on 1 + d P_1
    s = s_of(obs.lsts)
    c0, c1 = np.polynomial.legendre.legfit(s, g, 1)
    diag = diagnose(hidden(obs, tpl.total, gain=g), tpl)
    check(diag, "gain_drift", {"d_1": c1 / c0})
    assert diag.effects == ["gain_drift"]
    # what the effect does to the calibration products: a constant fit of this drift is
    # biased by ~10 % in G (tests/simulate/test_paper.py); the diagnosed model removes that bias
    impact = diag.steps[0]["product_impact"]
    for key, value in impact["G"].items():  # one step: the same change (after re-weighting)
        assert diag.product_change["G"][key] == pytest.approx(value, rel=1e-3)
    assert abs(impact["G"]["median_relative_change"]) > 0.05
    assert impact["G"]["channels"] == obs.nfreq
    assert impact["G"]["max_change_over_sigma"] >= impact["G"]["median_change_over_sigma"] > 0
    assert "calibration products" in summary_text(diag)


def test_noise_drift(setup):
    obs, tpl = setup
    trxr = (150 * (1 + 0.03 * s_of(obs.lsts)))[:, None] * np.ones(obs.nfreq)
    diag = diagnose(hidden(obs, tpl.total, trxr=trxr), tpl)
    check(diag, "noise_drift", {"e_1": 0.03})


def test_cable_reflection(setup):
    obs, tpl = setup
    f = obs.freqs
    g = np.broadcast_to(1 + 5e-3 * np.cos(2 * np.pi * f * 250e-9 + 0.3), (obs.ntime, f.size))
    diag = diagnose(hidden(obs, tpl.total, gain=g), tpl)
    check(diag, "cable_reflection", {"a": 5e-3, "tau_ns": 250.0, "phi": 0.3})


def test_ground_temperature(setup):
    obs, tpl = setup
    truth = tpl.total - 50.0 * tpl.f_below[:, None, :]  # 250 K ground, model 300 K
    diag = diagnose(hidden(obs, truth), tpl, trxr_prior=150.0, trxr_prior_sigma=PRIOR_SIGMA)
    check(diag, "ground_temperature", {"dT_gnd": -50.0})


def test_missing_cmb(setup):
    obs, tpl = setup
    diag = diagnose(
        hidden(obs, tpl.total - tpl.cmb), tpl, trxr_prior=150.0, trxr_prior_sigma=PRIOR_SIGMA
    )
    check(diag, "missing_cmb", {"cmb_factor": -1.0})
    assert diag.steps[0]["parameters"]["cmb_factor"]["adopted"] == -1.0


def test_sky_spectral_index(setup):
    obs, tpl = setup
    truth = tpl.total + tpl.galactic * ((obs.freqs / tpl.nu0) ** 0.1 - 1)
    diag = diagnose(hidden(obs, truth), tpl, trxr_prior=150.0, trxr_prior_sigma=PRIOR_SIGMA)
    check(diag, "sky_spectral_index", {"dbeta": 0.1})


def test_write_diagnosis(setup, tmp_path: Path):
    obs, tpl = setup
    diag = diagnose(
        hidden(obs, tpl.total - tpl.cmb), tpl, trxr_prior=150.0, trxr_prior_sigma=PRIOR_SIGMA
    )
    out = write_diagnosis(diag, tmp_path / "diag", obs)
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["effects"] == ["missing_cmb"]
    step = doc["steps"][0]
    assert {"name", "parameters", "statistic", "delta", "gap_before", "gap_after"} <= set(step)
    assert (out / "residuals_step1.png").stat().st_size > 1000
    assert "missing_cmb" in (out / "summary.txt").read_text()


def test_rfi_is_flagged_not_named(setup):
    """Narrow-band and impulsive RFI is flagged; it neither breaks the fit nor is named."""
    obs, tpl = setup
    data = hidden(obs, tpl.total, seed=7)
    spiky = data.data.copy()
    rng = np.random.default_rng(3)
    spiky[..., 20] *= 3.0  # a channel of persistent RFI
    t, f = rng.integers(0, obs.ntime, 40), rng.integers(0, obs.nfreq, 40)
    spiky[0, 0, t, f] *= rng.uniform(1.5, 10, 40)  # impulsive RFI
    diag = diagnose(dataclasses.replace(data, data=spiky), tpl)
    assert diag.effects == []
    flagged = diag.config["outlier_flagging"]
    assert flagged["samples_flagged"] >= 40
    assert diag.final_gap["reduced_chi2"] < 1.1
    unflagged = diagnose(dataclasses.replace(data, data=spiky), tpl, flag_rfi=False)
    assert unflagged.initial_gap["reduced_chi2"] > 10 * diag.initial_gap["reduced_chi2"]


def test_hidden_case_round_trip(tmp_path: Path):
    """The generator writes UVH5 with a truth file; the score rejects a wrong answer."""
    cfg = SimulationConfig(
        sky=SKY, beam="dipole", channel_width_khz=1000, cadence_s=1800, nside=16, noise_dnu_hz=BT
    )
    gen = HiddenGenerator(cfg)
    case = draw_case(("cable_reflection",), seed=5)
    row = run_case(gen, case, tmp_path)
    truth = json.loads((tmp_path / "hidden_5.uvh5.truth.json").read_text())
    assert truth["effects"][0]["name"] == "cable_reflection"
    assert row["score"]["ok"], row
    wrong = dataclasses.replace(
        case, effects=(draw_effect("gain_drift", np.random.default_rng(1)),)
    )
    diag = diagnose(gen.observation(case), gen.templates, trxr_prior=150.0)
    assert not score(gen, wrong, diag).ok


@pytest.mark.slow
def test_hidden_suite(tmp_path: Path):
    """The fixed-seed 42-case suite (the README's identification rate)."""
    cfg = SimulationConfig(
        sky=SKY, beam="dipole", channel_width_khz=1000, cadence_s=600, nside=32, noise_dnu_hz=BT
    )
    gen = HiddenGenerator(cfg)
    rows = [run_case(gen, case, tmp_path) for case in suite_cases(42)]
    clean = [r for r in rows if not r["case"]["effects"]]
    assert len(clean) >= 4
    assert all(not r["score"]["found"] for r in clean), "an effect was named on clean data"
    assert all(r["score"]["gap_shrinks"] for r in rows)
    assert sum(r["score"]["ok"] for r in rows) / len(rows) >= 0.9


@pytest.mark.parametrize("with_prior", [False, True])
def test_projected_normal_equations_equal_the_dense_projected_jacobian(with_prior):
    """The factorised sums give what the projected (samples x K) Jacobian gives."""
    from autocal.diagnosis.search import projected_normal_equations

    rng = np.random.default_rng(7)
    na, npol, nf, nt = 3, 2, 5, 7
    shape = (na, npol, nf, nt)
    w = rng.uniform(0.5, 2.0, shape) * (rng.uniform(size=shape) > 0.1)
    a1, a2 = rng.normal(size=shape) + 3.0, rng.normal(size=shape) + 1.0
    r = rng.normal(size=shape)
    wp = rng.uniform(0.1, 1.0, shape[:3]) if with_prior else np.zeros(shape[:3])
    t0 = rng.uniform(50.0, 150.0, nf) * with_prior
    rp = rng.normal(size=shape[:3]) * with_prior
    n11 = (w * a1 * a1).sum(-1) + wp * t0**2
    n12 = (w * a1 * a2).sum(-1) - wp * t0
    n22 = (w * a2 * a2).sum(-1) + wp
    det = n11 * n22 - n12**2
    inv = np.stack([n22 / det, -n12 / det, n11 / det])
    inv[:, 1, 0, 2] = 0.0  # a channel without a (G, n) solution is not projected
    # a Tsky-like block (shared by antennas, depends on pol and channel), a gain-like and a
    # noise-like block (time bases only)
    blocks = [
        (slice(0, 2), rng.normal(size=shape), rng.normal(size=(npol, nf, nt, 2))),
        (slice(2, 5), rng.normal(size=shape), rng.normal(size=(1, 1, nt, 3))),
        (slice(5, 6), rng.normal(size=shape), rng.normal(size=(1, 1, nt, 1))),
    ]
    nfree = 6
    jac = np.concatenate(
        [x[..., None] * np.broadcast_to(y, (*shape, y.shape[-1])) for _, x, y in blocks], -1
    )
    c1 = np.einsum("apft,apftk->apfk", w * a1, jac)
    c2 = np.einsum("apft,apftk->apfk", w * a2, jac)
    k1 = inv[0][..., None] * c1 + inv[1][..., None] * c2
    k2 = inv[1][..., None] * c1 + inv[2][..., None] * c2
    jp = jac - a1[..., None] * k1[..., None, :] - a2[..., None] * k2[..., None, :]
    jprior = t0[:, None] * k1 - k2
    h_dense = np.einsum("apft,apftk,apftl->kl", w, jp, jp) + np.einsum(
        "apf,apfk,apfl->kl", wp, jprior, jprior
    )
    grad_dense = np.einsum("apft,apftk,apft->k", w, jp, r) + np.einsum(
        "apf,apfk,apf->k", wp, jprior, rp
    )
    q1 = (w * a1 * r).sum(-1) - wp * t0 * rp
    q2 = (w * a2 * r).sum(-1) + wp * rp
    h, grad, raw = projected_normal_equations(blocks, w, w * a1, w * a2, inv, r, q1, q2, nfree)
    np.testing.assert_allclose(h, h_dense, rtol=1e-10, atol=1e-10 * np.abs(h_dense).max())
    np.testing.assert_allclose(grad, grad_dense, rtol=1e-10, atol=1e-10 * np.abs(grad_dense).max())
    np.testing.assert_allclose(raw, np.einsum("apft,apftk->k", w, jac**2), rtol=1e-12)


def test_beam_width_templates_come_from_the_tsky_cache(tmp_cache, monkeypatch) -> None:
    """The four widened beams of the beam_width template are cached Tsky harmonics: a
    second diagnosis of the night computes none of them again (same templates)."""
    import autocal.tsky.compute
    from autocal.core.sites import HERA
    from autocal.diagnosis.effects import sky_templates

    freqs = np.linspace(120e6, 180e6, 4)
    lsts = np.linspace(0.0, 23.0, 24)
    kw = {"pols": ("ee",), "nside": 16, "epoch": 2458116.0}
    first = sky_templates("uniform:300", "dipole", HERA, freqs, lsts, **kw)
    assert len(list(tmp_cache.rglob("*.h5"))) >= 4
    real = autocal.tsky.ringfft.tsky_harmonics

    def no_widened_beams(sky, beam, *args, **kwargs):
        assert "scaled" not in str(beam.describe()), "a widened beam was computed again"
        return real(sky, beam, *args, **kwargs)

    monkeypatch.setattr(autocal.tsky.compute, "tsky_harmonics", no_widened_beams)
    second = sky_templates("uniform:300", "dipole", HERA, freqs, lsts, **kw)
    np.testing.assert_allclose(second.beam_width_poly, first.beam_width_poly, rtol=1e-12)


def test_timing_offset(setup):
    """Data whose clock runs 90 s ahead (the sky seen at LST + 90 s): named timing_offset,
    its dt recovered; computed from Tsky at shifted LSTs, not from the template."""
    from autocal.tsky.compute import compute_tsky

    obs, tpl = setup
    dt = 90.0
    shift = dt * 1.002737909 / 3600.0  # hours of LST
    truth = compute_tsky(
        SKY,
        "dipole",
        "hera",
        obs.freqs,
        (obs.lsts + shift) % 24,
        nside=32,
        epoch=night_epoch(obs.jds, obs.site.lon_deg),
        pol="ee",
    ).tsky[None]
    diag = diagnose(hidden(obs, truth), tpl)
    # over 24 h a 90 s offset hardly moves G and Trxr, but it dominates the residual
    # (its Delta chi^2 is more than a tenth of the data count): named, not "negligible"
    assert diag.effects == ["timing_offset"] and diag.negligible == []
    step = diag.steps[0]
    assert step["name"] == "timing_offset" and not step["negligible"]
    assert abs(step["parameters"]["dt_s"]["value"] - dt) < 3 * step["parameters"]["dt_s"]["sigma"]
    assert step["product_impact"]["G"]["median_change_over_sigma"] < 0.1
    assert step["delta"] > 0.1 * diag.final_fit.ndata


def test_unexplained_remainder_is_described_not_named(setup):
    """A gap left after the search is reported with its structure; a fit within the noise
    is not."""
    from types import SimpleNamespace

    from autocal.diagnosis.search import describe_unexplained

    obs, _ = setup
    rng = np.random.default_rng(3)
    shape = (1, 1, obs.ntime, obs.nfreq)
    white = rng.standard_normal(shape)
    dof = white.size - 2 * obs.nfreq
    base = {
        "chi2": float((white**2).sum()),
        "dof": dof,
        "reduced_chi2": float((white**2).sum() / dof),
        "time_mode_power": [1.0, 1.1, 0.9, 1.0],
        "integration_jitter": 1.0,
        "residual_delay_power": {"max": 1.5, "delay_ns": 300.0},
    }
    assert describe_unexplained(SimpleNamespace(residuals=white), obs, base) is None
    smooth = white + 0.5 * np.linspace(-1, 1, obs.ntime)[None, None, :, None]
    gap = {
        **base,
        "chi2": float((smooth**2).sum()),
        "reduced_chi2": float((smooth**2).sum() / dof),
        "time_mode_power": [1.0, 40.0, 2.0, 1.0],
    }
    out = describe_unexplained(SimpleNamespace(residuals=smooth), obs, gap)
    assert out is not None and out["time"] == "smooth in time"
    assert out["excess_sigma"] > 5 and "unexplained" in out["message"]
    assert out["antennas"][0]["antenna"] == int(obs.antennas[0])
    jumpy = {**gap, "time_mode_power": [1.0, 1.2, 1.1, 1.0], "integration_jitter": 6.0}
    out = describe_unexplained(SimpleNamespace(residuals=smooth), obs, jumpy)
    assert out is not None and out["time"].startswith("integration to integration")


def test_negligible_needs_a_verdict_on_most_channels() -> None:
    from autocal.diagnosis.search import is_negligible

    tiny = {
        "channels": 161,
        "of": 161,
        "median_change_over_sigma": 0.01,
        "max_change_over_sigma": 0.05,
    }
    impact = {
        "G": {**tiny, "median_relative_change": 1e-5, "median_abs_relative_change": 1e-5},
        "Trxr": {**tiny, "median_change_K": 0.01, "median_abs_change_K": 0.01},
    }
    impact["G"]["max_abs_relative_change"] = 2e-5
    impact["Trxr"]["max_abs_change_K"] = 0.02
    assert is_negligible(impact)
    # the yardstick calibration failed in 158 of 161 channels: no verdict, not negligible
    few = {name: {**entry, "channels": 3} for name, entry in impact.items()}
    assert not is_negligible(few)
    # tiny in absolute terms (below the sky model's accuracy) though many sigma
    precise = {
        "G": {**impact["G"], "median_change_over_sigma": 0.6, "median_abs_relative_change": 2e-4},
        "Trxr": {**impact["Trxr"], "median_change_over_sigma": 0.5, "median_abs_change_K": 0.2},
    }
    assert is_negligible(precise)
    big = {**precise, "G": {**precise["G"], "median_abs_relative_change": 0.02}}
    assert not is_negligible(big)
    # a change alternating in sign: its signed median is ~0, its absolute one is not
    alternating = {**precise, "G": {**precise["G"], "median_relative_change": 0.0}}
    alternating["G"]["median_abs_relative_change"] = 0.05
    assert not is_negligible(alternating)
    # below the sky model's accuracy it does not matter how many sigma the change is ...
    sharp = {**precise, "Trxr": {**precise["Trxr"], "max_change_over_sigma": 1.5}}
    assert is_negligible(sharp)
    # ... unless a channel moves by ten times that accuracy
    spike = {**sharp, "Trxr": {**sharp["Trxr"], "max_abs_change_K": 12.0}}
    assert not is_negligible(spike)
    # the products' variation in time must stay put as well: a 1 % rms jitter is not
    # negligible to whoever applies the gains per integration, however well the time
    # means agree
    jitter = {**impact, "G_time": {"rms_relative_change": 1e-2, "max_abs_relative_change": 3e-2}}
    assert not is_negligible(jitter)
    steady = {**impact, "G_time": {"rms_relative_change": 1e-4, "max_abs_relative_change": 3e-4}}
    assert is_negligible(steady)
    drifting = {**impact, "Trxr_time": {"median_max_abs_change_K": 3.0, "max_abs_change_K": 5.0}}
    assert not is_negligible(drifting)
    # an effect that removes a fifth of the noise variance per sample is never negligible
    assert not is_negligible(steady, chi2_share=0.2) and is_negligible(steady, chi2_share=0.01)


def test_fits_from_another_start_compare(setup):
    """A fit started elsewhere reaches the same minimum with the same chi2: its receiver
    prior's weights come from the model without effects, not from the start."""
    from autocal.diagnosis.effects import catalogue
    from autocal.diagnosis.search import fit_extended, radiometer_weights

    obs, tpl = setup
    g = 1 + 0.02 * s_of(obs.lsts)
    data = hidden(obs, tpl.total, gain=g)
    drift = next(e for e in catalogue() if e.name == "gain_drift" and e.order == 1)
    w = radiometer_weights(data, data.data)
    kw = {"weights": w, "trxr_prior": 150.0, "trxr_prior_sigma": PRIOR_SIGMA}
    zero = fit_extended(data, tpl, [drift], **kw)
    far = fit_extended(data, tpl, [drift], start={"gain_drift": np.array([-0.05])}, **kw)
    assert far.chi2 == pytest.approx(zero.chi2, rel=1e-9)
    np.testing.assert_allclose(far.params["gain_drift"], zero.params["gain_drift"], rtol=1e-5)
    # a start of the wrong length is ignored
    odd = fit_extended(data, tpl, [drift], start={"gain_drift": np.zeros(3)}, **kw)
    assert odd.chi2 == pytest.approx(zero.chi2, rel=1e-12)
    # the gain factor over time is the fitted drift, the noise factor is one
    np.testing.assert_allclose(zero.gain_factor, 1 + zero.params["gain_drift"][0] * s_of(obs.lsts))
    np.testing.assert_array_equal(zero.noise_factor, np.ones(obs.ntime))


def test_band_consistency_tells_a_real_effect_from_an_absorbing_template(setup):
    """A sky spectral index error is the same in both halves of the band; the same
    template made to absorb a beam-shape error (a narrower beam at low frequencies only)
    is not."""
    from autocal.diagnosis.effects import catalogue
    from autocal.diagnosis.search import band_consistency, fit_extended, radiometer_weights

    obs, tpl = setup
    index = next(e for e in catalogue() if e.name == "sky_spectral_index")
    kw = {"trxr_prior": 150.0, "trxr_prior_sigma": PRIOR_SIGMA}
    real = tpl.total + index.delta(np.array([0.1]), tpl)
    data = hidden(obs, real)
    w = radiometer_weights(data, data.data)
    fit = fit_extended(data, tpl, [index], weights=w, **kw)
    check = band_consistency(data, tpl, [], index, fit, w, kw)
    assert check is not None and check["consistent"], check
    lower, upper = check["values"]["lower"][0], check["values"]["upper"][0]
    assert abs(lower - 0.1) < 0.02 and abs(upper - 0.1) < 0.02
    # a chromatic error the index template can only partly follow: the beam-width
    # template's change in the lower half of the band only
    low = (obs.freqs < np.median(obs.freqs)).astype(float)
    other = tpl.total + 0.08 * tpl.beam_dwidth * low[None, None, :]
    data = hidden(obs, other)
    w = radiometer_weights(data, data.data)
    fit = fit_extended(data, tpl, [index], weights=w, **kw)
    check = band_consistency(data, tpl, [], index, fit, w, kw)
    assert check is not None and not check["consistent"], check
    assert check["p_value"] < 1e-3 and check["relative_difference"] > 0.3
    # no verdict for a per-integration series or a fixed hypothesis
    jitter = next(e for e in catalogue(ntime=obs.ntime) if e.basis == "integration")
    assert band_consistency(data, tpl, [], jitter, fit, w, kw) is None


def test_band_consistency_with_a_partner(setup):
    """A noise drift next to a spectral-index error: fitted alone its half-band values are
    pulled apart by the other chromatic error; fitted with it alongside, both agree."""
    from autocal.diagnosis.effects import catalogue
    from autocal.diagnosis.search import band_consistency, fit_extended, radiometer_weights

    obs, tpl = setup
    cat = catalogue()
    index = next(e for e in cat if e.name == "sky_spectral_index")
    drift = next(e for e in cat if e.name == "noise_drift" and e.order == 1)
    truth = tpl.total + index.delta(np.array([-0.1]), tpl)
    trxr = (150 * (1 + 0.02 * s_of(obs.lsts)))[:, None] * np.ones(obs.nfreq)
    data = hidden(obs, truth, trxr=trxr)
    w = radiometer_weights(data, data.data)
    kw = {"trxr_prior": 150.0, "trxr_prior_sigma": PRIOR_SIGMA}
    alone = fit_extended(data, tpl, [drift], weights=w, **kw)
    check = band_consistency(data, tpl, [], drift, alone, w, kw)
    joint = fit_extended(data, tpl, [drift, index], weights=w, **kw)
    both = band_consistency(data, tpl, [], drift, joint, w, kw, partner=index)
    assert both is not None and both["consistent"] and both["partner"] == "sky_spectral_index"
    assert abs(joint.params["noise_drift"][0] - 0.02) < 5 * joint.sigmas["noise_drift"][0]
    # alone: both halves biased (0.046 and 0.034 against 0.02), and significantly apart
    assert check is not None and check["p_value"] < 1e-3 and both["p_value"] > 1e-3
    assert check["relative_difference"] > 5 * both["relative_difference"]


def test_robust_overdispersion_ignores_a_few_outliers() -> None:
    """The bulk's scatter: 1 for unit normal residuals with 1 % huge outliers, which
    multiply chi2/dof by ~100."""
    from types import SimpleNamespace

    from autocal.diagnosis.search import robust_overdispersion

    rng = np.random.default_rng(5)
    res = rng.standard_normal((1, 2, 200, 100))
    res.flat[::100] = 100.0
    res[0, 0, 0, 0] = np.nan
    fit = SimpleNamespace(residuals=res, reduced_chi2=float(np.nanmean(res**2)))
    assert fit.reduced_chi2 > 50
    assert robust_overdispersion(fit) == pytest.approx(1.0, abs=0.05)


def test_feed_gains_with_a_dead_antenna(setup):
    """Every antenna-pol its own drift: an antenna-pol without data follows the shared
    series and adds no parameter; one whose own parameters have no data is an error the
    search records, not a silent None."""
    from autocal.diagnosis.effects import catalogue
    from autocal.diagnosis.search import (
        DiagnoseError,
        fit_extended,
        fit_feed_gains,
        radiometer_weights,
    )

    obs, tpl = setup
    drift = next(e for e in catalogue(nfeeds=2) if e.name == "antenna_gain_drift" and e.order == 1)
    jitter = next(e for e in catalogue(ntime=obs.ntime) if e.basis == "integration")
    two = hidden(obs, tpl.total)
    two = dataclasses.replace(
        two,
        antennas=np.array([0, 1]),
        antenna_names=("ant0", "ant1"),
        data=np.concatenate([two.data, two.data * (1 + 0.01 * s_of(obs.lsts))[:, None]]),
        flags=np.concatenate([two.flags, two.flags]),
        nsamples=np.concatenate([two.nsamples, two.nsamples]),
    )
    w = radiometer_weights(two, two.data)
    current = fit_extended(two, tpl, [], weights=w)
    feed = fit_feed_gains(two, tpl, [], current, w, {}, drift)
    assert feed is not None and feed.k == 2
    assert abs(feed.values[1, 0, 0] - 0.01) < 1e-3 and abs(feed.values[0, 0, 0]) < 1e-3
    dead = dataclasses.replace(two, flags=two.flags.copy())
    dead.flags[1] = True
    feed = fit_feed_gains(dead, tpl, [], current, w, {}, drift)
    assert feed is not None and feed.k == 1
    np.testing.assert_array_equal(feed.factors[1], 1.0)
    # an integration flagged for one antenna-pol only: its own jitter factor has no data
    gap = dataclasses.replace(two, flags=two.flags.copy())
    gap.flags[1, 0, 5] = True
    wg = radiometer_weights(gap, gap.data)
    with_jitter = fit_extended(gap, tpl, [jitter], weights=wg)
    own = next(e for e in catalogue(ntime=obs.ntime, nfeeds=2) if e.name == "antenna_gain_jitter")
    with pytest.raises(DiagnoseError, match="no data"):
        fit_feed_gains(gap, tpl, [jitter], with_jitter, wg, {}, own)


def test_summary_marks_superseded_and_dropped_steps() -> None:
    """summary.txt says which steps a later one superseded or the re-test dropped."""
    from autocal.diagnosis.search import Diagnosis

    gap = {"reduced_chi2": 2.0, "rms_normalised_residual": 1.4}
    step = {
        "parameters": {"rms": {"value": 0.004, "sigma": 1e-4}},
        "statistic": 50.0,
        "delta": 80.0,
        "gap_before": gap,
        "gap_after": gap,
    }
    diag = Diagnosis(config={}, initial_gap=gap, final_gap=gap)
    diag.steps = [
        {**step, "name": "gain_jitter", "superseded_by": "antenna_gain_jitter"},
        {**step, "name": "beam_width", "dropped_in_backward_pass": {"at": "step 3"}},
    ]
    text = summary_text(diag)
    assert "gain_jitter [superseded by antenna_gain_jitter]" in text
    assert "beam_width [dropped at step 3]" in text
