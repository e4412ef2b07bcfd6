"""compare.json/h5/png and the command line (autocal.compare.report, autocal compare)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.cli import compare as compare_cmd
from autocal.cli.args import CliError
from autocal.compare.comparison import compare
from autocal.compare.drift import auto_trend
from autocal.compare.errors import CompareError
from autocal.compare.report import write_comparison
from autocal.compare.stability import REFERENCE_DRIFT_FACTOR
from autocal.io.calsol_write import write_calh5
from autocal.io.products import write_solution
from tests.compare.helpers import drifting, reference_for
from tests.io.test_calsol import make_solution


def _run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="autocal")
    sub = parser.add_subparsers(dest="command", required=True)
    compare_cmd.add(sub)
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_writes_plot_and_json(tmp_path, capsys):
    sol = make_solution()
    sol_path = write_solution(sol, tmp_path / "sol.h5")
    # the reference: an autocal calh5 (gain_scale K) of a solution with G / 1.21
    other = replace(sol, coeffs=sol.coeffs / 1.21, cov=sol.cov / 1.21**2)
    ref_path = write_calh5(other, tmp_path / "ref.calh5")
    out = tmp_path / "out"
    assert (
        _run_cli(["compare", str(sol_path), str(ref_path), "--out", str(out), "--smooth-mhz", "5"])
        == 0
    )
    printed = capsys.readouterr().out
    assert "absolute comparison of 2 antenna(s) x 2 pol(s)" in printed
    summary = json.loads((out / "compare.json").read_text())
    assert summary["mode"] == "absolute"
    assert summary["conversion"]["applied"] is False
    for row in summary["per_antenna_pol"]:
        assert row["ratio_mean"] == pytest.approx(1.1, rel=0.01)
    assert summary["smoothing"]["fwhm_MHz"] == 5.0
    assert (out / "compare.png").stat().st_size > 10_000
    assert (out / "compare.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "compare.h5").exists()
    # outputs are not overwritten unless asked; relative mode and selections work
    with pytest.raises(CliError, match="overwrite"):
        _run_cli(["compare", str(sol_path), str(ref_path), "--out", str(out)])
    assert (
        _run_cli(
            [
                "compare",
                str(sol_path),
                str(ref_path),
                "--out",
                str(out),
                "--overwrite",
                "--mode",
                "relative",
                "--antennas",
                "23",
                "--pols",
                "nn",
            ]
        )
        == 0
    )
    summary = json.loads((out / "compare.json").read_text())
    assert summary["mode"] == "relative" and summary["antennas"] == [23]
    assert summary["pols"] == ["nn"]
    with pytest.raises(CliError, match="smooth"):
        _run_cli(["compare", str(sol_path), str(ref_path), "--out", str(out), "--smooth-mhz", "-1"])
    with pytest.raises(CompareError, match=r"not in the solution; it has \[0, 23\]"):
        _run_cli(
            [
                "compare",
                str(sol_path),
                str(ref_path),
                "--out",
                str(out),
                "--overwrite",
                "--antennas",
                "5",
            ]
        )


def test_write_comparison_refuses_overwrite(tmp_path):
    sol = make_solution()
    result = compare(sol, reference_for(sol, 0.5, gain_scale="K"))
    paths = write_comparison(result, tmp_path / "cmp")
    assert set(paths) == {"json", "png", "h5"}
    with pytest.raises(FileExistsError):
        write_comparison(result, tmp_path / "cmp")
    text = (tmp_path / "cmp/compare.json").read_text()
    assert "NaN" not in text  # strict JSON


def test_figure_and_outputs_carry_the_drift(tmp_path):
    sol = make_solution(ntime=20)
    ref = drifting(reference_for(sol, 0.5, gain_scale="K", ntime=20), 0.5)
    power = np.ones((2, 2, 20, sol.freqs.size))
    result = compare(sol, ref, **auto_trend(power, sol.jds, sol.antennas, sol.pols))
    paths = write_comparison(result, tmp_path / "cmp")
    summary = json.loads(paths["json"].read_text())
    row = summary["per_antenna_pol"][0]
    for key in ("offset", "offset_error", "offset_sigma", "reference_drift", "reference_stable"):
        assert key in row
    assert "bootstrap" in summary["offset_method"]
    assert (
        str(REFERENCE_DRIFT_FACTOR).rstrip("0").rstrip(".") in summary["reference_stability_rule"]
    )
    import h5py

    with h5py.File(paths["h5"]) as h5:
        assert h5["reference_series"].shape == (2, 2, 20)
        assert "auto_series/0_ee/power_over_mean" in h5
    assert paths["png"].stat().st_size > 10_000
