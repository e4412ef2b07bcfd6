"""Candidates screened by their score: the path of large observations."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.diagnosis import chunks
from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.extended_fit import fit_extended, radiometer_weights
from autocal.diagnosis.normal_equations import (
    MIN_IDENTIFIABLE,
)
from autocal.diagnosis.screening import screen_candidates
from autocal.diagnosis.stepwise import diagnose


def test_score_screening_predicts_the_full_fits(several) -> None:
    """One Gauss-Newton step from the current model predicts each candidate's Delta chi^2:
    within 1 % for the effects in the data, and it ranks the data's effect first."""
    obs, tpl = several
    w = radiometer_weights(obs, obs.data)
    current = fit_extended(obs, tpl, [], weights=w)
    w = radiometer_weights(obs, current)
    current = fit_extended(obs, tpl, [], weights=w)
    cands = [c for c in catalogue(ntime=obs.ntime) if c.kind != "bandpass"]
    scores = screen_candidates(obs, tpl, [], current, cands, weights=w)
    full = {}
    for cand, score in zip(cands, scores, strict=True):
        fit = fit_extended(obs, tpl, [cand], weights=w)
        assert score.identifiable == pytest.approx(fit.identifiable[cand.name], rel=1e-9)
        if score.identifiable >= MIN_IDENTIFIABLE:
            full[cand.name, cand.basis, cand.order] = (score.delta_chi2, current.chi2 - fit.chi2)
    assert full["gain_drift", "legendre", 1][0] == pytest.approx(
        full["gain_drift", "legendre", 1][1], rel=0.01
    )
    assert max(full, key=lambda k: full[k][0])[0] in ("gain_drift", "gain_jitter")


def test_large_path_reaches_the_same_diagnosis(several, monkeypatch) -> None:
    """Screening, warm starts and float32 weights (the path of observations above
    LARGE_SAMPLES) name the same effects as the exact search."""
    obs, tpl = several
    exact = diagnose(obs, tpl, max_steps=2)
    monkeypatch.setattr(chunks, "LARGE_SAMPLES", 0)
    assert radiometer_weights(obs, obs.data).dtype == np.float32
    screened = diagnose(obs, tpl, max_steps=2)
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
