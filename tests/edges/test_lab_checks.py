"""The receiver calibration against the lab loads of the data folder."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from autocal.edges.lab_checks import check_edges2_loads, lab_check_edges3, lab_check_receiver01
from autocal.edges.solutions import load_receiver_solution


@pytest.mark.data
def test_edges2_loads_calibrate_to_their_thermistors(data_root: Path) -> None:
    res = check_edges2_loads()
    ref = res["edges_cal_reference"]
    for load, entry in ref.items():
        assert abs(entry["mean"] - entry["thermistor_K"]) < 0.6, load
        assert entry["rms_about_mean"] < 1.5, load
    alan = res["specal_alan"]
    # ambient, open and short cables are all at room temperature; the hot load is hot
    for load in ("open", "short"):
        assert abs(alan[load]["mean"] - alan["amb"]["mean"]) < 0.5
        assert alan[load]["rms_about_mean"] < 1.0
    assert alan["amb"]["mean"] == pytest.approx(ref["ambient"]["thermistor_K"], abs=0.5)
    assert alan["hot"]["mean"] == pytest.approx(ref["hot_load"]["thermistor_K"], abs=1.0)


@pytest.mark.data
def test_edges3_lab_loads_against_the_temperature_log(data_root: Path) -> None:
    res = lab_check_edges3()
    amb, hot = res["amb"], res["hot"]
    assert abs(amb["mean"] - amb["log_amb_load_K"]) < 4.0
    assert abs(hot["mean"] - hot["log_hot_load_K"]) < 6.0
    assert amb["rms_about_mean"] < 1.0 and hot["rms_about_mean"] < 1.0  # flat over 50-190 MHz
    assert hot["tstar"]["rms_about_mean"] > 3.0  # T* is not flat; the calibration makes it so
    # the solution's nominal noise source is 1000 K: with 400 K the hot load is far off
    wrong = lab_check_edges3(replace(load_receiver_solution("edges3-2022-316"), t_load_ns=400.0))
    assert abs(wrong["hot"]["mean"] - hot["log_hot_load_K"]) > 30.0


@pytest.mark.data
def test_receiver01_lab_loads_two_load_calibration(data_root: Path) -> None:
    res = lab_check_receiver01()
    files = res["files"]
    amb0, hot0 = "Ambient_01_2019_329_23_01_16_lab.acq", "HotLoad_01_2019_330_23_38_05_lab.acq"
    # the load thermistors at the spectrum times (ambient ~22 C, hot load warming through 70 C)
    assert 293.0 < res["t_amb_K"] < 297.0 and 335.0 < res["t_hot_K"] < 350.0
    # uncalibrated T* (400 K / 300 K nominal): ambient reads near T_L, the hot load more
    assert abs(files[amb0]["tstar_400_300"]["mean"] - 300.0) < 3.0
    assert files[hot0]["tstar_400_300"]["mean"] > files[amb0]["tstar_400_300"]["mean"] + 10.0
    # the derived internal load sits at the receiver's 25 C
    assert res["t_load_eff"]["mean"] == pytest.approx(298.15, abs=3.0)
    assert res["t_ns_eff"]["min"] > 900.0 and res["t_ns_eff"]["max"] < 2200.0
    # the second ambient file (1 h later) reads the ambient temperature again
    assert files["Ambient_01_2019_330_00_00_00_lab.acq"]["two_load"]["mean"] == pytest.approx(
        res["t_amb_K"], abs=4.0
    )
    # the hot load, settled on later days, reads hot and flat within the noise
    for name in ("HotLoad_01_2019_331_00_00_23_lab.acq", "HotLoad_01_2019_333_00_00_01_lab.acq"):
        assert 380.0 < files[name]["two_load"]["mean"] < 415.0
        assert files[name]["two_load"]["rms_about_mean"] < 8.0
