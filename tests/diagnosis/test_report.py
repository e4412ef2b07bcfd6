"""The diagnosis's products: diagnosis.json, summary.txt and plots."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import autocal.plots
from autocal.diagnosis.candidate_fits import try_feed_gains
from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.effects import SkyTemplates
from autocal.diagnosis.report import Diagnosis, summary_text, write_diagnosis
from autocal.diagnosis.stepwise import diagnose
from autocal.simulate.mock import mock_autos
from tests.diagnosis.simulated import BT, PRIOR_SIGMA, hidden


def _keep_figures(monkeypatch) -> dict[str, Any]:
    """Keep every figure saved (file name -> figure) for inspection."""
    figures: dict[str, Any] = {}
    save = autocal.plots.save_figure

    def keep(fig, path):
        figures[Path(path).name] = fig
        return save(fig, path)

    monkeypatch.setattr(autocal.plots, "save_figure", keep)
    return figures


def test_write_diagnosis(setup, tmp_path: Path, monkeypatch):
    obs, tpl = setup
    diag = diagnose(
        hidden(obs, tpl.total - tpl.cmb), tpl, trxr_prior=150.0, trxr_prior_sigma=PRIOR_SIGMA
    )
    figures = _keep_figures(monkeypatch)
    out = write_diagnosis(diag, tmp_path / "diag", obs, stems=("zen.1.HH",))
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["effects"] == ["missing_cmb"]
    step = doc["steps"][0]
    assert {"name", "parameters", "statistic", "delta", "gap_before", "gap_after"} <= set(step)
    assert (out / "residuals_step1.png").stat().st_size > 1000
    # the waterfalls say which antenna and pol they show, of how many, from which run
    fig = figures["residuals_step1.png"]
    assert obs.shape[:2] == (1, 1)  # its one antenna-pol, before and after
    shown = f"ant {obs.antennas[0]} {obs.pols[0]}"
    titles = [ax.get_title() for ax in fig.axes if ax.images]
    assert len(titles) == 2
    assert titles[0].startswith(f"{shown}, initial model")
    assert titles[1].startswith(f"{shown}, after missing_cmb")
    assert "showing" not in " ".join(t.get_text() for t in fig.texts)
    head = fig._suptitle.get_text()
    assert head.startswith("zen.1.HH | JD ") and f"{obs.jds.min():.5f}" in head
    assert "missing_cmb" in (out / "summary.txt").read_text()


def _two_pols(tpl: SkyTemplates) -> SkyTemplates:
    """The same templates for pols ee and nn."""
    fields: dict[str, Any] = {
        name: np.repeat(getattr(tpl, name), 2, axis=0)
        for name in ("total", "galactic", "cmb", "ground", "f_above", "f_below")
    }
    for name in ("beam_dwidth", "lst_derivative"):
        if getattr(tpl, name) is not None:
            fields[name] = np.repeat(getattr(tpl, name), 2, axis=0)
    for name in ("beam_width_poly", "frame_tilt"):  # (K or 2, Npol, Ntime, Nfreq)
        if getattr(tpl, name) is not None:
            fields[name] = np.repeat(getattr(tpl, name), 2, axis=1)
    return dataclasses.replace(tpl, **fields)


@pytest.mark.parametrize("nant", [2, 3])
def test_residual_plots_show_every_antenna_pol_up_to_calibrates_limit(
    setup, nant, tmp_path: Path, monkeypatch, caplog
) -> None:
    """As ``autocal calibrate``'s residuals.png: a labelled waterfall (before and after, side
    by side) of each antenna-pol up to the same limit, 'showing N of M' (figure and log)
    beyond it."""
    obs, tpl = setup
    tpl2 = _two_pols(tpl)
    data = mock_autos(
        tpl2.total - tpl2.cmb, np.ones(obs.ntime), 150.0, nant=nant, bandwidth_time=BT,
        rng=np.random.default_rng(5),
    )  # fmt: skip
    many = dataclasses.replace(
        obs, data=data, antennas=np.arange(nant) + 10, pols=("ee", "nn"), flags=None,
        nsamples=np.broadcast_to(obs.nsamples, data.shape).copy(), antenna_names=(),
    )  # fmt: skip
    diag = diagnose(many, tpl2, trxr_prior=150.0, trxr_prior_sigma=PRIOR_SIGMA)
    assert diag.effects == ["missing_cmb"]
    figures = _keep_figures(monkeypatch)
    with caplog.at_level(logging.INFO, logger="autocal.diagnosis.report"):
        write_diagnosis(diag, tmp_path / "diag", many, stems=("zen.2.HH",))
    total = 2 * nant
    shown_ants = many.antennas[: autocal.plots.waterfall_antennas(2)].tolist()
    shown = [f"ant {a} {p}" for a in shown_ants for p in ("ee", "nn")]
    assert len(shown) == min(total, autocal.plots.MAX_PLOTTED)
    fig = figures["residuals_step1.png"]
    waterfalls = [ax for ax in fig.axes if ax.images]
    assert len(waterfalls) == 2 * len(shown)
    for i, label in enumerate(shown):
        before, after = waterfalls[2 * i : 2 * i + 2]
        assert before.get_title().startswith(f"{label}, initial model")
        assert after.get_title().startswith(f"{label}, after missing_cmb")
        assert before.get_position().y0 == pytest.approx(after.get_position().y0)  # one row
        assert before.get_position().x0 < after.get_position().x0
    head = fig._suptitle.get_text()
    assert head.startswith("zen.2.HH | JD ") and f"{many.jds.min():.5f}" in head
    note = f"showing {len(shown)} of {total} antenna-pols"
    notes = " ".join(t.get_text() for t in fig.texts)
    logged = [r.getMessage() for r in caplog.records if "residual plots show" in r.getMessage()]
    if len(shown) < total:
        assert note in notes
        assert logged == [f"residual plots show {len(shown)} of {total} antenna-pols "
                          f"({', '.join(shown)})"]  # fmt: skip
    else:
        assert "showing" not in notes and not logged


def test_summary_marks_superseded_and_dropped_steps() -> None:
    """summary.txt says which steps a later one superseded or the re-test dropped."""
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


def test_entries_not_tested_are_reported_with_the_reason(setup) -> None:
    """Above 64 antenna-pols the per-antenna entries are not tested: diagnosis.json says so
    ('not_tested', with the reason) and so does the summary, so that their absence from
    the effects is not read as 'not present'."""
    obs, _ = setup
    many = dataclasses.replace(
        obs,
        data=np.repeat(obs.data, 66, axis=0),
        flags=np.repeat(obs.flags, 66, axis=0),
        nsamples=np.repeat(obs.nsamples, 66, axis=0),
        antennas=np.arange(66),
        antenna_names=(),
    )
    entry = next(e for e in catalogue(ntime=obs.ntime, nfeeds=66) if e.name == "antenna_gain_drift")
    gap = {"reduced_chi2": 1.0, "rms_normalised_residual": 1.0}
    diag = Diagnosis(config={"failed_candidates": {}}, initial_gap=gap, final_gap=gap)
    state = SimpleNamespace(obs=many, active=[], feed_accepted=set(), diag=diag)
    state.fail = lambda key, why: diag.config["failed_candidates"].__setitem__(key, why)
    assert try_feed_gains(SimpleNamespace(), state, entry) is None
    assert "66 antenna-pols" in diag.to_dict()["not_tested"]["antenna_gain_drift"]
    assert "not tested: antenna_gain_drift (66 antenna-pols" in summary_text(diag)


def test_weak_negligible_effects_of_an_unexplained_remainder_are_not_detections() -> None:
    """With an unexplained remainder, an effect negligible for the products that explains
    less than ABSORBED_SHARE of its excess chi2 is reported as part of the remainder, not as
    detected; one explaining more stays "detected, negligible"; without a remainder nothing
    moves."""
    from autocal.diagnosis.gap import ABSORBED_SHARE
    from autocal.diagnosis.report import Diagnosis, summary_text
    from autocal.diagnosis.stepwise import _absorb_into_remainder

    def make(unexplained: bool) -> Diagnosis:
        gap = {"chi2": 4000.0, "dof": 1000.0, "reduced_chi2": 4.0, "rms_normalised_residual": 2.0}
        steps = [
            {
                "name": name,
                "parameters": {},
                "statistic": 20.0,
                "delta": delta,
                "negligible": True,
                "gap_before": gap,
                "gap_after": gap,
            }
            for name, delta in (
                ("gain_drift", 0.5 * ABSORBED_SHARE * 3000.0),
                ("noise_drift", 600.0),
            )
        ]
        return Diagnosis(
            steps=steps,
            negligible=["gain_drift", "noise_drift"],
            initial_gap=gap,
            final_gap=gap,
            unexplained={"message": "unexplained: chi2/dof 4 remains"} if unexplained else None,
        )

    diag = make(unexplained=True)
    _absorb_into_remainder(diag)
    assert diag.absorbed == ["gain_drift"] and diag.negligible == ["noise_drift"]
    assert diag.unexplained["absorbed"][0]["share"] == 0.5 * ABSORBED_SHARE
    assert diag.to_dict()["absorbed"] == ["gain_drift"]
    text = summary_text(diag)
    assert "part of the unexplained remainder" in text and "gain_drift (5.0 %)" in text
    plain = make(unexplained=False)
    _absorb_into_remainder(plain)
    assert plain.absorbed == [] and plain.negligible == ["gain_drift", "noise_drift"]


def test_negligible_effects_below_the_model_accuracy_are_not_detections() -> None:
    """A negligible effect of the data's structure whose signal is under the forward model's
    accuracy is reported as such; above it, or one seen through the prior, stays "detected,
    negligible". A named entry under it is not attributed either, whatever it would change in
    the products (reported below the accuracy, "would move the products"); one above it stays
    named."""
    from autocal.diagnosis.impact import (
        FORWARD_MODEL_ACCURACY,
        forward_model_accuracy,
        signal_rms,
    )
    from autocal.diagnosis.stepwise import _below_model_accuracy

    radiometer = 1e6 * 15456  # dnu dt = 1e6 over a clean day of one feed
    gap = {"chi2": 15456.0, "dof": 15450.0, "reduced_chi2": 1.0, "rms_normalised_residual": 1.0}

    def delta_for(size: float) -> float:
        return size**2 * radiometer

    steps = [
        {"name": name, "parameters": {}, "statistic": 30.0, "delta": delta_for(size)}
        | {"gap_before": gap, "gap_after": gap}
        for name, size in (
            ("gain_drift", 0.4 * FORWARD_MODEL_ACCURACY),
            ("timing_offset", 3.0 * FORWARD_MODEL_ACCURACY),
            ("ground_temperature", 0.4 * FORWARD_MODEL_ACCURACY),
            ("noise_drift", 0.1 * FORWARD_MODEL_ACCURACY),
            ("beam_width", 0.3 * FORWARD_MODEL_ACCURACY),
            ("gain_jitter", 2.0 * FORWARD_MODEL_ACCURACY),
        )
    ]
    for st in steps:
        st["negligible"] = st["name"] in ("gain_drift", "timing_offset", "ground_temperature")

    def diagnosis() -> Diagnosis:
        return Diagnosis(
            steps=[dict(st) for st in steps],
            effects=["noise_drift", "beam_width", "gain_jitter"],
            negligible=["gain_drift", "timing_offset", "ground_temperature"],
            initial_gap=gap,
            final_gap=gap,
        )

    diag = diagnosis()
    _below_model_accuracy(diag, radiometer, forward_model_accuracy({"beam": "gaussian_dipole"}))
    assert diag.below_model_accuracy == ["gain_drift", "noise_drift", "beam_width"]
    assert diag.negligible == ["timing_offset", "ground_temperature"]
    assert diag.effects == ["gain_jitter"]
    assert diag.steps[0]["signal_rms"] == pytest.approx(0.4 * FORWARD_MODEL_ACCURACY)
    assert signal_rms(delta_for(2e-4), radiometer) == pytest.approx(2e-4)
    text = summary_text(diag)
    assert "below the forward model's accuracy" in text and "4.0e-05 of the data rms" in text
    assert "noise_drift (would move the products)" in text
    assert "beam_width (would move the products)" in text
    assert "gain_drift (would" not in text
    assert "step 4: noise_drift [1.0e-05 of the data rms, below" in text  # not "negligible"
    assert diag.to_dict()["below_model_accuracy"] == ["gain_drift", "noise_drift", "beam_width"]
    # through a beam read from a HEALPix file the floor is coarser (measured in
    # tests/diagnosis/test_model_accuracy.py): a 3e-4 timing offset is below it, and the
    # summary states the floor the run used
    floor = forward_model_accuracy({"beam": "uvbeam_healpix", "file": "HERA_NF.beamfits"})
    assert floor > 3.0 * FORWARD_MODEL_ACCURACY
    coarse = diagnosis()
    coarse.config["forward_model_accuracy"] = floor
    _below_model_accuracy(coarse, radiometer, floor)
    assert coarse.below_model_accuracy == [
        "gain_drift",
        "timing_offset",
        "noise_drift",
        "beam_width",
        "gain_jitter",  # 2e-4: above the dipole's floor, under this one
    ]
    assert coarse.effects == []
    assert coarse.negligible == ["ground_temperature"]
    assert f"under {floor:g} of the data rms" in summary_text(coarse)
    assert forward_model_accuracy(None) == FORWARD_MODEL_ACCURACY
    widened = {"beam": "scaled", "factor": 1.1, "base": {"beam": "uvbeam_healpix"}}
    assert forward_model_accuracy(widened) == floor  # judged by the beam it is made from


def test_timing_offsets_and_tilts_beyond_their_templates_are_refused() -> None:
    """The clock offset beyond its template's step, and (over long spans) a frame tilt beyond
    its templates' +-30 arcmin, are refused as other structure; within them, accepted."""
    from autocal.diagnosis.candidate_fits import (
        TILT_MAX_ARCMIN,
        TIMING_MAX_S,
        _beyond_timing_range,
    )

    entries = catalogue(include_timing=True, include_tilt=True, ntime=100)
    timing = next(e for e in entries if e.name == "timing_offset")
    assert timing.params == ("dt_s", "tilt_x_arcmin", "tilt_y_arcmin")

    def trial(*values: float) -> SimpleNamespace:
        return SimpleNamespace(params={"timing_offset": np.array(values)})

    assert _beyond_timing_range(timing, trial(50.0, 0.1, 6.0)) is None
    assert "beyond the linear" in _beyond_timing_range(timing, trial(TIMING_MAX_S + 1, 0, 0))[1]
    refused = _beyond_timing_range(timing, trial(50.0, 0.0, -(TILT_MAX_ARCMIN + 1)))
    assert refused is not None and "tilt" in refused[1]
    short = next(e for e in catalogue(include_timing=True, ntime=100) if e.name == "timing_offset")
    assert short.params == ("dt_s",) and _beyond_timing_range(short, trial(50.0)) is None
