"""The reference stability rule (autocal.compare.stability)."""

from __future__ import annotations

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.compare.comparison import compare
from autocal.compare.stability import REFERENCE_DRIFT_ALLOWANCE, REFERENCE_DRIFT_FACTOR
from tests.compare.helpers import drifting, end_change, reference_for
from tests.io.test_calsol import make_solution


def test_drifting_reference_is_unstable_and_a_flat_one_stable():
    sol = make_solution(ntime=20)
    flat = reference_for(sol, 0.5, gain_scale="K", ntime=20)
    rising = drifting(flat, 0.5)  # |g_ref|^2 +50 % while the autos are flat
    result = compare(sol, rising, auto_drift=0.0)
    expected = end_change(0.5, 20, 2)
    for row in result.summary["per_antenna_pol"]:
        assert row["reference_drift"] == pytest.approx(expected, rel=1e-9)
        assert row["reference_drift_rms"] > 0.1
        assert row["auto_drift"] == 0.0
        assert row["reference_stable"] is False
        assert row["reference_stability"]["failed"] == ["drift"]
        assert row["reference_stability"]["drift_limit"] == pytest.approx(REFERENCE_DRIFT_ALLOWANCE)
    np.testing.assert_allclose(
        result.reference_series[0, 0], (1 + 0.5 * np.linspace(0, 1, 20)) / 1.25, rtol=1e-9
    )
    stable = compare(sol, flat, auto_drift=0.0)
    for row in stable.summary["per_antenna_pol"]:
        assert row["reference_drift"] == pytest.approx(0.0, abs=1e-12)
        assert row["reference_stable"] is True
    # a reference drift the autos share is allowed (3x the auto's change + 5 %)
    auto = {(0, "ee"): 0.2, (0, "nn"): 0.2, (23, "ee"): 0.1, (23, "nn"): 0.1}
    shared = compare(sol, rising, auto_drift=auto)
    verdict = {
        (r["antenna"], r["pol"]): r["reference_stable"] for r in shared.summary["per_antenna_pol"]
    }
    assert verdict[(0, "ee")] is True and verdict[(23, "nn")] is False  # 0.47 > 0.35
    assert expected > REFERENCE_DRIFT_FACTOR * 0.1 + REFERENCE_DRIFT_ALLOWANCE
    # without the auto's change the drift clause is skipped, the verdict unknown
    unknown = compare(sol, rising)
    row = unknown.summary["per_antenna_pol"][0]
    assert row["auto_drift"] is None and row["reference_stable"] is None
    assert set(row["reference_stability"]["skipped"]) == {"drift", "negative_trxr"}
    assert row["reference_drift"] == pytest.approx(expected)
    # one reference time: no drift, no verdict
    one = compare(sol, reference_for(sol, 0.5, gain_scale="K", ntime=1), auto_drift=0.0)
    assert one.summary["per_antenna_pol"][0]["reference_drift"] is None
    assert one.summary["per_antenna_pol"][0]["reference_stable"] is None


def test_negative_receiver_temperature_implied_by_the_reference():
    sol = make_solution(antennas=(0,), pols=("ee",), ntime=20, flagged=())
    ref = drifting(reference_for(sol, 1.0, gain_scale="K", ntime=20), 0.5)
    g2 = sol.G[0, 0]
    first, last = (
        (1 + 0.5 * np.linspace(0, 1, 20)[:2]).mean(),
        (1 + 0.5 * np.linspace(0, 1, 20)[-2:]).mean(),
    )
    power = np.stack([g2 * 150.0, g2 * 150.0])  # the raw autos do not move
    for tsky, verdict in ((20.0, True), (120.0, False)):
        result = compare(
            sol,
            ref,
            auto_power_ends={(0, "ee"): power},
            tsky_ends={"ee": np.full((2, sol.freqs.size), tsky)},
        )
        row = result.summary["per_antenna_pol"][0]
        implied = row["reference_stability"]["implied_trxr_K"]
        assert implied["first"] == pytest.approx(150.0 / first - tsky, rel=1e-6)
        assert implied["last"] == pytest.approx(150.0 / last - tsky, rel=1e-6)
        assert row["reference_stability"]["tested"] == ["negative_trxr"]
        assert row["reference_stable"] is verdict
