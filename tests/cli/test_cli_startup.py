"""Fresh processes stay light (issue 25, item 5): parsing the command line, ``--help`` and usage
errors load none of the science stack, and ``import autocal`` does not load astropy, which is
still configured offline as soon as anything imports it.

Checked structurally (which modules a fresh interpreter has loaded), not by timing; the
times are in ``benchmarks/startup.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from autocal.cli.options import HELP_DEFAULTS, default_text
from autocal.pipeline.config import CalibrationConfig

#: Packages that take 0.1-1 s each to import and that parsing never needs.
HEAVY = (
    "numpy",
    "scipy",
    "astropy",
    "pyuvdata",
    "healpy",
    "h5py",
    "matplotlib",
    "numba",
    "dask",
    "distributed",
    "sqlalchemy",
    "fastapi",
    "uvicorn",
    "pydantic",
    "pygdsm",
)

_RUN_CLI = """
import contextlib, io, json, sys
from autocal.cli.main import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
    try:
        status = main({argv!r})
    except SystemExit as exit_:
        status = exit_.code
heavy = sorted(m for m in {heavy!r} if m in sys.modules)
print(json.dumps({{"status": status, "heavy": heavy, "stderr": err.getvalue()[-300:]}}))
"""

COMMANDS = (
    "calibrate",
    "apply",
    "compare",
    "diagnose",
    "tsky",
    "simulate",
    "paper",
    "info",
    "serve",
    "worker",
    "nightly",
)


def _fresh(code: str) -> dict:
    """Run ``code`` in a fresh interpreter; return the JSON it prints last."""
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def _run_cli(argv: list[str]) -> dict:
    return _fresh(_RUN_CLI.format(argv=argv, heavy=HEAVY))


@pytest.mark.parametrize("argv", [["--help"], ["--version"], *([c, "--help"] for c in COMMANDS)])
def test_help_loads_no_science_module(argv: list[str]) -> None:
    result = _run_cli(argv)
    assert result["status"] == 0, result
    assert result["heavy"] == [], f"autocal {' '.join(argv)} imported {result['heavy']}"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["calibrate", "x.uvh5", "--out", "o", "--bogus"], "unrecognized arguments: --bogus"),
        (["calibrate"], "the following arguments are required"),
        (["nightly"], "one of the arguments --night --watch is required"),
        (["tsky", "--nside", "abc"], "invalid int value: 'abc'"),
        (["calibrate", "x.uvh5", "--out", "o", "--model", "spline"], "invalid choice"),
        (["calibrate", "x.uvh5", "--out", "o", "--antennas", "a,b"], "comma-separated integers"),
        (["calibrate", "x.uvh5", "--out", "o", "--order", "2"], "needs --model legendre"),
        (["calibrate", "x.uvh5", "--out", "o", "--dask-workers", "0"], "at least 1"),
        (["calibrate", "x.uvh5", "--out", "o", "--freq-range", "1:2:3"], "LOW:HIGH"),
    ],
)
def test_usage_errors_load_no_science_module(argv: list[str], message: str) -> None:
    result = _run_cli(argv)
    assert result["status"] == 2, result
    assert message in result["stderr"], result
    assert result["heavy"] == [], f"autocal {' '.join(argv)} imported {result['heavy']}"


def test_a_settings_error_loads_only_the_settings() -> None:
    """A value the settings refuse (checked by the pydantic model) needs numpy and pydantic,
    not the fit, astropy or the file formats (importing the fit took 1.3 s)."""
    result = _run_cli(["calibrate", "x.uvh5", "--out", "o", "--nside", "3"])
    assert result["status"] == 2 and "power of two" in result["stderr"], result
    assert set(result["heavy"]) <= {"numpy", "pydantic"}, result


def test_import_autocal_loads_no_science_module() -> None:
    result = _fresh(
        f"import json, sys, autocal\nprint(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    )
    assert result == []


@pytest.mark.parametrize(
    "first_import",
    [
        "import pyuvdata",  # astropy imported by another package
        "import astropy.units",  # by the user
        # by a module the configuration itself imports, coordinates first
        "from autocal.core.sites import HERA; HERA.location",
        "import autocal.core.offline",
        "from autocal.tsky.compute import compute_tsky",
    ],
)
def test_astropy_is_configured_offline_by_whoever_imports_it(first_import: str) -> None:
    code = (
        "import json, sys, autocal\n"
        f"{first_import}\n"
        "state = dict(autocal._offline_state)\n"
        "from astropy.coordinates import EarthLocation\n"
        "from astropy.utils import iers\n"
        "from astropy.utils.data import conf\n"
        "print(json.dumps({'state': state, 'auto_download': iers.conf.auto_download,\n"
        "    'internet': conf.allow_internet, 'sites': EarthLocation._site_registry.names,\n"
        "    'hooks': [type(f).__name__ for f in sys.meta_path]}))\n"
    )
    result = _fresh(code)
    assert result["state"]["configured"] is True, result  # right after the first import
    assert result["auto_download"] is False and result["internet"] is False
    assert result["sites"], "no site registry: astropy would download one"
    assert "_OfflineImportHook" not in result["hooks"], "the hook stays after its work"


def test_the_offline_configuration_does_not_import_astropys_coordinates() -> None:
    """astropy's coordinates (~0.3 s) wait until something uses them; then get the sites."""
    code = (
        "import json, sys, autocal\n"
        "import astropy.units, astropy.time\n"
        "before = 'astropy.coordinates' in sys.modules\n"
        "configured = autocal._offline_state['configured']\n"
        "from astropy.coordinates import EarthLocation\n"
        "print(json.dumps([before, configured, EarthLocation._site_registry.names]))\n"
    )
    before, configured, sites = _fresh(code)
    assert before is False and configured is True
    assert "hera" in sites


def test_astropy_loaded_before_autocal_is_configured_at_import() -> None:
    code = (
        "import json, astropy, autocal\n"
        "from astropy.utils import iers\n"
        "print(json.dumps([autocal._offline_state['configured'], iers.conf.auto_download]))\n"
    )
    assert _fresh(code) == [True, False]


def test_help_defaults_are_the_configurations() -> None:
    for name, value in HELP_DEFAULTS.items():
        field = CalibrationConfig.model_fields[name]
        assert value == field.get_default(call_default_factory=True), name
        assert default_text(value) == default_text(field.get_default(call_default_factory=True))


def test_diagnose_help_shows_the_diagnosis_defaults() -> None:
    """``autocal diagnose --help`` reads ``--rfi-flagging``'s default from HELP_DEFAULTS:
    it must be DiagnoseConfig's own (and calibrate's)."""
    from autocal.diagnosis.run import DiagnoseConfig

    assert (
        DiagnoseConfig.model_fields["rfi_flagging"].get_default() is HELP_DEFAULTS["rfi_flagging"]
    )


def test_a_calibration_imports_the_comparison_and_pyuvdata_writers_only_when_asked() -> None:
    """What ``autocal calibrate`` loads before it runs (the pipeline and the command's
    after-run module) leaves out the comparison (scipy.signal, the beam area) and the
    calibration-solution writers and readers of pyuvdata formats: an hdf5-only run without
    a reference never needs them (they cost ~1.1 s of a fresh process, measured with
    ``python -X importtime``)."""
    code = (
        "import json, sys\n"
        "import autocal.cli.quality, autocal.pipeline.calibrate\n"
        "names = ('autocal.compare.comparison', 'autocal.compare.report', "
        "'autocal.io.calsol_write', 'autocal.io.calsol_read', 'autocal.solution_plots', "
        "'scipy.signal')\n"
        "print(json.dumps([m for m in names if m in sys.modules]))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
