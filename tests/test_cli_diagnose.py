"""``autocal diagnose`` on a simulated UVH5 observation with a hidden gain drift."""

from __future__ import annotations

import json

from autocal.cli import main


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
