"""Calibration options: the command line, the REST API and the configuration agree."""

from __future__ import annotations

import argparse

import pytest

from autocal.cli.args import CliError
from autocal.cli.main import build_parser
from autocal.cli.options import calibration_dests, calibration_settings
from autocal.pipeline.config import CalibrationConfig

SETTINGS = set(CalibrationConfig.model_fields) - {"inputs"}


def _subparser(name: str) -> argparse.ArgumentParser:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def test_every_setting_has_one_option_in_calibrate_and_nightly() -> None:
    fields = calibration_dests()  # the options set the configuration fields of their name
    assert len(fields) == len(set(fields))
    assert set(fields) == SETTINGS
    for command in ("calibrate", "nightly"):
        dests = {a.dest for a in _subparser(command)._actions}
        assert set(calibration_dests()) <= dests, command


def test_every_setting_is_an_api_option() -> None:
    from service.schemas import CalibrationOptions

    assert set(CalibrationOptions.model_fields) == SETTINGS


def _settings(*argv: str) -> dict:
    args = _subparser("calibrate").parse_args(["x.uvh5", "--out", "o", *argv])
    return calibration_settings(args)


def test_options_are_parsed_into_configuration_fields() -> None:
    assert _settings() == {}  # nothing given: the configuration's defaults apply
    got = _settings(
        "--format",
        "edges",
        "--edges-r",
        "p0",
        "--edges-bin",
        "16",
        "--passes",
        "2",
        "--no-inflate-errors",
        "--tgnd",
        "290",
        "--freq-range",
        "50:100",
        "--lst-range",
        "22:2",
        "--antennas",
        "1,2",
        "--pols",
        "EE",
        "--products",
        "calfits,hdf5",
    )
    assert got == {
        "input_format": "edges",
        "edges_r": "p0",
        "edges_bin": 16,
        "passes": 2,
        "inflate_errors": False,
        "tgnd_k": 290.0,
        "freq_range_mhz": (50.0, 100.0),
        "lst_range_h": (22.0, 2.0),
        "antennas": [1, 2],
        "pols": ["ee"],
        "products": ["calfits", "hdf5"],
    }
    config = CalibrationConfig(inputs=["x"], **got)
    assert config.passes == 2 and config.inflate_errors is False and config.edges_bin == 16
    assert _settings("--passes", "auto", "--inflate-errors") == {
        "passes": "auto",
        "inflate_errors": True,
    }


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--edges-bin", "0"], "--edges-bin"),
        (["--nside", "63"], "power of two"),
        (["--order", "11"], "order"),
        (["--freq-range", "110e6:190e6"], "MHz"),
        (["--products", "fits"], "products"),
        (["--antennas", "a,b"], "comma-separated integers"),
    ],
)
def test_bad_options_name_the_setting(argv: list[str], message: str) -> None:
    with pytest.raises(CliError, match=message):
        _settings(*argv)


def test_help_shows_the_configuration_defaults(capsys) -> None:
    with pytest.raises(SystemExit):
        _subparser("calibrate").parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    for field in ("edges_bin", "nside", "tgnd_k", "passes"):
        default = CalibrationConfig.model_fields[field].default
        assert f"(default: {default})" in text, field
