"""The diagnosis's products: diagnosis.json, summary.txt and plots."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

import autocal.plots
from autocal.diagnosis.candidate_fits import try_feed_gains
from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.report import Diagnosis, summary_text, write_diagnosis
from autocal.diagnosis.stepwise import diagnose
from tests.diagnosis.simulated import PRIOR_SIGMA, hidden


def test_write_diagnosis(setup, tmp_path: Path, monkeypatch):
    obs, tpl = setup
    diag = diagnose(
        hidden(obs, tpl.total - tpl.cmb), tpl, trxr_prior=150.0, trxr_prior_sigma=PRIOR_SIGMA
    )
    figures = {}
    save = autocal.plots.save_figure

    def keep(fig, path):
        figures[Path(path).name] = fig
        return save(fig, path)

    monkeypatch.setattr(autocal.plots, "save_figure", keep)
    out = write_diagnosis(diag, tmp_path / "diag", obs, stems=("zen.1.HH",))
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["effects"] == ["missing_cmb"]
    step = doc["steps"][0]
    assert {"name", "parameters", "statistic", "delta", "gap_before", "gap_after"} <= set(step)
    assert (out / "residuals_step1.png").stat().st_size > 1000
    # the waterfalls say which antenna and pol they show, of how many, from which run
    fig = figures["residuals_step1.png"]
    shown = f"ant {obs.antennas[0]} {obs.pols[0]}"
    titles = [ax.get_title() for ax in fig.axes if ax.images]
    assert titles[0].startswith(f"{shown}, initial model")
    assert titles[1].startswith(f"{shown}, after missing_cmb")
    total = len(obs.antennas) * len(obs.pols)
    notes = " ".join(t.get_text() for t in fig.texts)
    assert (f"showing 1 of {total} antenna-pols" in notes) == (total > 1)
    head = fig._suptitle.get_text()
    assert head.startswith("zen.1.HH | JD ") and f"{obs.jds.min():.5f}" in head
    assert "missing_cmb" in (out / "summary.txt").read_text()


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
