"""User errors are AutocalErrors (exit 2 with a message); bugs are not reported as bad input."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from autocal.cli.main import EXIT_USER_ERROR, main, user_error_message
from autocal.errors import AutocalError

#: Every error class a user can cause, by module.
USER_ERRORS = {
    "autocal.sky.beam_base": "BeamError",
    "autocal.cli.args": "CliError",
    "autocal.compare.errors": "CompareError",
    "autocal.core.coords": "EpochError",
    "autocal.compare.delay": "DelayError",
    "autocal.edges.solutions": "ReceiverCalError",
    "autocal.fit.model": "FitError",
    "autocal.diagnosis.hidden": "HiddenError",
    "autocal.core.observation": "ObservationError",
    "autocal.pipeline.config": "PipelineError",
    "autocal.fit.priors": "PriorError",
    "autocal.simulate.mock": "SimulationError",
    "autocal.core.sites": "SiteError",
    "autocal.sky.models": "SkyModelError",
    "autocal.tsky.result": "TskyError",
    "autocal.io.calsol_files": "CalsolFormatError",
    "autocal.io.datasets": "DataFileMissingError",
    "autocal.io.edges_spectra": "EdgesFormatError",
    "autocal.io.feko": "BeamFileError",
    "autocal.io.miriad": "MiriadFormatError",
    "autocal.io.products": "ProductFormatError",
    "autocal.io.simtruth": "SimTruthError",
    "autocal.io.tskyfile": "TskyFileError",
    "autocal.io.uvh5_meta": "UVH5FormatError",
    "autocal.service.nightly": "NightlyError",
    "autocal.service.paths": "InputPathError",
    "autocal.service.store": "StoreError",
}


@pytest.mark.parametrize(("module", "name"), sorted(USER_ERRORS.items()))
def test_every_user_error_is_an_autocal_error(module: str, name: str) -> None:
    cls = getattr(importlib.import_module(module), name)
    assert issubclass(cls, AutocalError) and issubclass(cls, ValueError)


def test_missing_data_file_is_both_a_missing_file_and_a_user_error() -> None:
    from autocal.io.datasets import DataFileMissingError

    err = DataFileMissingError("sky/x.h5 is not in the data folder")
    assert isinstance(err, FileNotFoundError) and isinstance(err, AutocalError)
    assert user_error_message(err) == "sky/x.h5 is not in the data folder"


def test_user_errors_exit_2_with_the_message(tmp_path: Path, capsys) -> None:
    missing = tmp_path / "zen.2458116.30448.HH.uvh5"
    assert main(["calibrate", str(missing), "--out", str(tmp_path / "o")]) == EXIT_USER_ERROR
    assert "input(s) not found" in capsys.readouterr().err
    # options pydantic rejects
    bad = ["calibrate", str(missing), "--freq-range", "200:100", "--out", str(tmp_path)]
    assert main(bad) == EXIT_USER_ERROR
    assert "--freq-range" in capsys.readouterr().err  # the option, not the field
    # an unknown site (SiteError) from another command
    site = ["tsky", "--beam", "dipole", "--site", "moon", "--freqs", "100e6:110e6:2",
            "--lsts", "0:1:2", "--out", str(tmp_path / "t.h5")]  # fmt: skip
    assert main(site) == EXIT_USER_ERROR
    assert "unknown site 'moon'" in capsys.readouterr().err


@pytest.mark.parametrize("bug", [ValueError("operands could not be broadcast"), ZeroDivisionError])
def test_an_internal_bug_is_not_reported_as_bad_input(
    bug: BaseException, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    import autocal.pipeline.calibrate

    def broken(*args: object, **kwargs: object) -> None:
        raise bug

    monkeypatch.setattr(autocal.pipeline.calibrate, "run_calibration", broken)
    argv = ["calibrate", str(tmp_path / "a.uvh5"), "--out", str(tmp_path / "o")]
    with pytest.raises(type(bug) if isinstance(bug, BaseException) else bug):
        main(argv)
    assert "error:" not in capsys.readouterr().err
    assert user_error_message(ValueError("numpy")) is None


def test_a_bug_exits_1_with_its_traceback(tmp_path: Path) -> None:
    code = (
        "import sys, autocal.pipeline.calibrate\n"
        "from autocal.cli.main import main\n"
        "def broken(*a, **k):\n"
        "    raise ValueError('a bug deep inside')\n"
        "autocal.pipeline.calibrate.run_calibration = broken\n"
        f"sys.exit(main(['calibrate', {str(tmp_path / 'a.uvh5')!r}, '--out', "
        f"{str(tmp_path / 'o')!r}]))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert "Traceback" in done.stderr and "a bug deep inside" in done.stderr
    assert "autocal calibrate: error:" not in done.stderr
