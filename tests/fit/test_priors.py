"""Receiver-temperature priors: numbers, CSV tables, previous solutions and their errors."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from autocal.fit.model import FitModel
from autocal.fit.priors import PriorError, TrxrPrior, parse_trxr_prior
from autocal.fit.solution import Solution
from autocal.io.products import write_solution

DATA_FREQS = np.linspace(120e6, 180e6, 13)


def write_csv(tmp_path: Path, text: str, name: str = "prior.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def make_solution(
    antennas: tuple[int, ...] = (0, 5, 9),
    pols: tuple[str, ...] = ("ee", "nn"),
    nfreq: int = 11,
    flagged: tuple[int, ...] = (4,),
) -> Solution:
    """A constant-model solution with Trxr depending on antenna, pol and channel."""
    freqs = np.linspace(100e6, 200e6, nfreq)
    nant, npol = len(antennas), len(pols)
    ia = np.arange(nant)[:, None, None]
    ip = np.arange(npol)[None, :, None]
    f = (freqs / 150e6)[None, None, :]
    gain = 0.02 * (1 + 0.1 * ia + 0.05 * ip) * f
    trxr = 100.0 + 10.0 * ia + 5.0 * ip + 40.0 * (f - 1)
    coeffs = np.stack([gain, gain * trxr], axis=-1)
    cov = np.zeros((nant, npol, nfreq, 2, 2))
    cov[..., 0, 0] = (0.01 * gain) ** 2
    cov[..., 1, 1] = (0.01 * gain * trxr) ** 2
    reason = np.zeros((nant, npol, nfreq), np.int64)
    reason[..., list(flagged)] = 2
    coeffs[reason != 0] = np.nan
    cov[reason != 0] = np.nan
    ntime = 4
    return Solution(
        model=FitModel(),
        antennas=np.array(antennas, dtype=np.int64),
        pols=pols,
        freqs=freqs,
        lsts=np.linspace(1.0, 2.0, ntime),
        jds=2458116.3 + np.arange(ntime) / 1440,
        coeffs=coeffs,
        cov=cov,
        chi2=np.ones((nant, npol, nfreq)),
        dof=np.full((nant, npol, nfreq), 2.0),
        count=np.full((nant, npol, nfreq), ntime, np.int64),
        nflagged=np.zeros((nant, npol, nfreq), np.int64),
        flag_reason=reason,
    )


# numbers ---------------------------------------------------------------------------------
@pytest.mark.parametrize("spec", [150, 150.0, "150", " 1.5e2 ", np.float32(150)])
def test_number_is_a_constant_prior(spec):
    prior = parse_trxr_prior(spec, sigma_k=20.0)
    assert prior.kind == "constant"
    assert prior.freqs_hz is None
    assert prior.antennas is None and prior.pols is None
    assert prior.source == "constant 150 K +- 20 K"
    mean, sigma = prior.at(DATA_FREQS, antennas=[0, 1, 2], pols=["ee", "nn"])
    assert mean.shape == sigma.shape == (3, 2, DATA_FREQS.size)
    assert np.all(mean == 150.0) and np.all(sigma == 20.0)
    mean[:] = 0  # a writable copy, the prior is unchanged
    assert prior.at(DATA_FREQS)[0].shape == (1, 1, DATA_FREQS.size)
    assert np.all(prior.at(np.array([1e6, 1e9]))[0] == 150.0)  # any frequency


def test_negative_constant_is_allowed():
    prior = parse_trxr_prior("-35", sigma_k=5)
    assert float(prior.trxr_k) == -35.0
    desc = prior.describe()
    assert desc["kind"] == "constant" and desc["band_mhz"] is None
    assert desc["trxr_median_k"] == -35.0 and desc["sigma_median_k"] == 5.0
    json.dumps(desc)


@pytest.mark.parametrize("spec", ["nan", "inf", float("-inf")])
def test_non_finite_number(spec):
    with pytest.raises(PriorError, match="give a finite temperature"):
        parse_trxr_prior(spec, sigma_k=20.0)


@pytest.mark.parametrize("sigma", [0.0, -1.0, float("nan"), float("inf")])
def test_sigma_argument_must_be_positive(sigma):
    with pytest.raises(PriorError, match="give a finite 1-sigma > 0 K"):
        parse_trxr_prior(150, sigma_k=sigma)


def test_prior_is_read_only():
    prior = parse_trxr_prior(150, sigma_k=20.0)
    with pytest.raises(AttributeError):
        prior.source = "x"  # type: ignore[misc]
    with pytest.raises(ValueError):
        prior.trxr_k[...] = 1.0


# tables ----------------------------------------------------------------------------------
def test_table_with_sigma_comments_and_whitespace(tmp_path):
    path = write_csv(
        tmp_path,
        "# receiver temperature from the lab\n"
        "#   measured 2024-01-01\n"
        "\n"
        " freq_mhz , trxr_k ,sigma_k \n"
        "100, 200, 10\n"
        " 150 ,100 , 30\n"
        "200,  -50,20\n",
    )
    prior = parse_trxr_prior(path, sigma_k=99.0)
    assert prior.kind == "table"
    np.testing.assert_array_equal(prior.freqs_hz, [100e6, 150e6, 200e6])
    # exact at the table points
    mean, sigma = prior.at(np.array([100e6, 150e6, 200e6]))
    np.testing.assert_array_equal(mean[0, 0], [200, 100, -50])
    np.testing.assert_array_equal(sigma[0, 0], [10, 30, 20])
    # linear between them
    mean, sigma = prior.at(np.array([125e6, 110e6, 175e6]), antennas=[1, 2], pols=["ee"])
    assert mean.shape == (2, 1, 3)
    np.testing.assert_allclose(mean[1, 0], [150, 180, 25])
    np.testing.assert_allclose(sigma[1, 0], [20, 14, 25])
    assert prior.source.startswith("table ") and "sha256 " in prior.source
    desc = prior.describe()
    assert desc["kind"] == "table" and desc["band_mhz"] == [100.0, 200.0]
    assert desc["trxr_median_k"] == 100.0 and desc["sigma_median_k"] == 20.0
    assert len(desc["sha256"]) == 64 and desc["sha256"] in desc["source"]
    json.dumps(desc)


def test_table_without_sigma_uses_default(tmp_path):
    path = write_csv(tmp_path, "freq_mhz,trxr_k\n100,150\n200,250\n")
    prior = parse_trxr_prior(path, sigma_k=20.0)
    mean, sigma = prior.at(DATA_FREQS)
    np.testing.assert_allclose(mean[0, 0], 150 + (DATA_FREQS / 1e6 - 100))
    assert np.all(sigma == 20.0)
    assert "sigma 20 K" in prior.source


def test_relative_path_and_base_dir(tmp_path):
    write_csv(tmp_path, "freq_mhz,trxr_k\n100,150\n200,250\n")
    prior = parse_trxr_prior("prior.csv", sigma_k=20.0, base_dir=tmp_path)
    assert "prior.csv" in prior.source
    with pytest.raises(PriorError, match="does not exist: check the path"):
        parse_trxr_prior("prior.csv", sigma_k=20.0, base_dir=tmp_path / "elsewhere")


def test_a_table_must_cover_the_data_band(tmp_path):
    path = write_csv(tmp_path, "freq_mhz,trxr_k\n120,150\n130,160\n170,200\n180,210\n")
    prior = parse_trxr_prior(path, sigma_k=20.0)
    mean, _ = prior.at(np.array([119.9995e6, 180.0005e6]))  # within 1 kHz: rounding
    np.testing.assert_array_equal(mean[0, 0], [150, 210])  # held at the edges
    with pytest.raises(
        PriorError,
        match=r"covers 120\.000-180\.000 MHz but the data span 110\.000-190\.000 MHz: give a "
        "table that covers the data band",
    ):
        prior.at(np.array([110e6, 150e6, 190e6]))
    with pytest.raises(PriorError, match=r"data span 150\.000-180\.100 MHz"):
        prior.at(np.array([150e6, 180.1e6]))


BAD_TABLES = [
    ("freq,trxr\n100,150\n200,150\n", r"line 1: header 'freq,trxr' is not 'freq_mhz,trxr_k'"),
    ("freq_mhz;trxr_k\n100;150\n", "line 1: header .* write one of these"),
    ("freq_mhz,trxr_k,sigma\n100,150,1\n", "line 1: header 'freq_mhz,trxr_k,sigma' is not"),
    ("# c\nfreq_mhz,trxr_k\n100,150\n150,nan\n", r"line 4: trxr_k is 'nan': give finite"),
    ("freq_mhz,trxr_k\n100,150\n150,inf\n", r"line 3: trxr_k is 'inf': give finite"),
    ("freq_mhz,trxr_k,sigma_k\n100,150,-inf\n", r"line 2: sigma_k is '-inf'"),
    ("freq_mhz,trxr_k\n100,150\nabc,150\n", r"line 3: freq_mhz 'abc' is not a number"),
    ("freq_mhz,trxr_k\n100,150\n150\n", r"line 3: 1 values, expected 2 \(freq_mhz,trxr_k\)"),
    (
        "freq_mhz,trxr_k\n100,150\n200,150\n150,150\n",
        r"line 4: frequency 150\.0 MHz does not increase \(previous 200\.0\): sort the rows",
    ),
    (
        "freq_mhz,trxr_k\n100,150\n150,150\n150,160\n",
        r"line 4: frequency 150\.0 MHz does not increase \(previous 150\.0\): sort the rows",
    ),
    ("freq_mhz,trxr_k\n100,150\n", r"1 data row\(s\), need at least two"),
    ("freq_mhz,trxr_k\n", r"0 data row\(s\), need at least two"),
    ("", "the file is empty: give a header"),
    ("# only a comment\n\n", "the file is empty"),
    ("freq_mhz,trxr_k,sigma_k\n100,150,0\n200,150,1\n", r"line 2: sigma_k 0 is not positive"),
    ("freq_mhz,trxr_k,sigma_k\n100,150,1\n200,150,-2\n", r"line 3: sigma_k -2 is not positive"),
    ("freq_mhz,trxr_k\n1e8,150\n2e8,150\n", r"line 2: frequency 1e\+08 looks like Hz: give .*MHz"),
    ("freq_mhz,trxr_k\n-100,150\n200,150\n", r"line 2: frequency -100 MHz is not positive"),
]


@pytest.mark.parametrize(("text", "message"), BAD_TABLES)
def test_bad_tables(tmp_path, text, message):
    path = write_csv(tmp_path, text)
    with pytest.raises(PriorError, match=r"^trxr prior .*prior\.csv: " + message):
        parse_trxr_prior(path, sigma_k=20.0)


def test_undecodable_table(tmp_path):
    path = tmp_path / "prior.csv"
    path.write_bytes(b"freq_mhz,trxr_k\n\xff\xfe\x00\n")
    with pytest.raises(PriorError, match="cannot read it as UTF-8 text"):
        parse_trxr_prior(path, sigma_k=20.0)


# files of the wrong kind -----------------------------------------------------------------
def test_unknown_extension(tmp_path):
    path = write_csv(tmp_path, "freq_mhz,trxr_k\n100,150\n200,150\n", name="prior.txt")
    with pytest.raises(PriorError, match=r"neither a number nor a \.csv, \.h5 or \.hdf5 file"):
        parse_trxr_prior(path, sigma_k=20.0)
    with pytest.raises(PriorError, match="neither a number"):
        parse_trxr_prior("warm", sigma_k=20.0)


@pytest.mark.parametrize("name", ["missing.csv", "missing.h5"])
def test_missing_file(tmp_path, name):
    with pytest.raises(PriorError, match=f"{name} does not exist: check the path"):
        parse_trxr_prior(tmp_path / name, sigma_k=20.0)


def test_directory(tmp_path):
    (tmp_path / "d.csv").mkdir()
    with pytest.raises(PriorError, match="is a directory"):
        parse_trxr_prior(tmp_path / "d.csv", sigma_k=20.0)


def test_empty_spec():
    with pytest.raises(PriorError, match="trxr prior is empty"):
        parse_trxr_prior("  ", sigma_k=20.0)


def test_garbage_hdf5(tmp_path):
    path = tmp_path / "solution.h5"
    path.write_bytes(b"\x89HDF garbage")
    with pytest.raises(PriorError, match=r"not an HDF5 file \(truncated or corrupt\?\)"):
        parse_trxr_prior(path, sigma_k=20.0)


def test_truncated_hdf5(tmp_path):
    full = write_solution(make_solution(), tmp_path / "full.h5")
    data = full.read_bytes()
    path = tmp_path / "cut.hdf5"
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(PriorError, match="truncated, corrupt or incomplete solution file"):
        parse_trxr_prior(path, sigma_k=20.0)


def test_hdf5_of_another_kind(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as h5:
        h5["x"] = np.arange(3)
    with pytest.raises(PriorError, match="format None, not an autocal solution"):
        parse_trxr_prior(path, sigma_k=20.0)


# previous solutions ----------------------------------------------------------------------
@pytest.fixture
def solution_file(tmp_path):
    sol = make_solution()
    return sol, write_solution(sol, tmp_path / "solution.h5")


def test_solution_prior_equals_its_derived_trxr(solution_file):
    sol, path = solution_file
    prior = parse_trxr_prior(str(path), sigma_k=20.0)
    assert prior.kind == "solution"
    assert prior.antennas == (0, 5, 9) and prior.pols == ("ee", "nn")
    assert prior.trxr_k.shape == (3, 2, 11)
    assert prior.source.startswith("solution ") and "sha256" in prior.source
    ok = ~sol.flags
    mean, sigma = prior.at(sol.freqs)
    assert mean.shape == (3, 2, 11)
    np.testing.assert_array_equal(mean[ok], sol.Trxr[ok])
    np.testing.assert_array_equal(sigma[ok], sol.sigma_Trxr[ok])
    desc = prior.describe()
    assert desc["kind"] == "solution" and desc["antennas"] == [0, 5, 9]
    assert desc["band_mhz"] == [100.0, 200.0] and desc["nfreq"] == 11
    json.dumps(desc)


def test_solution_prior_skips_flagged_channels(solution_file):
    sol, path = solution_file
    prior = parse_trxr_prior(path, sigma_k=20.0)
    assert np.all(np.isnan(prior.trxr_k[..., 4]))
    mean, sigma = prior.at(sol.freqs[3:6])
    # channel 4 is flagged: linear between its neighbours
    expect = 0.5 * (sol.Trxr[..., 3] + sol.Trxr[..., 5])
    np.testing.assert_allclose(mean[..., 1], expect, rtol=1e-12)
    expect_s = 0.5 * (sol.sigma_Trxr[..., 3] + sol.sigma_Trxr[..., 5])
    np.testing.assert_allclose(sigma[..., 1], expect_s, rtol=1e-12)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(sigma))


def test_solution_prior_per_row_nan_and_edges(tmp_path):
    sol = make_solution(flagged=())
    path = write_solution(sol, tmp_path / "solution.h5")
    with h5py.File(path, "r+") as h5:  # NaN (not flagged) channels in one row only
        h5["derived/Trxr"][1, 0, 0] = np.nan
        h5["derived/sigma_Trxr"][1, 0, 6] = np.nan
    prior = parse_trxr_prior(path, sigma_k=20.0)
    mean, sigma = prior.at(sol.freqs, antennas=[5], pols=["ee"])
    row = sol.Trxr[1, 0]
    assert mean[0, 0, 0] == row[1]  # held beyond the outermost usable channel
    np.testing.assert_allclose(mean[0, 0, 6], 0.5 * (row[5] + row[7]), rtol=1e-12)
    np.testing.assert_array_equal(mean[0, 0, 1:6], row[1:6])
    srow = sol.sigma_Trxr[1, 0]
    np.testing.assert_allclose(sigma[0, 0, 6], 0.5 * (srow[5] + srow[7]), rtol=1e-12)
    assert sigma[0, 0, 0] == srow[1]
    # the other rows keep every channel
    np.testing.assert_array_equal(prior.at(sol.freqs, [0], ["ee"])[0][0, 0], sol.Trxr[0, 0])


def test_solution_prior_selects_antennas_and_pols(solution_file):
    _, path = solution_file
    prior = parse_trxr_prior(path, sigma_k=20.0)
    freqs = np.array([110e6, 150e6, 190e6])
    full, full_s = prior.at(freqs)
    mean, sigma = prior.at(freqs, antennas=np.array([9, 0]), pols=("NN",))
    assert mean.shape == (2, 1, 3)
    np.testing.assert_array_equal(mean[0, 0], full[2, 1])
    np.testing.assert_array_equal(mean[1, 0], full[0, 1])
    np.testing.assert_array_equal(sigma[0, 0], full_s[2, 1])


def test_solution_prior_missing_antenna_or_pol(solution_file):
    _, path = solution_file
    prior = parse_trxr_prior(path, sigma_k=20.0)
    with pytest.raises(PriorError, match=r"antenna\(s\) 7, 8 not in the file, which has "):
        prior.at(DATA_FREQS, antennas=[0, 7, 8])
    with pytest.raises(PriorError, match="which has antennas 0, 5, 9"):
        prior.at(DATA_FREQS, antennas=[7])
    with pytest.raises(PriorError, match=r"polarisation\(s\) ne not in the file, which has ee, nn"):
        prior.at(DATA_FREQS, pols=["ne"])  # xx would be ee's other name (x east: HERA's)


def test_solution_prior_band(solution_file):
    _, path = solution_file
    prior = parse_trxr_prior(path, sigma_k=20.0)
    prior.at(np.array([95e6, 205e6]))  # within half a 10 MHz channel
    with pytest.raises(PriorError, match=r"covers 100\.000-200\.000 MHz .* give a solution"):
        prior.at(np.array([90e6, 150e6]))


def test_solution_row_without_solved_channel(tmp_path):
    sol = make_solution()
    path = write_solution(sol, tmp_path / "solution.h5")
    with h5py.File(path, "r+") as h5:
        h5["derived/Trxr"][2, 1, :] = np.nan
    prior = parse_trxr_prior(path, sigma_k=20.0)
    prior.at(DATA_FREQS, antennas=[0, 5], pols=["nn"])  # the dead row is not asked for
    with pytest.raises(PriorError, match="antenna 9 pol nn has no solved channel in the file"):
        prior.at(DATA_FREQS, antennas=[9], pols=["nn"])


def test_solution_without_any_solved_channel(tmp_path):
    sol = make_solution(flagged=tuple(range(11)))
    path = write_solution(sol, tmp_path / "solution.h5")
    with pytest.raises(PriorError, match="no solved channel in the file"):
        parse_trxr_prior(path, sigma_k=20.0)


def test_direct_construction_is_checked():
    with pytest.raises(PriorError, match="must have shape"):
        TrxrPrior("x", np.array([1e8, 2e8]), np.array([1.0]), np.array([1.0]))
    with pytest.raises(PriorError, match="at least two increasing"):
        TrxrPrior("x", np.array([2e8, 1e8]), np.ones(2), np.ones(2))
    with pytest.raises(PriorError, match="sigma_k > 0"):
        TrxrPrior("x", None, 150.0, 0.0)


def test_a_solution_of_pols_named_xx_yy_is_a_prior_for_ee_nn_data(solution_file):
    """A review (2026-11-29): runs now name a polarisation asked for as ``xx`` the way the
    file does (``ee``), so a solution of an earlier such run (pols ``xx``, ``yy``) must still
    serve as the prior of the same feeds (HERA's files: x east)."""
    _, path = solution_file
    prior = parse_trxr_prior(path, sigma_k=20.0)
    freqs = np.array([110e6, 150e6, 190e6])
    renamed = dataclasses.replace(
        prior, pols=tuple({"ee": "xx", "nn": "yy"}[p] for p in prior.pols)
    )
    for wanted, stored in (("ee", "xx"), ("nn", "yy")):
        mean, _ = renamed.at(freqs, pols=[wanted])
        np.testing.assert_array_equal(mean, prior.at(freqs, pols=[wanted])[0])
        assert renamed.at(freqs, pols=[stored])[0].shape == mean.shape
    with pytest.raises(PriorError, match="not in the file"):
        dataclasses.replace(prior, pols=("xy", "yx")).at(freqs, pols=["ee"])
    # only as HERA orients its feeds (x east): never the other feed's prior (a review)
    with pytest.raises(PriorError, match="not in the file"):
        dataclasses.replace(prior, pols=("xx", "ne")).at(freqs, pols=["nn"])
