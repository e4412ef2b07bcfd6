"""The outlier tests (autocal.service.outliers) on values with known departures."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import median_abs_deviation

from autocal.service.outliers import night_outliers, robust_centre


def _row(ant: int, night: int = 10, **values: float) -> dict:
    base = {"G": 20.0, "sigma_G": 0.1, "Trxr": 150.0, "sigma_Trxr": 2.0, "reduced_chi2": 1.0}
    return {"antenna": ant, "pol": "ee", "night": night, "config_hash": "c", **base, **values}


def test_robust_centre_is_the_median_and_the_normal_scaled_mad() -> None:
    values = np.random.default_rng(1).normal(5.0, 2.0, 501)
    centre, spread = robust_centre(values)
    assert centre == np.median(values)
    assert spread == pytest.approx(median_abs_deviation(values, scale="normal"), rel=1e-4)


def test_the_array_test_weighs_the_departure_by_spread_and_sigma() -> None:
    rng = np.random.default_rng(2)
    tonight = [_row(a, Trxr=150.0 + rng.normal(0, 2.0)) for a in range(12)]
    tonight[4]["Trxr"] = 150.0 + 40.0  # ~20 sigma: an outlier
    tonight[7]["Trxr"], tonight[7]["sigma_Trxr"] = 190.0, 30.0  # as far, but poorly measured
    found = night_outliers(tonight, [])
    assert [(o["antenna"], o["test"], o["quantity"]) for o in found] == [(4, "array", "Trxr")]
    assert found[0]["z"] > 5 and "array's median" in found[0]["reason"]


def test_only_the_same_configuration_is_compared_with_the_past() -> None:
    earlier = [_row(1, night=n) for n in (7, 8, 9)]
    tonight = [_row(1, G=25.0), {**_row(2, G=25.0), "config_hash": "other"}]
    earlier.append({**_row(2, night=9), "config_hash": "c"})
    found = night_outliers(tonight, earlier)
    assert {(o["antenna"], o["test"]) for o in found} == {(1, "history")}
    assert found[0]["reference"] == 20.0 and found[0]["spread"] == 0.0
