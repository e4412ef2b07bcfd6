"""Figures of autocal.pipeline.products that show fewer antenna-pols than there are say so."""

from __future__ import annotations

import logging

from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig
from autocal.simulate.mock import SimulationConfig, simulate


def test_figures_showing_part_of_the_antenna_pols_say_so_in_the_log(tmp_path, caplog) -> None:
    sim = SimulationConfig(
        beam="dipole",
        antennas=[0, 1, 2],
        pols=["ee", "nn"],
        channel_width_khz=8000.0,
        duration_h=6.0,
        cadence_s=1800.0,
        seed=2,
    )
    obs, _ = simulate(sim)
    config = CalibrationConfig(inputs=["sim"], beam="dipole", products=["png"])
    with caplog.at_level(logging.INFO, logger="autocal.pipeline.products"):
        run_calibration(config, tmp_path, observation=obs)
    assert "show 4 of 6 antenna-pols" in caplog.text
    assert (tmp_path / "residuals.png").exists() and (tmp_path / "data_model.png").exists()
