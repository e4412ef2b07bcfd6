"""The outlier tests (autocal.service.outliers) on values with known departures."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.service.outliers import night_outliers, robust_centre


def _row(ant: int, night: int = 10, **values: float) -> dict:
    base = {"G": 20.0, "sigma_G": 0.1, "Trxr": 150.0, "sigma_Trxr": 2.0, "reduced_chi2": 1.0}
    return {"antenna": ant, "pol": "ee", "night": night, "config_hash": "c", **base, **values}


def test_robust_centre_estimates_a_normal_width_despite_outliers() -> None:
    values = np.random.default_rng(1).normal(5.0, 2.0, 2001)
    values[:100] = 1e4  # 5 % wild values move neither the centre nor the width much
    centre, spread = robust_centre(values)
    assert centre == pytest.approx(5.0, abs=0.2) and spread == pytest.approx(2.0, rel=0.1)


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
