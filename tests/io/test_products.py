"""The HDF5 solution product: exact round trip, provenance, atomic writes, errors."""

from __future__ import annotations

import json
from dataclasses import fields, replace

import h5py
import numpy as np
import pytest

import autocal
from autocal.fit.solution import Solution
from autocal.fit.solve import FLAG_REASONS
from autocal.io import products
from autocal.io.products import (
    FORMAT,
    ProductFormatError,
    read_provenance,
    read_solution,
    write_solution,
)
from tests.io.test_calsol import fitted_solution, make_solution


def assert_same_solution(a: Solution, b: Solution) -> None:
    for f in fields(Solution):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if f.name == "total" and va is not None:
            assert vb is not None, "total"
            for g in fields(va):
                xa, xb = getattr(va, g.name), getattr(vb, g.name)
                if isinstance(xa, np.ndarray):
                    assert xa.dtype == xb.dtype and xa.shape == xb.shape, g.name
                    np.testing.assert_array_equal(xa, xb, err_msg=g.name)
                else:
                    assert xa == xb, g.name
        elif isinstance(va, np.ndarray) or isinstance(vb, np.ndarray):
            assert va is not None and vb is not None, f.name
            assert np.asarray(va).dtype == np.asarray(vb).dtype, f.name
            np.testing.assert_array_equal(va, vb, err_msg=f.name)  # NaN == NaN here
        else:
            assert va == vb, f.name


@pytest.mark.parametrize(
    "make",
    [
        lambda: make_solution(),
        lambda: fitted_solution(order=1, residuals=True),
        lambda: fitted_solution(order=0, residuals=False),
    ],
    ids=["constant-direct", "legendre1-residuals", "constant-fitted"],
)
def test_exact_round_trip(tmp_path, make):
    sol = make()
    path = write_solution(sol, tmp_path / "sol.h5")
    back = read_solution(path)
    assert_same_solution(sol, back)
    # derived quantities follow exactly
    for name in ("G", "abs_g", "n", "Trxr", "sigma_G", "sigma_n", "sigma_Trxr", "reduced_chi2"):
        np.testing.assert_array_equal(getattr(back, name), getattr(sol, name), err_msg=name)
    assert back.describe() == sol.describe()


def test_layout_holds_every_array_and_legends(tmp_path):
    sol = fitted_solution(order=1, residuals=True)
    path = write_solution(sol, tmp_path / "sol.h5")
    with h5py.File(path, "r") as h5:
        assert h5.attrs["format"] == FORMAT
        assert h5.attrs["autocal_version"] == autocal.__version__
        for name in (
            "antennas",
            "antenna_names",
            "pols",
            "freqs",
            "lsts",
            "jds",
            "coeffs",
            "cov",
            "chi2",
            "dof",
            "count",
            "nflagged",
            "flag_reason",
            "residuals",
        ):
            assert name in h5, name
        for name in ("G", "abs_g", "n", "Trxr", "sigma_G", "sigma_abs_g", "sigma_n"):
            np.testing.assert_array_equal(h5["derived"][name][()], getattr(sol, name))
        np.testing.assert_array_equal(h5["derived/sigma_Trxr"][()], sol.sigma_Trxr)
        np.testing.assert_array_equal(h5["derived/flags"][()], sol.flags)
        assert h5["derived/Trxr"].attrs["units"] == "K"
        legend = json.loads(h5["flag_reason"].attrs["legend"])
        assert legend == {str(k): v for k, v in FLAG_REASONS.items()}
        assert json.loads(h5["coeffs"].attrs["parameters"]) == ["g_0", "g_1", "n_0", "n_1"]
        assert h5["model"].attrs["kind"] == "legendre" and h5["model"].attrs["order"] == 1
        assert "Legendre" in h5["model"].attrs["description"]
        assert json.loads(h5.attrs["config"]) == sol.config
    assert sol.flag_reason[0, 0, 5] == 1  # the fully flagged channel, kept as NaN
    assert np.isnan(read_solution(path).G[0, 0, 5])


def test_provenance_records_inputs_and_conventions(tmp_path):
    data_file = tmp_path / "input.uvh5"
    data_file.write_bytes(b"some observation")
    sol = make_solution(
        config={
            "inputs": [str(data_file), "/nonexistent/file.uvh5"],
            "cmb": "added once (2.725 K)",
            "tgnd_K": 300.0,
            "array": np.arange(3),
        }
    )
    path = write_solution(sol, tmp_path / "sol.h5", provenance={"job": "42"})
    prov = read_provenance(path)
    assert prov["autocal_version"] == autocal.__version__
    assert prov["job"] == "42"
    assert prov["software"]["pyuvdata"]
    from autocal.core.files import file_checksum

    assert prov["inputs"][0] == {"path": str(data_file), "sha256": file_checksum(data_file)}
    assert prov["inputs"][1] == {"path": "/nonexistent/file.uvh5"}
    conv = prov["conventions"]
    assert conv["sky"] == "gsm2008" and conv["beam"] == "hera"
    assert conv["cmb"].startswith("added once") and conv["tgnd_K"] == 300.0
    assert prov["model"]["kind"] == "constant"
    # numpy values in the configuration are stored as JSON lists
    assert read_solution(path).config["array"] == [0, 1, 2]


def test_refuses_overwrite_and_is_atomic(tmp_path, monkeypatch):
    sol = make_solution()
    path = write_solution(sol, tmp_path / "sol.h5")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite"):
        write_solution(sol, path)

    def boom(*args, **kwargs):
        raise RuntimeError("interrupted")

    monkeypatch.setattr(products, "_write_strings", boom)
    with pytest.raises(RuntimeError, match="interrupted"):
        write_solution(sol, path, overwrite=True)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["sol.h5"]
    monkeypatch.undo()
    other = make_solution(flagged=(0, 1))
    write_solution(other, path, overwrite=True)
    assert_same_solution(read_solution(path), other)


def test_errors_name_the_problem(tmp_path):
    with pytest.raises(ProductFormatError, match="does not exist"):
        read_solution(tmp_path / "missing.h5")
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(ProductFormatError, match="not an HDF5 file"):
        read_solution(text)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as h5:
        h5.attrs["format"] = "autocal-tsky-1"
    with pytest.raises(ProductFormatError, match="autocal-tsky-1"):
        read_solution(other)
    from autocal.io.calsol_write import write_calh5

    cal = write_calh5(make_solution(), tmp_path / "gains.calh5")
    with pytest.raises(ProductFormatError, match="calh5"):
        read_solution(cal)
    good = write_solution(make_solution(), tmp_path / "good.h5")
    cut = tmp_path / "cut.h5"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ProductFormatError, match=r"truncated or corrupt|not an HDF5"):
        read_solution(cut)
    broken = tmp_path / "broken.h5"
    broken.write_bytes(good.read_bytes())
    with h5py.File(broken, "a") as h5:
        del h5["cov"]
    with pytest.raises(ProductFormatError, match="cov"):
        read_solution(broken)
    assert issubclass(ProductFormatError, ValueError)


def test_pipeline_style_configuration_is_searched(tmp_path):
    """autocal.pipeline.calibrate stores {"calibration": settings, "provenance": conventions}."""
    from autocal.core.sites import HERA

    config = {
        "calibration": {"inputs": ["/data/a.uvh5"], "sky": "gsm2008", "beam": "hera"},
        "provenance": {
            "inputs": {"/data/a.uvh5": "ab" * 32},
            "sky": {"model": "gsm2008", "cmb": "added"},
            "beam": {"beam": "uvbeam_healpix", "file": "HERA.beamfits"},
            "site": HERA.describe(),
            "tgnd_K": 300.0,
            "cmb": "2.725 K added once",
        },
    }
    sol = replace(make_solution(), config=config)
    prov = read_provenance(write_solution(sol, tmp_path / "sol.h5"))
    assert prov["inputs"] == [{"path": "/data/a.uvh5", "sha256": "ab" * 32}]
    conv = prov["conventions"]
    assert conv["sky"] == {"model": "gsm2008", "cmb": "added"}  # resolved beats requested
    assert conv["site"]["name"] == "hera" and conv["cmb"] == "2.725 K added once"
    assert conv["beam"]["file"] == "HERA.beamfits" and conv["tgnd_K"] == 300.0
    assert read_solution(tmp_path / "sol.h5").config == config
