"""``autocal simulate`` and ``autocal paper``; mock UVH5 files read like real data."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.cli.main import main
from autocal.fit.passes import fit
from autocal.io.simtruth import read_truth
from autocal.io.uvh5 import read_uvh5

ARGS = ["--beam", "dipole", "--duration", "8", "--channel-width", "1000", "--seed", "3"]


def test_simulate_writes_uvh5_that_the_loader_reads_and_the_fit_calibrates(
    tmp_path, capsys
) -> None:
    out = tmp_path / "mock.uvh5"
    status = main(["simulate", *ARGS, "--antennas", "0,11", "--pols", "ee,nn", "--out", str(out)])
    assert status == 0, capsys.readouterr().err
    assert "wrote" in capsys.readouterr().out
    obs = read_uvh5(out)
    truth = read_truth(tmp_path / "mock.truth.h5")
    assert obs.shape == (2, 2, 96, 81)
    assert obs.telescope_name == "HERA"
    np.testing.assert_allclose(obs.bandwidth_time(), 5e3, rtol=1e-6)
    np.testing.assert_allclose(obs.lsts, truth["lsts"], atol=1 / 3600)
    sol = fit(obs, truth["tsky"])
    pulls = (sol.G - truth["gain"].mean(0)) / sol.sigma_G
    assert np.all(np.abs(pulls) < 5)
    assert abs(np.mean(pulls)) < 0.3
    trxr_pulls = (sol.Trxr - truth["trxr"]) / sol.sigma_Trxr
    assert abs(np.std(trxr_pulls) - 1) < 0.25


def test_simulate_refuses_bad_arguments(tmp_path, capsys) -> None:
    out = tmp_path / "mock.uvh5"
    assert main(["simulate", *ARGS, "--out", str(tmp_path / "mock.h5")]) == 2
    assert ".uvh5" in capsys.readouterr().err
    assert main(["simulate", *ARGS, "--antennas", "0,x", "--out", str(out)]) == 2
    assert "integers" in capsys.readouterr().err
    assert main(["simulate", *ARGS, "--antennas", "9999", "--out", str(out)]) == 2
    assert "9999" in capsys.readouterr().err
    assert not out.exists()
    assert main(["simulate", *ARGS, "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["simulate", *ARGS, "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err


@pytest.mark.slow
def test_paper_quick_writes_table_and_figures(tmp_path, capsys) -> None:
    status = main(["paper", "--quick", "--beams", "dipole", "--out", str(tmp_path)])
    assert status == 0, capsys.readouterr().err
    text = capsys.readouterr().out
    assert "| Reference: truth = model | dipole |" in text
    assert (tmp_path / "paper_table.md").is_file()
    assert (tmp_path / "delay_spectra_dipole.png").is_file()
    assert main(["paper", "--beams", "nope", "--out", str(tmp_path)]) == 2
    assert "unknown" in capsys.readouterr().err
