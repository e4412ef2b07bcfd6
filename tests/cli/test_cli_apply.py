"""``autocal apply``: real HERA autos calibrated from the command line; bad input exits 2."""

from __future__ import annotations

import pytest
from pyuvdata import UVData

from autocal.cli.main import EXIT_OK, EXIT_USER_ERROR, main
from tests.io.real_solution import real_products

pytestmark = [pytest.mark.slow, pytest.mark.data]


@pytest.fixture(scope="module")
def real(data_root, tmp_path_factory):
    return real_products(data_root, tmp_path_factory.mktemp("real"))


def test_apply_writes_calibrated_uvh5(real, tmp_path, capsys) -> None:
    out = tmp_path / "calibrated.uvh5"
    code = main(["apply", str(real.calfits), str(real.band), "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == EXIT_OK
    assert "vis_units 'K str'" in printed and f"wrote {out}" in printed
    cal = UVData.from_file(str(out))
    assert cal.vis_units == "K str" and "autocal apply:" in cal.history
    assert main(["apply", str(real.calh5), str(real.band), "--out", str(out)]) == EXIT_USER_ERROR
    assert "--overwrite" in capsys.readouterr().err
    args = ["apply", str(real.calh5), str(real.band), "--out", str(out), "--overwrite"]
    assert main(args) == EXIT_OK


@pytest.mark.parametrize(
    ("which", "message"),
    [
        ("raw", "no gains for antenna(s) [24, 25]"),
        ("auto", "not channels of the solution"),
        ("corrupt", "corrupt"),
        ("foreign", "not a UVH5 file autocal wrote"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(real, tmp_path, capsys, which, message) -> None:
    solution, data, out = real.calfits, real.band, tmp_path / "out.uvh5"
    if which in ("raw", "auto"):
        data = real.raw if which == "raw" else real.auto
    elif which == "corrupt":
        solution = tmp_path / "bad.calfits"
        solution.write_bytes(real.calfits.read_bytes()[:5000])
    else:
        out.write_text("someone else's file")
    code = main(["apply", str(solution), str(data), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == EXIT_USER_ERROR
    assert err.startswith("autocal apply: error:") and message in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert (not out.exists()) if which != "foreign" else out.read_text() == "someone else's file"


def test_antennas_select_the_baselines_to_calibrate(real, tmp_path, capsys) -> None:
    """The raw file has crosses to antennas 24 and 25 without autos (no gains): --antennas 23
    keeps antenna 23's baselines, so the antenna refusal gives way to the next check (this
    solution covers 150-160 MHz only); an antenna the data lack is a clear error."""
    out = tmp_path / "out.uvh5"
    args = ["apply", str(real.calfits), str(real.raw), "--out", str(out)]
    assert main([*args, "--antennas", "23"]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "not channels of the solution" in err and "no gains for antenna" not in err
    assert main([*args, "--antennas", "99"]) == EXIT_USER_ERROR
    assert "antenna selection [99] keeps no data" in capsys.readouterr().err
    assert not out.exists()
