"""End to end: :func:`autocal.diagnosis.stepwise.diagnose` finds effects hidden in simulated
observations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from autocal.core.coords import night_epoch
from autocal.diagnosis.impact import FORWARD_MODEL_ACCURACY, forward_model_accuracy
from autocal.diagnosis.report import Diagnosis, summary_text
from autocal.diagnosis.stepwise import diagnose
from autocal.simulate.mock import gain_profile
from autocal.tsky.compute import compute_tsky
from tests.diagnosis.simulated import PRIOR_SIGMA, SKY, hidden, s_of


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
    # the floor of "below the forward model's accuracy" is the templates' beam's (a dipole)
    assert tpl.meta["tsky"]["beam"]["beam"] == "gaussian_dipole"
    assert diag.config["forward_model_accuracy"] == forward_model_accuracy(tpl.meta["tsky"]["beam"])
    assert diag.to_dict()["config"]["forward_model_accuracy"] == FORWARD_MODEL_ACCURACY
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


def test_timing_offset(setup):
    """Data whose clock runs 90 s ahead (the sky seen at LST + 90 s): named timing_offset,
    its dt recovered; computed from Tsky at shifted LSTs, not from the template."""
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


def test_tilted_sky_frame(setup):
    """A sky tilted by 8 arcmin about the equatorial y axis (a frame error, like J2000 against
    the date): with the frame-tilt templates, ``timing_offset`` names it with its tilt and
    no time offset; the tilt is computed from a turned sky, not from the template."""
    from autocal.diagnosis.effects import sky_templates
    from autocal.sky.models import TiltedSky, get_sky

    obs, _ = setup
    epoch = night_epoch(obs.jds, obs.site.lon_deg)
    tpl = sky_templates(
        SKY, "dipole", "hera", obs.freqs, obs.lsts, nside=32, epoch=epoch, tilt=True
    )
    assert tpl.frame_tilt is not None and tpl.frame_tilt.shape == (2, *tpl.total.shape)
    tilted = TiltedSky(base=get_sky(SKY), tilt_y_arcmin=8.0)
    truth = compute_tsky(
        tilted, "dipole", "hera", obs.freqs, obs.lsts, nside=32, epoch=epoch, pol="ee"
    ).tsky[None]
    diag = diagnose(hidden(obs, truth), tpl)
    assert diag.effects == ["timing_offset"], diag.effects
    params = diag.steps[0]["parameters"]
    assert set(params) == {"dt_s", "tilt_x_arcmin", "tilt_y_arcmin"}
    for name, value in (("tilt_y_arcmin", 8.0), ("tilt_x_arcmin", 0.0), ("dt_s", 0.0)):
        got = params[name]
        assert abs(got["value"] - value) < 3 * got["sigma"] + 0.05 * abs(value), (name, got)
