"""The top-level API (``import autocal``): one calibration for every caller, short reprs.

``autocal.calibrate(path)`` (a notebook), ``autocal calibrate`` (the CLI) and a service job
run the same function with the same defaults, so they give bit-identical solutions on the
same real HERA file.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import autocal
from autocal.cli.main import main
from autocal.fit.passes import DEFAULT_INFLATE_ERRORS, DEFAULT_PASSES, fit
from autocal.io.products import read_solution
from autocal.pipeline.config import CalibrationConfig

pytestmark = pytest.mark.data

#: One antenna of a real HERA file (60 integrations x 64 channels).
HERA_FILE = "hera/autos/zen.2458043.40141.xx.HH.XRAA.uvh5"
ANTENNA = 24
#: Every array a product carries.
ARRAYS = (
    "coeffs",
    "cov",
    "chi2",
    "dof",
    "G",
    "n",
    "Trxr",
    "abs_g",
    "sigma_G",
    "sigma_n",
    "sigma_Trxr",
    "sigma_abs_g",
    "sigma_G_stat",
    "sigma_n_stat",
    "sigma_Trxr_stat",
    "sigma_abs_g_stat",
    "flag_reason",
    "flags",
)


@pytest.fixture(scope="module")
def hera_file(data_root: Path) -> Path:
    return data_root / HERA_FILE


@pytest.fixture(scope="module")
def notebook(hera_file: Path) -> autocal.Solution:
    """What a notebook gets: ``autocal.calibrate(path, antennas=[24])``."""
    return autocal.calibrate(hera_file, antennas=[ANTENNA])


def assert_identical(a: autocal.Solution, b: autocal.Solution) -> None:
    for name in ARRAYS:
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.shape == y.shape, name
        assert np.array_equal(x, y, equal_nan=True), f"{name} differs"
    assert np.array_equal(a.antennas, b.antennas) and a.pols == b.pols


def test_notebook_cli_and_service_job_give_bit_identical_solutions(
    notebook, hera_file: Path, tmp_path: Path
) -> None:
    from autocal.service.settings import Settings
    from autocal.service.store import JobStore
    from autocal.service.worker import Worker

    # the command line
    assert main(["calibrate", str(hera_file), "--antennas", str(ANTENNA), "--products",
                 "hdf5", "--out", str(tmp_path / "cli")]) == 0  # fmt: skip
    cli = read_solution(tmp_path / "cli" / "solution.h5")

    # a service job, run by a worker
    settings = Settings(
        state_dir=tmp_path / "service",
        database_url=f"sqlite:///{tmp_path / 'jobs.sqlite'}",
        dask_scheduler="",
    )
    store = JobStore(settings.resolved_database_url())
    config = CalibrationConfig(inputs=[str(hera_file)], antennas=[ANTENNA], products=["hdf5"])
    job, _ = store.submit(config.model_dump(mode="json"))
    assert Worker(store, settings, worker_id="api-test").run_once()
    done = store.get(job["id"])
    store.engine.dispose()
    assert done["state"] == "succeeded", done.get("error")
    service = read_solution(done["products"]["hdf5"])

    assert_identical(notebook, cli)
    assert_identical(notebook, service)
    assert notebook.config["provenance"]["passes"] == 1  # real HERA data: read once
    assert notebook.config["provenance"]["errors"] == "covariance x max(1, chi2/dof)"
    assert done["result"]["solution"]["median_abs_g"] == pytest.approx(
        notebook.describe()["median_abs_g"], rel=0, abs=0
    )


def test_calibrate_takes_an_observation_a_config_and_options(notebook, hera_file: Path) -> None:
    obs = autocal.read(hera_file, antennas=[ANTENNA])
    assert isinstance(obs, autocal.Observation)
    assert_identical(notebook, autocal.calibrate(obs))
    config = CalibrationConfig(inputs=[str(hera_file)], antennas=[ANTENNA])
    assert_identical(notebook, autocal.calibrate(config))
    # options override a configuration; its defaults are CalibrationConfig's
    legendre = autocal.calibrate(hera_file, config, model="legendre", order=1)
    assert legendre.model.kind == "legendre" and legendre.model.order == 1
    with pytest.raises(autocal.AutocalError, match="unknown calibration option"):
        autocal.calibrate(hera_file, antennas=[ANTENNA], passess=2)
    with pytest.raises(autocal.AutocalError, match="not found"):
        autocal.calibrate(hera_file.with_name("missing.uvh5"))


def test_low_level_fit_agrees_with_calibrate(notebook, hera_file: Path) -> None:
    """``autocal.fit.passes.fit`` has CalibrationConfig's defaults and the same pass loop."""
    defaults = CalibrationConfig.model_fields
    assert defaults["passes"].default == DEFAULT_PASSES == "auto"
    assert defaults["inflate_errors"].default is DEFAULT_INFLATE_ERRORS is True
    obs = autocal.read(hera_file, antennas=[ANTENNA])
    epoch = notebook.config["provenance"]["epoch_jd"]
    tsky = autocal.compute_tsky(
        "gsm2008", "hera", obs.site, obs.freqs, obs.lsts, epoch=epoch, pol="ee"
    ).tsky
    low = fit(obs, tsky)
    assert low.config["passes"] == 1 and low.config["scale_covariance"] == "inflate"
    # the low-level fit has no flagging stage (band edges, RFI): compare with calibrate
    # without it, and check that the flagging only adds flags
    unflagged = autocal.calibrate(hera_file, antennas=[ANTENNA], rfi_flagging=False)
    assert np.all(notebook.flags[unflagged.flags])
    ok = ~unflagged.flags
    assert np.array_equal(low.flags, unflagged.flags)
    # the in-memory sums add the integrations in another order than the streamed blocks
    np.testing.assert_allclose(low.G[ok], unflagged.G[ok], rtol=1e-9)
    np.testing.assert_allclose(low.sigma_G[ok], unflagged.sigma_G[ok], rtol=1e-7)


def test_solution_write_and_to_uvcal(notebook, tmp_path: Path) -> None:
    written = notebook.write(tmp_path, ["calh5", "hdf5"])
    assert sorted(written) == ["calh5", "hdf5"]
    assert_identical(notebook, read_solution(written["hdf5"]))
    uvcal = notebook.to_uvcal()
    ok = ~notebook.flags[:, 0]
    assert np.array_equal(uvcal.flag_array[:, :, 0, 0], ~ok)
    np.testing.assert_allclose(np.abs(uvcal.gain_array[:, :, 0, 0])[ok], notebook.abs_g[:, 0][ok])
    with pytest.raises(FileExistsError):
        notebook.write(tmp_path, ["hdf5"])
    with pytest.raises(autocal.AutocalError, match="unknown product"):
        notebook.write(tmp_path, ["fits"])


def test_reprs_are_short(notebook, hera_file: Path) -> None:
    obs = autocal.read(hera_file)
    tsky = autocal.compute_tsky(
        "gsm2008", "dipole", "hera", obs.freqs, obs.lsts, nside=16, progress=False
    )
    for record, words in (
        (obs, ["7 antennas", "60 times x 64 channels", "100-198.4 MHz", "LST 0.77"]),
        (notebook, ["constant", "antenna [24]", "median |g|", "Trxr", "chi2/dof", "total"]),
        (tsky, ["gsm2008", "gaussian_dipole", "60 LSTs", "64 channels", "median"]),
    ):
        text = repr(record)
        assert "\n" not in text and len(text) < 400 and "array(" not in text, text
        for word in words:
            assert word in text, (word, text)
    assert str(notebook) == repr(notebook)
    many = autocal.calibrate(hera_file)  # 7 antennas: the list is abbreviated
    assert "(7)" in repr(many) and "..." in repr(many)


def test_import_is_lazy_and_diagnose_is_callable() -> None:
    code = (
        "import sys, autocal\n"
        "assert 'autocal.pipeline.calibrate' not in sys.modules, 'pipeline imported eagerly'\n"
        "assert callable(autocal.calibrate) and 'autocal.pipeline.calibrate' in sys.modules\n"
        "assert 'autocal.diagnosis.run' not in sys.modules, 'diagnosis imported eagerly'\n"
        "import autocal.diagnosis.stepwise\n"
        "assert autocal.diagnose is autocal.api.diagnose, 'a submodule shadows autocal.diagnose'\n"
        "assert issubclass(autocal.AutocalError, ValueError)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_other_records_print_shapes_not_arrays() -> None:
    from autocal.fit.model import FitModel
    from autocal.fit.priors import TrxrPrior
    from autocal.fit.sums import NormalSums

    sums = NormalSums.zeros(FitModel.for_lsts(np.linspace(1, 2, 5)), 2, 1, 300)
    text = repr(sums)
    assert text.startswith("NormalSums(") and "float64(2, 1, 300, 2, 2)" in text
    assert "array(" not in text and len(text) < 400
    prior = TrxrPrior("table", np.linspace(1e8, 2e8, 50), np.full(50, 150.0), np.full(50, 5.0))
    assert repr(prior) == (
        "TrxrPrior(source='table', freqs_hz=float64(50,), trxr_k=float64(50,), "
        "sigma_k=float64(50,))"
    )


def test_autocal_diagnose_is_the_diagnosis_stage(hera_file: Path, tmp_path: Path) -> None:
    summary = autocal.diagnose(hera_file, out=tmp_path, antennas=[ANTENNA], max_steps=0)
    assert summary["effects"] == [] and (tmp_path / "summary.json").exists()
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="passes"):  # not a DiagnoseConfig field
        autocal.diagnose(hera_file, out=tmp_path, passes=2)
