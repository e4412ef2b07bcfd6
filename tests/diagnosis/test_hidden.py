"""Hidden-effect test cases: written, read back, diagnosed and scored."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from autocal.diagnosis.hidden import (
    HiddenGenerator,
    draw_case,
    draw_effect,
    run_case,
    score,
    suite_cases,
)
from autocal.diagnosis.stepwise import diagnose
from autocal.simulate.mock import SimulationConfig
from tests.diagnosis.simulated import BT, SKY


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
