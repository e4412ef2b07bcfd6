"""The diagnosis on data from the independent forward model (a small, fast subset).

The whole suite is ``scripts/diagnose_independent_suite.py`` (52 cases,
``docs/results/diagnose_independent/``). Here: the injection of the hidden effects into
the independent model (cheap checks on a few integrations), the suite's plan and scoring,
and a handful of cases diagnosed end to end by :func:`autocal.diagnosis.run.run_diagnosis`.
The end-to-end assertions: clean 31-minute and 24-hour dipole controls name nothing (over
a day a ~1.7e-4 diurnal gain drift and a ~2 s timing offset, the difference between the
independent model's nside-32 Tsky and autocal's nside-64 templates, are detected and
reported negligible); strong time-structured effects and a missing CMB over a day are
named; a beam made narrower in FWHM (not the catalogue's stretch) is named beam_width
alone, the templates that would absorb the rest rejected because the two halves of the
band disagree on them; a gain jitter with a noise drift over 31 minutes (a model with a
local minimum) is found with the drift's true sign; every antenna-pol's own gain jitter
is named as such; a clean half hour through the HERA beam is reported indistinguishable
(a receiver drift or the forward model), nothing named. Not asserted (see the suite's
report): the other HERA-beam cases.
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.rivals import DECISIVE_MARGIN, LEAD_SIGMAS, domain
from autocal.fit.priors import parse_trxr_prior
from autocal.io.uvh5 import read_uvh5
from tests import independent_effects as ie
from tests import independent_sim as sim

SHORT = ie.SPANS["short"]


def _few_jds(count: int = 3) -> np.ndarray:
    jd0 = sim.jd_at_lst(SHORT.lst_start_h)
    return jd0 + np.arange(count) * (600.0 / 86400.0)


def _script() -> Any:
    path = Path(__file__).resolve().parents[2] / "scripts" / "diagnose_independent_suite.py"
    spec = importlib.util.spec_from_file_location("diagnose_independent_suite", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ---------------------------------------------------------------------------------------
# plan and scoring (no data)
# ---------------------------------------------------------------------------------------
def test_suite_plan_covers_the_catalogue() -> None:
    """>= 40 fixed cases: clean controls, every effect alone, pairs, both spans and beams."""
    plan = ie.suite_plan()
    assert len(plan) >= 40
    assert len({c.name for c in plan}) == len(plan)
    assert [c.seed for c in plan] == [c.seed for c in ie.suite_plan()]  # fixed seeds
    clean = [c for c in plan if not c.effects]
    assert len(clean) >= 6
    assert {c.beam for c in clean} == {"dipole", "hera"}
    assert {c.span.name for c in clean} >= {"day", "short"}
    alone = {c.hidden[0] for c in plan if len(c.effects) == 1}
    assert alone == set(ie.HIDDEN_NAMES)
    assert sum(len(c.effects) == 2 for c in plan) >= 6
    assert any("nn" in c.pols for c in plan)
    assert any(len(c.antennas) == 2 for c in plan)
    assert SHORT.ntime == 174 and ie.SPANS["day"].ntime == 96


def test_drawn_parameters_are_in_range() -> None:
    """Draws stay in the catalogue's ranges; the ground is at least 20 K off 300 K."""
    rng = np.random.default_rng(1)
    day = ie.SPANS["day"]
    for _ in range(50):
        p = ie.draw_effect("gain_drift:linear", SHORT, rng).params
        assert 0.01 <= abs(p["amplitude"]) <= 0.05
        p = ie.draw_effect("gain_drift", day, rng).params
        assert p["profile"] == "diurnal" and 0.02 <= p["amplitude"] <= 0.10
        assert 1e-3 <= ie.draw_effect("gain_jitter", day, rng).params["rms"] <= 1e-2
        assert 2e-3 <= ie.draw_effect("antenna_gain_jitter", day, rng).params["rms"] <= 1e-2
        assert 0.01 <= abs(ie.draw_effect("noise_drift", day, rng).params["e_1"]) <= 0.05
        p = ie.draw_effect("cable_reflection", day, rng).params
        assert 1e-3 <= p["a"] <= 1e-2 and 100 <= p["tau_ns"] <= 400
        assert 0.05 <= abs(ie.draw_effect("sky_spectral_index", day, rng).params["dbeta"]) <= 0.2
        tgnd = ie.draw_effect("ground_temperature", day, rng).params["tgnd_K"]
        assert 200 <= tgnd <= 350 and abs(tgnd - 300) >= 20
        assert 0.05 <= abs(ie.draw_effect("beam_width", day, rng).params["w"]) <= 0.15
    with pytest.raises(ie.CaseError, match="unknown"):
        ie.draw_effect("sky_colour", day, rng)
    with pytest.raises(ie.CaseError, match="twice"):
        ie.make_case("x", ("noise_drift", "noise_drift"), "day", 1)


def test_score_names_is_exact() -> None:
    """Exact means the named set is the hidden set; extras and misses are listed."""
    s = ie.score_names(["gain_drift"], ["gain_drift"])
    assert s["exact"] and not s["extras"] and not s["misses"]
    s = ie.score_names([], ["gain_drift", "timing_offset"])
    assert not s["exact"] and s["extras"] == ["gain_drift", "timing_offset"]
    s = ie.score_names(["gain_jitter"], [], negligible=["gain_jitter"])
    assert not s["exact"] and s["misses"] == ["gain_jitter"] and s["exact_or_negligible"]
    s = ie.score_names(["ground_temperature"], [], visible=[])
    assert not s["exact"] and s["exact_visible"] and s["correct"]
    # correct: no extras, and every visible hidden effect named or reported negligible
    assert ie.score_names(["gain_jitter"], [], negligible=["gain_jitter"])["correct"]
    assert not ie.score_names([], ["gain_drift"])["correct"]
    assert not ie.score_names(["sky_scale"], [])["correct"]
    s = ie.score_names([], [], negligible=["gain_drift"])  # reported negligible: no extra
    assert s["exact"] and s["correct"] and not s["extras"]
    assert not s["exact_or_negligible"]  # ... but a report of an effect that is not there
    # exact on what moves the products: an effect that does not may be left unnamed, one
    # that does must be named, and a name that is not hidden is still wrong
    s = ie.score_names(["ground_temperature"], [], matters=[])
    assert not s["exact"] and s["exact_matters"]
    assert ie.score_names(["ground_temperature"], ["ground_temperature"], matters=[])[
        "exact_matters"
    ]
    assert not ie.score_names(["sky_scale"], [], matters=["sky_scale"])["exact_matters"]
    assert not ie.score_names([], ["gain_drift"], matters=[])["exact_matters"]


def test_product_impact_applies_the_negligibility_rule() -> None:
    """Judged from the truth: a bias beyond the rule matters, a small or sub-model one not."""
    gain, trxr = np.full(50, 2.0), np.full(50, 100.0)
    fit = {"g": gain.copy(), "sigma_g": np.full(50, 1e-4), "trxr": trxr.copy()}
    fit["sigma_trxr"] = np.full(50, 0.1)
    assert not ie.product_impact(fit, gain, trxr)["matters"]
    off = dict(fit, trxr=trxr + 2.0)  # 20 sigma and 2 K: matters
    impact = ie.product_impact(off, gain, trxr)
    assert impact["matters"] and impact["trxr_median_k"] == pytest.approx(2.0)
    # 5 sigma but 0.5 K and 2e-4 of G: below what the sky model supports
    assert not ie.product_impact(dict(fit, trxr=trxr + 0.5, g=gain * 1.0002), gain, trxr)["matters"]
    # 0.8 K but 8 sigma: beyond the sigma rule, within the sky model's support
    assert not ie.product_impact(dict(fit, trxr=trxr + 0.8), gain, trxr)["matters"]
    assert ie.product_impact(dict(fit, trxr=trxr + 1.2), gain, trxr)["matters"]
    # one channel 12 K off is more than ten times what the sky model supports
    worst = trxr.copy()
    worst[7] += 12.0
    assert ie.product_impact(dict(fit, trxr=worst), gain, trxr)["matters"]
    # products untouched, but a substantial feature of the data (a clock error over a day)
    assert ie.product_impact(fit, gain, trxr, chi2_share=7.5)["matters"]


def test_simulation_kwargs_inject_the_catalogue_effects() -> None:
    """Gains, ripple, receiver drift, sky and beam changes reach simulate_autos."""
    case = ie.Case(
        "k",
        ie.SPANS["day"],
        (
            ie.Hidden("gain_drift", {"profile": "diurnal", "amplitude": 0.05, "phase": 0.3}),
            ie.Hidden("gain_jitter", {"rms": 0.004, "seed": 5}),
            ie.Hidden("cable_reflection", {"a": 0.005, "tau_ns": 200.0, "phi": 1.0}),
            ie.Hidden("noise_drift", {"e_1": -0.03}),
            ie.Hidden("sky_spectral_index", {"dbeta": 0.1}),
            ie.Hidden("missing_cmb", {"cmb_factor": -1.0}),
            ie.Hidden("beam_width", {"w": 0.1, "mode": "stretch"}),
            ie.Hidden("ground_temperature", {"tgnd_K": 250.0}),
        ),
    )
    kw = ie.simulation_kwargs(case)
    freqs = kw["freqs_hz"]
    t_frac = np.linspace(0.0, 1.0, 96)
    lst = 0.0 + t_frac * 95 * 0.25 * sim.SIDEREAL_RATE
    jitter = ie.jitter_factors(0.004, 5, 96)
    assert abs(np.mean(jitter) - 1) < 1e-12 and 0.002 < np.std(jitter) < 0.006
    expected = (1 + 0.05 * np.sin(2 * np.pi * lst / 24 + 0.3)) * jitter - 1
    np.testing.assert_allclose(kw["drift"](t_frac), expected, rtol=0, atol=1e-15)
    ripple = 1 + 0.005 * np.cos(2 * np.pi * freqs * 200e-9 + 1.0)
    np.testing.assert_allclose(kw["G0"], sim.default_bandpass(freqs) * ripple, rtol=1e-15)
    assert kw["noise_drift"] == -0.03 and kw["tgnd_k"] == 250.0
    assert kw["beam_width"] == 0.1 and kw["beam_width_mode"] == "stretch"
    assert kw["sky"] == sim.SkyChange(dbeta=0.1, nu0_hz=150e6, cmb_k=0.0)
    assert "feed_gain" not in kw
    two = ie.Case(
        "f",
        SHORT,
        (ie.Hidden("antenna_gain_jitter", {"rms": 0.005, "seed": 9}),),
        antennas=(0, 1),
        pols=("ee", "nn"),
    )
    feed = ie.simulation_kwargs(two)["feed_gain"]
    assert feed.shape == (2, 2, SHORT.ntime)
    np.testing.assert_allclose(feed.mean(axis=-1), 1.0, atol=1e-12)
    corr = np.corrcoef(feed.reshape(4, -1))  # independent series
    assert np.max(np.abs(corr - np.eye(4))) < 0.3
    trxr = ie.receiver_temperature(freqs)
    assert trxr[80] == 150.0 and trxr[0] == pytest.approx(130.0) and trxr[-1] == 210.0


def test_trxr_prior_table_reads_back(tmp_path: Path) -> None:
    """The per-channel CSV prior is what autocal's prior reader gives on the channels."""
    freqs = sim.default_freqs()
    trxr = ie.receiver_temperature(freqs)
    path = ie.write_trxr_prior(tmp_path / "p.csv", freqs, trxr, 1.0)
    mean, sigma = parse_trxr_prior(str(path), sigma_k=5.0).at(freqs)
    np.testing.assert_allclose(mean[0, 0], trxr, atol=1e-6)
    np.testing.assert_allclose(sigma, 1.0)


# ---------------------------------------------------------------------------------------
# the injection in the independent model (a few integrations)
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_sky_changes_act_on_the_galactic_part(data_root: Path) -> None:
    """No CMB, spectral index, scale and offset change Tsky exactly as defined."""
    freqs = sim.default_freqs()[::20]
    jds = _few_jds()
    base = sim.independent_tsky(freqs, jds)
    f_below = (sim.independent_tsky(freqs, jds, tgnd_k=400.0) - base) / 100.0
    f_above = 1.0 - f_below
    no_cmb = sim.independent_tsky(freqs, jds, sky=sim.SkyChange(cmb_k=0.0))
    np.testing.assert_allclose(base - no_cmb, sim.T_CMB_K * f_above, rtol=1e-9)
    offset = sim.independent_tsky(freqs, jds, sky=sim.SkyChange(offset_k=7.0))
    np.testing.assert_allclose(offset - base, 7.0 * f_above, rtol=1e-9)
    galactic = sim.independent_tsky(freqs, jds, tgnd_k=0.0, sky=sim.SkyChange(cmb_k=0.0))
    for change, factor in (
        (sim.SkyChange(dbeta=0.15), (freqs / 150e6) ** 0.15),
        (sim.SkyChange(scale=-0.07), np.full(freqs.size, 0.93)),
    ):
        changed = sim.independent_tsky(freqs, jds, sky=change)
        np.testing.assert_allclose(changed - base, galactic * (factor - 1.0), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(sim.independent_tsky(freqs, jds, sky=sim.SkyChange()), base)


@pytest.mark.data
def test_beam_width_changes_the_beam(data_root: Path) -> None:
    """A wider beam sees more ground; w = 0 is the default beam; both modes differ."""
    freqs = sim.default_freqs()[::40]
    jds = _few_jds(2)

    def ground_fraction(**kw: Any) -> np.ndarray:
        cold = sim.independent_tsky(freqs, jds, **kw)
        warm = sim.independent_tsky(freqs, jds, tgnd_k=400.0, **kw)
        return (warm - cold) / 100.0

    base = ground_fraction()
    np.testing.assert_array_equal(
        sim.independent_tsky(freqs, jds, beam_width=0.0, beam_width_mode="stretch"),
        sim.independent_tsky(freqs, jds),
    )
    for mode in ("fwhm", "stretch"):
        assert np.all(ground_fraction(beam_width=0.1, beam_width_mode=mode) > base)
        assert np.all(ground_fraction(beam_width=-0.1, beam_width_mode=mode) < base)
    fwhm = sim.independent_tsky(freqs, jds, beam_width=0.1)
    stretch = sim.independent_tsky(freqs, jds, beam_width=0.1, beam_width_mode="stretch")
    assert np.max(np.abs(fwhm / stretch - 1)) > 1e-3
    with pytest.raises(ValueError, match="beam_width_mode"):
        sim.independent_tsky(freqs, jds, beam_width=0.1, beam_width_mode="taper")


@pytest.mark.data
def test_noise_drift_is_in_the_file(tmp_path: Path, data_root: Path) -> None:
    """Trxr (1 + e_1 s), s from -1 to +1, is what the file holds (noise made negligible)."""
    freqs = sim.default_freqs()[::10]
    truth = sim.simulate_autos(
        tmp_path / "nd.uvh5",
        lst_start_h=SHORT.lst_start_h,
        duration_min=2.0,
        freqs_hz=freqs,
        trxr_k=ie.receiver_temperature(freqs),
        noise_drift=0.04,
        dnu_dt=1e14,
    )
    assert truth.trxr_drift is not None
    # s is linear in the JDs (rounding of JD differences: ~1e-7)
    np.testing.assert_allclose(truth.trxr_drift[[0, -1]], [-0.04, 0.04], rtol=1e-6)
    obs = read_uvh5(truth.path)
    expected = truth.G[None] * (truth.tsky + truth.Trxr * (1 + truth.trxr_drift[:, None]))
    np.testing.assert_allclose(obs.data[0, 0], expected[0], rtol=1e-5)
    np.testing.assert_allclose(truth.expected(), expected, rtol=1e-12)
    assert truth.settings["noise_drift"] == 0.04


@pytest.mark.data
def test_effect_strength_short_span(data_root: Path) -> None:
    """Over 31 min a time-constant effect costs the clean model almost nothing."""
    case = ie.make_case("s", ("missing_cmb",), "short", 3)
    weak = ie.effect_strength(case, case.effects[0])
    assert weak["k"] == 0 and weak["chi2"] < 20 and not weak["visible"]
    case = ie.make_case("s", ("noise_drift",), "short", 3)
    strong = ie.effect_strength(case, case.effects[0])
    assert strong["k"] == 1 and strong["dbic"] > 1e4 and strong["visible"]


# ---------------------------------------------------------------------------------------
# end to end: a handful of cases through run_diagnosis
# ---------------------------------------------------------------------------------------
FAST_CASES = (
    "clean_short",
    "clean_day",
    "noise_drift_short",
    "cable_reflection_short",
    "gain_drift_linear_day",
    "missing_cmb_day",
    "beam_width_fwhm_day",
    "gain_jitter+noise_drift_short",
    "antenna_gain_jitter_short_2ant_eenn",
    "antenna_gain_drift_short_2ant_eenn",
    "clean_short_hera",
    "sky_frame_j2000_day",
)


@pytest.fixture(scope="module")
def rows(tmp_path_factory: pytest.TempPathFactory, data_root: Path) -> dict[str, dict]:
    """The fast cases, simulated and diagnosed (~1 min in all)."""
    folder = tmp_path_factory.mktemp("diagnose_independent")
    plan = {c.name: c for c in ie.suite_plan()}
    return {name: ie.run_case(plan[name], folder) for name in FAST_CASES}


@pytest.mark.data
@pytest.mark.slow
def test_rows_record_the_diagnosis(rows: dict[str, dict]) -> None:
    """Every row holds the truth, the names, the steps with statistics and timings."""
    for name, row in rows.items():
        assert row["case"]["name"] == name
        assert set(row["misses"]) == set(row["hidden"]) - set(row["named"])
        assert set(row["extras"]) == set(row["named"]) - set(row["hidden"])
        assert row["exact"] == (set(row["named"]) == set(row["hidden"]))
        assert math.isfinite(row["initial_reduced_chi2"]) and row["initial_reduced_chi2"] > 0
        assert math.isfinite(row["final_reduced_chi2"])
        assert row["diagnose_config"]["trxr_prior_sigma_k"] == ie.PRIOR_SIGMA_K
        assert row["timings_s"]["diagnosis"] > 0
        for step in row["steps"]:
            assert {"statistic", "p_value", "delta_chi2", "k", "parameters"} <= set(step)
        json.dumps(row, allow_nan=False)


@pytest.mark.data
@pytest.mark.slow
def test_clean_short_dipole_names_nothing(rows: dict[str, dict]) -> None:
    """A clean 31-min dipole file: no effect named, chi2/dof ~ 1."""
    row = rows["clean_short"]
    assert row["named"] == []
    assert abs(row["final_reduced_chi2"] - 1.0) < 0.05


@pytest.mark.data
@pytest.mark.slow
def test_strong_effects_are_named(rows: dict[str, dict]) -> None:
    """Strong drifts, a reflection and a missing CMB (with the prior) are named."""
    assert rows["noise_drift_short"]["named"] == ["noise_drift"]
    assert rows["cable_reflection_short"]["named"] == ["cable_reflection"]
    assert "gain_drift" in rows["gain_drift_linear_day"]["named"]
    assert rows["gain_drift_linear_day"]["initial_reduced_chi2"] > 10
    assert rows["gain_drift_linear_day"]["final_reduced_chi2"] < 1.1
    assert "missing_cmb" in rows["missing_cmb_day"]["named"]
    step = next(s for s in rows["missing_cmb_day"]["steps"] if s["name"] == "missing_cmb")
    assert step["parameters"]["cmb_factor"]["adopted"] == -1.0
    strength = rows["missing_cmb_day"]["strength"]["missing_cmb"]
    # the prior sees 2.725 K x f_above in every channel: sum (2.7 K / 1 K)^2 over 161
    assert 900 < strength["chi2"] < 1300 and strength["visible"]


@pytest.mark.data
@pytest.mark.slow
def test_clean_day_names_nothing(rows: dict[str, dict]) -> None:
    """A clean 24-hour dipole file: nothing named; what the two codes' Tsky differ by is
    at most 'detected, negligible'."""
    row = rows["clean_day"]
    assert row["named"] == [] and row["correct"]
    assert set(row["negligible"]) <= {"gain_drift", "timing_offset"}


@pytest.mark.data
@pytest.mark.slow
def test_a_sky_left_in_j2000_is_named_a_frame_error_not_the_instrument(
    rows: dict[str, dict],
) -> None:
    """The mistake of issue 21 (GSM2008's J2000 places taken as those of the date, 2018):
    ``timing_offset`` alone, turned by precession in right ascension and tilted by it in
    declination (astropy: +54.5 s, 5.94 arcmin about the y axis, 0.12 about x), and no gain
    or noise drift (before the tilt parameters: a diurnal ``gain_drift`` at Delta BIC 747
    came with it). The fit is biased by a few seconds and a fraction of an arcminute by
    what else the two codes differ by (measured 49.9 +- 0.9 s, 6.7 +- 0.3 arcmin), so the
    bounds below allow for that rather than for the statistical sigma alone."""
    row = rows["sky_frame_j2000_day"]
    assert row["named"] == ["timing_offset"] and row["exact"]
    assert not row["negligible"] and not row.get("below_model_accuracy")
    params = row["steps"][0]["parameters"]
    assert 40.0 < params["dt_s"]["value"] < 65.0
    assert abs(params["tilt_y_arcmin"]["value"] - 5.94) < 1.5
    assert abs(params["tilt_x_arcmin"]["value"] - 0.12) < 1.5


@pytest.mark.data
@pytest.mark.slow
def test_clean_short_hera_is_not_blamed_on_the_receiver(rows: dict[str, dict]) -> None:
    """Half an hour through the independently evaluated HERA beam leaves a trend that a
    receiver entry and forward-model entries explain undecidedly (within the margin or twice
    the lead's noise): the step
    is reported indistinguishable, nothing is named or 'detected' (before: ``noise_drift``
    'detected, negligible' at Delta BIC 142, ``timing_offset`` 3.0 behind)."""
    row = rows["clean_short_hera"]
    assert row["named"] == [] and row["negligible"] == [] and row["correct"]
    ind = row["indistinguishable"]
    assert ind is not None and ind["step"] == 1
    kinds = {e.name: domain(e) for e in catalogue(include_timing=True, ntime=174, nfeeds=1)}
    cands = ind["candidates"]
    assert {kinds[name] for name in cands} == {"receiver", "forward model"}
    _assert_undecided(ind)


def _assert_undecided(ind: dict) -> None:
    """Every rival trails the best by less than the margin or twice its lead's sigma."""
    cands = ind["candidates"]
    best = max(cands.values())
    for name, value in cands.items():
        if value != best:
            lead, sigma = best - value, ind["lead_sigma"][name]
            assert lead <= DECISIVE_MARGIN or lead <= LEAD_SIGMAS * sigma, (name, lead, sigma)
    assert "none is named" in ind["message"]


#: Cases of other realisations of the suite (``suite_plan(seed)``) that the suite's own
#: seed did not show: each failed before the change its test names.
HELD_OUT = (
    # a noise drift led a clock offset by Delta BIC 7.9, 0.6 sigma of that lead's noise
    ("clean_short_hera", 20261),
    # a noise drift of 9e-5 of the data led every forward-model entry decisively
    ("clean_short_hera", 20262),
    # a sky offset, a clock offset with a 27-arcmin tilt, a diurnal gain drift and a gain
    # jitter of rms 0.70 +- 1.5 took up what a stretched beam leaves of a wider FWHM
    ("beam_width_fwhm_day", 20262),
    # a reflection of a = 0.24 % beside a 5 % gain drift: the receiver prior was weighted
    # with a gain 2.6x the true one (from a fit without the prior), so sigma_G was 2.5x too
    # large and the ripple's Delta chi^2 (89 by a perfect template) came out 21: missed
    ("gain_drift+cable_reflection_short", 20261),
    # a = 0.23 % at 102.5 ns beside a 4 % drift: refused as "at the edge" of 90-500 ns
    ("gain_drift+cable_reflection_short", 20265),
)


@pytest.fixture(scope="module")
def held_out(
    tmp_path_factory: pytest.TempPathFactory, data_root: Path
) -> dict[tuple[str, int], dict]:
    """The held-out cases, simulated and diagnosed (~70 s)."""
    folder = tmp_path_factory.mktemp("diagnose_held_out")
    out = {}
    for name, seed in HELD_OUT:
        case = next(c for c in ie.suite_plan(seed) if c.name == name)
        out[(name, seed)] = ie.run_case(case, folder / str(seed))
    return out


@pytest.mark.data
@pytest.mark.slow
def test_held_out_clean_hera_half_hour_names_nothing(held_out: dict) -> None:
    """Another noise realisation of the clean HERA-beam half hour: a noise drift leads the
    forward model's entries by more than the Delta BIC margin (7.9) but by less than two
    sigma of its own noise (Vuong's test), so the step is undecided and nothing is named."""
    row = held_out[("clean_short_hera", 20261)]
    assert row["named"] == [] and row["negligible"] == [] and row["correct"]
    ind = row["indistinguishable"]
    assert ind is not None
    _assert_undecided(ind)
    cands = ind["candidates"]
    assert max(cands.values()) - min(cands.values()) > DECISIVE_MARGIN  # the margin alone named it


@pytest.mark.data
@pytest.mark.slow
def test_held_out_receiver_drift_below_the_model_accuracy_is_not_named(held_out: dict) -> None:
    """A third realisation: the noise drift leads decisively, but its signal is under the
    HERA beam file's forward-model accuracy (7e-4 of the data rms): not blamed on the
    receiver, though it would move the products (reported with that change)."""
    row = held_out[("clean_short_hera", 20262)]
    assert row["named"] == [] and row["negligible"] == [] and row["correct"]
    assert row["below_model_accuracy"] == ["noise_drift"]
    step = row["steps"][0]
    assert step["name"] == "noise_drift" and not step["negligible"]
    assert step["signal_rms"] < 7e-4 and step["below_model_accuracy"]


@pytest.mark.data
@pytest.mark.slow
def test_held_out_wider_fwhm_is_beam_width_and_an_unexplained_rest(held_out: dict) -> None:
    """A wider FWHM in another realisation: beam_width alone and the rest unexplained. The
    entries that took up the rest before are refused because the whole band's value lies
    outside what the two halves combine to (a sky offset of +23.5 K from halves of -4.1
    and -4.2 K before)."""
    row = held_out[("beam_width_fwhm_day", 20262)]
    assert row["named"] == ["beam_width"] and row["unexplained"] is not None
    outside = [v for v in row["failed_candidates"].values() if "lies outside" in v]
    assert outside, row["failed_candidates"]
    step = row["steps"][0]["band_consistency"]
    assert step["consistent"] and step["whole_departure"] < 0.01


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.parametrize("seed", [20261, 20265])
def test_held_out_reflection_beside_a_gain_drift_is_named(held_out: dict, seed: int) -> None:
    """A small reflection beside a gain drift over a half hour is named with the drift,
    at its delay, and the ripple gains what a perfect template gains in the independent
    clean fit (``ripple_template_chi2``: the true delay, numpy's least squares on the
    simulator's own fit of ``G(nu)`` and its sigma): the receiver prior is weighted by the
    data's own gain (``prior_gain_reference``), so ``sigma_G`` is the clean fit's."""
    row = held_out[("gain_drift+cable_reflection_short", seed)]
    assert row["named"] == ["gain_drift", "cable_reflection"] and row["exact"]
    true = row["case"]["hidden"][1]["params"]
    step = row["steps"][1]
    tau = step["parameters"]["tau_ns"]
    assert abs(tau["value"] - true["tau_ns"]) < 3 * tau["sigma"] + 1.0
    perfect = row["strength"]["cable_reflection"]["chi2"]
    # the suite's prior is the true Trxr(nu), so G(nu) scatters far less than sigma_G (the
    # bandpass chi2/dof is ~0.003): the ripple's drop is the perfect template's up to a
    # few per cent (the fitted delay, the flags); a sigma_G 25 % off would move it by 40-80 %
    assert abs(step["delta_chi2"] - perfect) < 0.05 * perfect + 3, (step, perfect)


@pytest.mark.data
@pytest.mark.slow
def test_beam_shape_error_is_not_spread_over_other_entries(rows: dict[str, dict]) -> None:
    """A narrower FWHM is named beam_width alone; the rest stays unexplained."""
    row = rows["beam_width_fwhm_day"]
    assert row["named"] == ["beam_width"]
    halves = [v for v in row["failed_candidates"].values() if "two halves of the band" in v]
    assert halves, row["failed_candidates"]
    assert row["unexplained"] is not None
    consistency = row["steps"][0]["band_consistency"]
    assert consistency is not None and consistency["consistent"]


@pytest.mark.data
@pytest.mark.slow
def test_jitter_with_noise_drift_finds_the_true_minimum(rows: dict[str, dict]) -> None:
    """From the current model's values the joint fit reaches the true noise drift."""
    row = rows["gain_jitter+noise_drift_short"]
    assert set(row["named"]) == {"gain_jitter", "noise_drift"}
    assert row["final_reduced_chi2"] < 1.05
    truth = row["case"]["hidden"][1]["params"]["e_1"]
    e_1 = row["final_parameters"]["noise_drift"]["e_1"]["value"]
    assert abs(e_1 - truth) < 0.1 * abs(truth), (e_1, truth)


@pytest.mark.data
@pytest.mark.slow
def test_each_antenna_its_own_jitter(rows: dict[str, dict]) -> None:
    """Independent jitter in 2 antennas x 2 pols: antenna_gain_jitter supersedes the
    common gain_jitter, and the final model fits."""
    row = rows["antenna_gain_jitter_short_2ant_eenn"]
    assert row["named"] == ["antenna_gain_jitter"]
    common = next(s for s in row["steps"] if s["name"] == "gain_jitter")
    assert common["superseded_by"] == "antenna_gain_jitter"
    assert row["final_reduced_chi2"] < 1.05
    rms = row["case"]["hidden"][0]["params"]["rms"]
    step = next(s for s in row["steps"] if s["name"] == "antenna_gain_jitter")
    assert abs(step["parameters"]["rms"]["value"] - rms) < 0.25 * rms


@pytest.mark.data
@pytest.mark.slow
def test_each_antenna_its_own_drift(rows: dict[str, dict]) -> None:
    """Each of 2 antennas x 2 pols drifts its own way: antenna_gain_drift, each antenna-pol's
    d_1 recovered; the drift they share is superseded, not named."""
    row = rows["antenna_gain_drift_short_2ant_eenn"]
    assert row["named"] == ["antenna_gain_drift"]
    case = next(c for c in ie.suite_plan() if c.name == row["case"]["name"])
    factors = ie.simulation_kwargs(case)["feed_gain"]
    step = next(s for s in row["steps"] if s["name"] == "antenna_gain_drift")
    for feed in step["per_feed"]:
        ia = list(case.antennas).index(feed["antenna"])
        truth = factors[ia, list(case.pols).index(feed["pol"])]
        half_change = 0.5 * (truth[-1] - truth[0])  # d_1 of 1 + d_1 s, s from -1 to 1
        assert abs(feed["d_1"] - half_change) < 0.1 * abs(half_change), (feed, half_change)
    shared = [s for s in row["steps"] if s["name"] == "gain_drift"]
    assert shared and all(s["superseded_by"] == "antenna_gain_drift" for s in shared)


@pytest.mark.data
@pytest.mark.slow
def test_suite_report_from_rows(rows: dict[str, dict], tmp_path: Path) -> None:
    """The script's summary and markdown are built from the rows."""
    script = _script()
    result = {
        "generated": "test",
        "settings": {
            "sky": "gsm2008",
            "model_tgnd_k": 300.0,
            "prior_sigma_k": 1.0,
            "nside": 64,
            "dnu_dt": 1e6,
        },
        "cases": list(rows.values()),
    }
    result["summary"] = script.summarise(result["cases"])
    s = result["summary"]
    assert s["cases"] == len(FAST_CASES) and 0 <= s["exact"] <= s["cases"]
    assert s["clean_controls"] == 3 and s["clean_with_no_name"] == 3
    assert "clean_short_hera" in [x["case"] for x in s["indistinguishable"]]
    assert s["exact"] <= s["exact_matters"] <= s["cases"]
    assert set(s["per_effect"]) == {
        "noise_drift",
        "cable_reflection",
        "gain_drift",
        "missing_cmb",
        "beam_width",
        "gain_jitter",
        "antenna_gain_jitter",
        "antenna_gain_drift",
        "timing_offset",
    }
    assert 0 <= s["exact"] <= s["correct"] <= s["cases"]
    text = script.markdown(result)
    assert "| clean_short |" in text and "Per hidden effect" in text
    assert "(indistinguishable: noise_drift" in text
    json.dumps(result, allow_nan=False)
    assert script.select(ie.suite_plan(), ["clean_*"], 2)[1].name == "clean_day_b"
