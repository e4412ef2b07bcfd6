"""Accepting candidates: the final model's verdict on each kept effect's impact."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from autocal.diagnosis.acceptance import final_impacts
from autocal.diagnosis.report import Diagnosis


def _fit(g: float, chi2: float) -> SimpleNamespace:
    shape = (1, 1, 16)
    return SimpleNamespace(
        G=np.full(shape, g),
        Trxr=np.full(shape, 150.0),
        gain_factor=None,
        noise_factor=None,
        chi2=chi2,
        ndata=10_000,
    )


def test_final_verdict_on_the_products_is_the_final_models():
    """A drift that moved G by 1.2e-3 when it was accepted, but by 1e-4 in the final model
    (a later effect took over part of it), is reported negligible; an effect negligible
    at its step but not in the final model is named."""
    current = _fit(1.0, 10_000.0)
    ctx = SimpleNamespace(sigma_g=np.full((1, 1, 16), 1e-3), sigma_t=np.full((1, 1, 16), 0.5))
    diag = Diagnosis(effects=["sky_scale", "gain_drift"], negligible=["timing_offset"])
    diag.steps = [
        {"name": "sky_scale", "negligible": False},
        {"name": "gain_drift", "negligible": False},
        {"name": "timing_offset", "negligible": True},
    ]
    withouts = {
        "sky_scale": _fit(1.1, 90_000.0),
        "gain_drift": _fit(1.0 - 1e-4, 10_040.0),
        "timing_offset": _fit(1.0 - 5e-3, 10_040.0),
    }
    state = SimpleNamespace(diag=diag, current=current)
    final_impacts(ctx, state, withouts)
    assert diag.effects == ["sky_scale", "timing_offset"]
    assert diag.negligible == ["gain_drift"]
    drift = diag.steps[1]
    assert drift["negligible"] and drift["final_negligible"]
    assert abs(drift["final_product_impact"]["G"]["median_relative_change"] - 1e-4) < 1e-6
