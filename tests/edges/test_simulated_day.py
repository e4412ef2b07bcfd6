"""An EDGES-like day through a receiver solution, calibrated back by the fit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from autocal.edges.day_fit import fit_edges_day
from autocal.edges.lab_files import read_s11_csv
from autocal.edges.noise_waves import expected_auto_model
from autocal.edges.simulated_day import simulate_edges_day


@pytest.mark.data
@pytest.mark.slow
def test_edges_like_day_recovers_the_receiver(data_root: Path, tmp_path: Path) -> None:
    day = simulate_edges_day(tmp_path, noise=True, seed=11)
    assert len(day.paths) == 4 and all(p.suffix == ".acq" for p in day.paths)
    assert np.ptp(day.lsts) > 23.5
    for r in ("q", "p0"):
        res = fit_edges_day(day, r=r)
        s = res.summary()
        assert abs(s["mean_pull_gain"]) < 0.3 and abs(s["mean_pull_trxr"]) < 0.3, (r, s)
        assert 0.8 < s["std_pull_gain"] < 1.25 and 0.8 < s["std_pull_trxr"] < 1.25, (r, s)
        assert s["max_abs_pull"] < 4.5, (r, s)
        assert 0.9 < s["median_reduced_chi2"] < 1.1, (r, s)
        assert s["rms_err_trxr_K"] < 2.0
    np.testing.assert_allclose(day.expected["q"].trxr, day.solution.c2 - 300.0)


@pytest.mark.data
def test_edges_like_day_with_a_real_antenna_reflection(data_root: Path, tmp_path: Path) -> None:
    s11 = read_s11_csv(data_root / "edges/receiver_cal/edges3_2022_316/s11ant.csv")
    day = simulate_edges_day(
        tmp_path, noise=False, gamma_ant=s11, freq_range=(60e6, 100e6), n_times=24, n_files=2
    )
    matched = expected_auto_model(day.solution, 0.0, "q")
    assert np.min(np.abs(day.expected["q"].G / matched.G - 1)) > 0.02  # the reflection matters
    for r in ("q", "p0"):
        res = fit_edges_day(day, r=r)
        assert np.max(np.abs(res.rel_err_gain)) < 1e-5  # ACQ keeps 1e-5 dB
        assert np.max(np.abs(res.err_trxr)) < 0.02
