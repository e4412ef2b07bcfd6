"""``autocal diagnose`` on a simulated UVH5 observation with a hidden gain drift."""

from __future__ import annotations

import json

import pytest

from autocal.cli.main import main


def test_cli_diagnose_names_a_hidden_gain_drift(tmp_path, capsys) -> None:
    mock = tmp_path / "drift.uvh5"
    sim = ["simulate", "--beam", "dipole", "--gain", "a", "--cadence", "600"]
    sim += ["--channel-width", "1000", "--noise-dnu", "1e6", "--out", str(mock)]
    assert main(sim) == 0, capsys.readouterr().err
    out = tmp_path / "diag"
    assert main(["diagnose", str(mock), "--beam", "dipole", "--out", str(out)]) == 0
    assert "gain_drift" in capsys.readouterr().out
    result = json.loads((out / "diagnosis.json").read_text())
    assert result["effects"] == ["gain_drift"]
    assert (out / "summary.txt").is_file()
    assert main(["diagnose", str(mock), "--freq-range", "120", "--out", str(out)]) == 2
    assert "LOW:HIGH" in capsys.readouterr().err


def test_cli_diagnose_refuses_what_the_memory_cannot_hold(tmp_path, capsys, monkeypatch) -> None:
    from autocal.diagnosis import run as diagnose_run

    mock = tmp_path / "small.uvh5"
    sim = ["simulate", "--beam", "dipole", "--cadence", "1800", "--channel-width", "4000"]
    assert main([*sim, "--out", str(mock)]) == 0, capsys.readouterr().err
    capsys.readouterr()
    monkeypatch.setattr(diagnose_run, "available_memory", lambda: 0.5e9)
    out = tmp_path / "diag"
    assert main(["diagnose", str(mock), "--beam", "dipole", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "GB and 0.5 GB are available" in err and "--antennas" in err
    assert not out.exists()  # nothing half-written
    # unknown available memory (no /proc): no refusal
    monkeypatch.setattr(diagnose_run, "available_memory", lambda: None)
    diagnose_run.check_memory((350, 2, 8640, 1536))
    monkeypatch.setattr(diagnose_run, "available_memory", lambda: 24e9)
    diagnose_run.check_memory((30, 2, 192, 1536))  # 17.7 M samples: the measured 1.8 GB run
    diagnose_run.check_memory((350, 2, 192, 1536))  # a whole HERA file: the measured 6.3 GB
    with pytest.raises(diagnose_run.DiagnoseError, match="350 antennas x 2 pols x 1536 channels"):
        diagnose_run.check_memory((350, 2, 8640, 1536))  # a whole 8 h night: ~240 GB
    monkeypatch.setattr(diagnose_run, "available_memory", lambda: 4e9)
    with pytest.raises(diagnose_run.DiagnoseError, match="select fewer antennas"):
        diagnose_run.check_memory((350, 2, 192, 1536))


def test_cli_diagnose_takes_a_prior_table_and_refuses_a_bad_one(tmp_path, capsys) -> None:
    """A receiver that varies with frequency, given as a table: the diagnosis records its
    range; a table that does not cover the band is refused before anything is read."""
    mock = tmp_path / "clean.uvh5"
    sim = ["simulate", "--beam", "dipole", "--cadence", "1800", "--channel-width", "4000"]
    assert main([*sim, "--out", str(mock)]) == 0, capsys.readouterr().err
    table = tmp_path / "trxr.csv"
    table.write_text("freq_mhz,trxr_k,sigma_k\n100,140,2\n200,160,2\n")
    out = tmp_path / "diag"
    args = ["diagnose", str(mock), "--beam", "dipole", "--trxr-prior", str(table)]
    assert main([*args, "--out", str(out)]) == 0, capsys.readouterr().err
    config = json.loads((out / "diagnosis.json").read_text())["config"]
    prior = config["trxr_prior_K"]
    assert 140 <= prior["min"] < prior["median"] < prior["max"] <= 160
    assert config["trxr_prior_sigma_K"] == 2.0
    narrow = tmp_path / "narrow.csv"
    narrow.write_text("freq_mhz,trxr_k\n150,150\n160,150\n")
    bad = tmp_path / "bad"
    assert main(["diagnose", str(mock), "--trxr-prior", str(narrow), "--out", str(bad)]) == 2
    assert "covers the data band" in capsys.readouterr().err
    assert not bad.exists()
