"""The diagnosis's products: diagnosis.json, summary.txt and plots."""

from __future__ import annotations

import json
from pathlib import Path

import autocal.plots
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
