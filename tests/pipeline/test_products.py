"""The products of autocal.pipeline.products: the figures, drawn beside the solution files."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig
from autocal.pipeline.products import FIGURE_FILES
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


def _small_run(tmp_path, products):
    sim = SimulationConfig(
        beam="dipole", antennas=[0, 1], pols=["ee"], channel_width_khz=8000.0,
        duration_h=6.0, cadence_s=1800.0, seed=3,
    )  # fmt: skip
    obs, _ = simulate(sim)
    config = CalibrationConfig(inputs=["sim"], beam="dipole", products=products)
    return lambda: run_calibration(config, tmp_path, observation=obs)


def test_the_figures_are_drawn_beside_the_solution_files(tmp_path) -> None:
    _small_run(tmp_path, ["hdf5", "png"])()
    names = {p.name for p in tmp_path.iterdir()}
    expected = {"solution.h5", "solution.png", "summary.json", *FIGURE_FILES.values()}
    assert expected <= names
    assert not [n for n in names if n.startswith(".staging")]


@pytest.mark.parametrize("failing", ["figures", "files"])
def test_a_failure_in_either_part_leaves_no_product(tmp_path, monkeypatch, failing) -> None:
    import autocal.pipeline.products as products

    drawn = threading.Event()

    def slow_figures(*args, **kwargs):
        time.sleep(0.3)  # still drawing when the files fail
        drawn.set()
        if failing == "figures":
            raise RuntimeError("figure broke")

    def broken_files(*args, **kwargs):
        raise RuntimeError("file broke")

    monkeypatch.setattr(products, "write_figures", slow_figures)
    if failing == "files":
        monkeypatch.setattr(products, "write_solution", broken_files)
    with pytest.raises(RuntimeError, match=f"{failing[:-1]} broke"):
        _small_run(tmp_path, ["hdf5", "png"])()
    assert drawn.is_set()  # the figures ended before the run did
    assert list(tmp_path.iterdir()) == []  # no product, no staging folder
