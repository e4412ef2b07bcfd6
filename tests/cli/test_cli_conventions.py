"""One command-line convention (issue 23): MHz with unit suffixes, refused options, flagged
results, ``--out`` owned by autocal, usage of the sub-command, empty selections, nightly."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from autocal.cli.args import CliError, parse_freq_mhz, parse_freq_pair, parse_freq_range_mhz
from autocal.cli.main import build_parser, main
from autocal.cli.options import calibration_settings
from autocal.cli.quality import EXIT_FLAGGED

HERA_116 = "hera/autos/zen.2458116.*.HH.uvh5"


def _hera_files(data_root: Path) -> list[str]:
    files = sorted(str(p) for p in data_root.glob(HERA_116))
    assert len(files) == 3
    return files


@pytest.mark.parametrize(
    ("text", "mhz"),
    [("150", 150.0), ("150MHz", 150.0), ("1.5e8Hz", 150.0), ("250kHz", 0.25), ("0.15 GHz", 150.0)],
)
def test_a_frequency_is_mhz_or_carries_its_unit(text: str, mhz: float) -> None:
    assert parse_freq_mhz(text, "freq") == pytest.approx(mhz)


def test_a_bare_value_in_the_other_unit_gets_a_hint(capsys) -> None:
    with pytest.raises(CliError, match=r"looks like Hz \(150 MHz\): give 150 or 1.5e8Hz"):
        parse_freq_mhz("1.5e8", "freq-range")
    with pytest.raises(CliError, match=r"looks like kHz \(0.25 MHz\)"):
        parse_freq_mhz("250", "channel-width", bare_limit_mhz=10)
    with pytest.raises(CliError, match="give a frequency in MHz"):
        parse_freq_mhz("abcMHz", "freq")
    # an option whose unit used to be Hz reads such a value in Hz, and says so
    assert parse_freq_mhz("5e3", "noise-dnu", 100, legacy_unit="Hz") == pytest.approx(0.005)
    assert "read as Hz (0.005 MHz)" in capsys.readouterr().err
    assert parse_freq_pair("110MHz:1.9e8Hz", "freq-range") == pytest.approx((110, 190))
    np.testing.assert_allclose(parse_freq_range_mhz("100:1.2e8Hz:3", "freqs"), [100, 110, 120])


def test_calibrate_freq_range_takes_units_and_hints_at_hz() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    calibrate = sub.choices["calibrate"]
    args = calibrate.parse_args(["x.uvh5", "--freq-range", "1.1e8Hz:190MHz", "--out", "o"])
    assert calibration_settings(args)["freq_range_mhz"] == pytest.approx((110, 190))
    args = calibrate.parse_args(["x.uvh5", "--freq-range", "110e6:190e6", "--out", "o"])
    with pytest.raises(CliError, match=r"looks like Hz \(110 MHz\)"):
        calibration_settings(args)


@pytest.mark.data
def test_tsky_freqs_are_mhz_and_old_hz_values_still_work(tmp_path, capsys, data_root) -> None:
    common = ["tsky", "--sky", "uniform:100", "--nside", "16", "--lsts", "0:1:2", "--no-cache"]
    assert main([*common, "--freqs", "100:110:3", "--out", str(tmp_path / "a.h5")]) == 0
    assert main([*common, "--freqs", "100e6,1.05e8Hz,110", "--out", str(tmp_path / "b.h5")]) == 0
    assert "--freqs 100e6 is read as Hz (100 MHz)" in capsys.readouterr().err
    for name in ("a.h5", "b.h5"):
        with h5py.File(tmp_path / name) as h5:  # the table stores Hz
            np.testing.assert_allclose(h5["freqs"][()], [100e6, 105e6, 110e6])


def test_simulate_frequencies_are_mhz(tmp_path, capsys) -> None:
    base = ["simulate", "--beam", "dipole", "--duration", "1", "--cadence", "1800"]
    base += ["--sky", "uniform:100", "--nside", "8", "--freq-start", "100", "--freq-stop", "110"]
    for width, name in (("2.5", "a"), ("2500kHz", "b"), ("2500", "c")):
        out = tmp_path / f"{name}.uvh5"
        assert main([*base, "--channel-width", width, "--out", str(out)]) == 0
        with h5py.File(out) as h5:
            freqs = h5["Header/freq_array"][()].ravel()
        np.testing.assert_allclose(freqs, [100e6, 102.5e6, 105e6, 107.5e6, 110e6])
    assert "--channel-width 2500 is read as kHz (2.5 MHz)" in capsys.readouterr().err


def test_reference_goes_before_or_after_the_inputs(tmp_path) -> None:
    parser = build_parser()
    a, b = "a.calfits", "b.calfits"
    for argv in (
        ["calibrate", "--reference", a, "--reference", b, "in.uvh5", "--out", "o"],
        ["calibrate", "in.uvh5", "--reference", a, "--reference", b, "--out", "o"],
    ):
        args = parser.parse_args(argv)
        assert [str(p) for p in args.inputs] == ["in.uvh5"]
        assert [str(p) for p in args.reference] == [a, b]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--model", "constant", "--order", "3"], "--order .* needs --model legendre"),
        (["--order", "2"], "needs --model legendre"),
        (["--trxr-prior-sigma", "5"], "give the prior too"),
        (["--weights", "identity", "--passes", "2"], "nothing with --weights identity"),
        (["--format", "uvh5", "--edges-bin", "8"], "--edges-bin is an option of EDGES"),
    ],
)
def test_options_that_do_not_apply_are_refused(tmp_path, capsys, options, message) -> None:
    argv = ["calibrate", str(tmp_path / "x.uvh5"), *options, "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    import re

    assert re.search(message, capsys.readouterr().err)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--trxr-prior-sigma", "5"], "give the prior too"),
        (["--max-steps", "0", "--alpha", "0.01"], "--alpha: the acceptance test"),
        (["--max-steps", "0", "--bic-threshold", "3"], "--bic-threshold: the acceptance"),
    ],
)
def test_diagnose_refuses_options_that_do_not_apply(tmp_path, capsys, options, message) -> None:
    """As calibrate does: before any file is read, exit status 2, nothing written."""
    argv = ["diagnose", str(tmp_path / "x.uvh5"), *options, "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.data
def test_rfi_flagging_is_refused_on_edges_spectra(tmp_path, capsys, data_root) -> None:
    argv = ["calibrate", str(data_root / "edges/acq/sample.acq"), "--no-rfi-flagging"]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    assert "EDGES spectra are not flagged" in capsys.readouterr().err


@pytest.mark.data
def test_edges_options_are_refused_on_hera_data(tmp_path, capsys, data_root) -> None:
    argv = ["calibrate", *_hera_files(data_root), "--edges-r", "p0", "--out", str(tmp_path)]
    assert main(argv) == 2
    assert "inputs are uvh5 files" in capsys.readouterr().err
    assert not (tmp_path / "summary.json").exists()


@pytest.mark.data
def test_a_mostly_flagged_result_exits_3_and_says_why(tmp_path, capsys, data_root) -> None:
    from pyuvdata import UVCal

    out = tmp_path / "leg"
    argv = ["calibrate", *_hera_files(data_root), "--model", "legendre", "--order", "1"]
    assert main([*argv, "--products", "calfits", "--out", str(out)]) == EXIT_FLAGGED
    err = capsys.readouterr().err
    quality = json.loads((out / "summary.json").read_text())["quality"]
    # the counts the command reports are the flags pyuvdata reads from the written solution:
    # channels flagged at every integration (the file holds G(t) per integration, and a
    # Legendre G(t) can also be non-positive at some integrations of a solved channel)
    cal = UVCal.from_file(out / "solution.calfits")
    assert cal.Ntimes > 1
    flags = cal.flag_array.all(axis=2)  # (Nants, Nfreqs, Ntimes, Njones) -> per channel
    assert quality["flagged"] == int(flags.sum()) and quality["total"] == flags.size
    assert quality["status"] == "mostly_flagged" and flags.mean() > 0.5
    assert "non-positive gain" in quality["reasons"]
    assert f"{quality['flagged']} of {flags.size} channels flagged" in err
    assert "most channels flagged" in err


@pytest.mark.data
def test_a_rerun_into_the_same_out_leaves_nothing_stale(tmp_path, capsys, data_root) -> None:
    out = tmp_path / "cal"
    files = _hera_files(data_root)
    assert main(["calibrate", *files, "--products", "hdf5,png", "--out", str(out)]) == 0
    assert {"solution.png", "residuals.png", "solution.h5"} <= {p.name for p in out.iterdir()}
    (out / "compare.json").write_text("{}")  # an old comparison
    (out / "notes.txt").write_text("mine")  # not autocal's: kept
    assert main(["calibrate", *files, "--products", "hdf5", "--out", str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    assert names == {"solution.h5", "summary.json", "notes.txt"}
    assert "removed" in capsys.readouterr().out
    assert json.loads((out / "summary.json").read_text())["quality"]["status"] == "ok"


def test_an_unknown_option_shows_the_sub_command_usage(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "x.uvh5", "--site", "hera", "--out", "o"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "usage: autocal calibrate" in err and "unrecognized arguments: --site hera" in err


@pytest.mark.data
def test_an_empty_selection_names_the_data(tmp_path, capsys, data_root) -> None:
    from pyuvdata import UVData

    files = _hera_files(data_root)
    uv = UVData.from_file(files[0], read_data=False)
    band = uv.freq_array.ravel() / 1e6
    argv = ["calibrate", *files, "--out", str(tmp_path / "o")]
    assert main([*argv, "--freq-range", "250:300"]) == 2
    err = capsys.readouterr().err
    assert f"the data cover {band.min():.3f}-{band.max():.3f} MHz ({band.size} channels)" in err
    assert main([*argv, "--lst-range", "20:21"]) == 2
    assert "the data cover LST" in capsys.readouterr().err


@pytest.mark.data
def test_nightly_says_where_its_store_is(tmp_path, capsys, monkeypatch, data_root) -> None:
    from autocal.service import settings as settings_module

    data = tmp_path / "data"
    data.mkdir()
    for f in _hera_files(data_root)[:1]:
        (data / Path(f).name).symlink_to(f)
    monkeypatch.setenv("AUTOCAL_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("AUTOCAL_DATA_ROOTS", json.dumps([str(data), str(data_root)]))
    monkeypatch.delenv("AUTOCAL_DATABASE_URL", raising=False)
    settings_module.get_settings.cache_clear()
    try:
        assert main(["nightly", "--night", "2458116", "--folder", str(data), "--json"]) == 0
    finally:
        settings_module.get_settings.cache_clear()
    captured = capsys.readouterr()
    store = tmp_path / "state" / "jobs.sqlite"
    assert store.exists()
    assert f"job store sqlite:///{store}" in captured.err
    assert json.loads(captured.out)["created"]  # standard output stays JSON
