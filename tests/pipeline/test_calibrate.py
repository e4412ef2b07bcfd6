"""End-to-end calibration of one observation (autocal.pipeline.calibrate, ``autocal calibrate``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from autocal.cli.main import main
from autocal.core.coords import night_epoch
from autocal.fit.passes import fit
from autocal.io.uvh5 import read_uvh5, write_uvh5
from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig, PipelineError
from autocal.simulate.mock import SimulationConfig, simulate
from autocal.tsky.compute import compute_tsky

SIM = SimulationConfig(
    beam="dipole",
    antennas=[0, 1],
    pols=["ee", "nn"],
    channel_width_khz=2000.0,
    duration_h=12.0,
    cadence_s=600.0,
    gain="a",
    seed=8,
)


@pytest.fixture(scope="module")
def night(tmp_path_factory) -> list[Path]:
    """A simulated 12 h observation written as three consecutive UVH5 files."""
    folder = tmp_path_factory.mktemp("night")
    obs, _ = simulate(SIM)
    paths = []
    for i, (lo, hi) in enumerate([(0.0, 3.99), (4.0, 7.99), (8.0, 12.0)]):
        paths.append(write_uvh5(obs.select(lst_range=(lo, hi)), folder / f"part{i}.uvh5"))
    return paths


def _in_memory(paths: list[Path], model: str, order: int) -> object:
    obs = read_uvh5(paths)
    tsky = np.stack(
        [
            compute_tsky(
                "gsm2008",
                "dipole",
                obs.site,
                obs.freqs,
                obs.lsts,
                pol=p,
                epoch=night_epoch(obs.jds, obs.site.lon_deg),
            ).tsky
            for p in obs.pols
        ]
    )
    return fit(obs, tsky, model=model, order=order, scale_covariance="inflate")


@pytest.mark.parametrize(("model", "order"), [("constant", 0), ("legendre", 1)])
def test_streamed_pipeline_equals_in_memory_fit(night, tmp_path, model, order) -> None:
    config = CalibrationConfig(
        inputs=[str(p) for p in night],
        beam="dipole",
        model=model,
        order=order,
        products=["png"],
        rfi_flagging=False,  # the in-memory fit below sees the data's own flags only
    )
    result = run_calibration(config, tmp_path / "out")
    expected = _in_memory(night, model, order)
    sol = result.solution
    np.testing.assert_allclose(sol.coeffs, expected.coeffs, rtol=1e-8, atol=1e-10)
    # the total uncertainty from the streamed block sums equals the in-memory one
    assert sol.total is not None and expected.total is not None
    assert sol.total.nblocks == expected.total.nblocks == 10
    np.testing.assert_allclose(sol.total.cov, expected.total.cov, rtol=1e-4)
    np.testing.assert_allclose(sol.sigma_G, expected.sigma_G, rtol=1e-4)
    assert result.summary["provenance"]["passes"] == 2  # dnu dt = 5e3: reweighting matters
    assert sol.pols == ("ee", "nn") and sol.antennas.tolist() == [0, 1]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["solution"]["ntime"] == 72
    assert len(summary["provenance"]["inputs"]) == 3
    stages = {"scan_s", "tsky_s", "flagging_s", "fit_s", "solve_s", "products_s", "total_s"}
    assert set(summary["timings_s"]) == set(summary["cpu_s"]) == stages
    assert summary["cpu_s"]["total_s"] >= summary["cpu_s"]["fit_s"] > 0
    for name in ("solution.png", "residuals.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    if model == "legendre":
        # the order-1 model recovers drift (a): G(t) within its errors
        ev = sol.evaluate()
        truth = 1 - 0.1 * (sol.lsts / 12 - 1)
        pull = (ev["G"] - truth[None, None, :, None]) / ev["sigma_G"]
        assert np.median(np.abs(pull)) < 1.5


def test_selection_and_failed_run_leave_no_products(night, tmp_path, monkeypatch) -> None:
    import autocal.pipeline.products

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(autocal.pipeline.products, "plot_residuals", broken)
    config = CalibrationConfig(
        inputs=[str(p) for p in night],
        beam="dipole",
        antennas=[1],
        pols=["nn"],
        freq_range_mhz=(130.0, 170.0),
        lst_range_h=(2.0, 9.0),
        products=["png"],
    )
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="disk full"):
        run_calibration(config, out)
    assert list(out.iterdir()) == []


def test_selection_is_applied(night, tmp_path) -> None:
    config = CalibrationConfig(
        inputs=[str(p) for p in night],
        beam="dipole",
        antennas=[1],
        pols=["nn"],
        freq_range_mhz=(130.0, 170.0),
        lst_range_h=(2.0, 9.0),
        products=[],
    )
    sol = run_calibration(config, tmp_path / "sel").solution
    assert sol.antennas.tolist() == [1] and sol.pols == ("nn",)
    assert sol.freqs.min() >= 130e6 and sol.freqs.max() <= 170e6
    assert sol.lsts.min() >= 2.0 and sol.lsts.max() <= 9.0


def test_bad_configuration_is_refused(night, tmp_path) -> None:
    with pytest.raises(ValidationError, match="MHz"):
        CalibrationConfig(inputs=["x"], freq_range_mhz=(110e6, 190e6))
    with pytest.raises(ValidationError, match="extra"):
        CalibrationConfig(inputs=["x"], bogus=1)
    with pytest.raises(PipelineError, match="not found"):
        run_calibration(CalibrationConfig(inputs=[str(tmp_path / "nope.uvh5")]), tmp_path / "o")
    with pytest.raises(PipelineError, match="LST range"):
        run_calibration(
            CalibrationConfig(inputs=[str(night[0])], beam="dipole", lst_range_h=(20.0, 21.0)),
            tmp_path / "o",
        )


def test_cli_calibrate(night, tmp_path, capsys) -> None:
    out = tmp_path / "cli"
    args = [
        "calibrate",
        *map(str, night),
        "--beam",
        "dipole",
        "--products",
        "png",
        "--out",
        str(out),
    ]
    assert main(args) == 0, capsys.readouterr().err
    assert "median_Trxr_K" in capsys.readouterr().out
    assert (out / "summary.json").is_file()
    assert main(["calibrate", str(night[0]), "--freq-range", "110", "--out", str(out)]) == 2
    assert "LOW:HIGH" in capsys.readouterr().err
    assert main(["calibrate", str(night[0]), "--products", "fits", "--out", str(out)]) == 2
    assert "products" in capsys.readouterr().err


def test_cli_passes_and_error_scaling_reach_the_run(night, tmp_path, capsys) -> None:
    """``--passes`` and ``--no-inflate-errors`` change what the run does, not just its config."""
    common = [*map(str, night), "--beam", "dipole", "--nside", "32", "--products", "hdf5"]
    runs = {}
    for name, extra in {
        "auto": [],
        "one": ["--passes", "1", "--no-inflate-errors"],
    }.items():
        assert main(["calibrate", *common, *extra, "--out", str(tmp_path / name)]) == 0
        runs[name] = json.loads((tmp_path / name / "summary.json").read_text())
    capsys.readouterr()
    # the simulation's dnu dt N makes data weights bias G by > 1e-5: auto makes two passes
    assert runs["auto"]["provenance"]["passes"] == 2
    assert runs["one"]["provenance"]["passes"] == 1
    assert runs["one"]["config"]["passes"] == 1
    assert runs["auto"]["provenance"]["errors"] == "covariance x max(1, chi2/dof)"
    assert runs["one"]["provenance"]["errors"] == "covariance"
    assert runs["one"]["config"]["inflate_errors"] is False


def test_miriad_input(data_root, tmp_path) -> None:
    folder = data_root / "hera" / "autos"
    inputs = sorted(str(p) for p in folder.glob("zen.2458099.*.uvOR_36x_auto_only"))
    config = CalibrationConfig(inputs=inputs, products=[], nside=32)
    sol = run_calibration(config, tmp_path / "m").solution
    assert sol.antennas.tolist() == [36] and sol.lsts.size == 180
    solved = ~sol.flags
    assert solved.sum() > 500  # the rest: flagged channels and non-positive gains
    assert np.all(np.isfinite(sol.sigma_Trxr[solved]))


@pytest.mark.slow
def test_edges_raw_files_calibrate_to_the_receiver_solution(data_root, tmp_path) -> None:
    """An EDGES-like day written as raw ACQ switch powers, calibrated by the pipeline."""
    from autocal.edges.noise_waves import expected_auto_model
    from autocal.edges.simulated_day import simulate_edges_day
    from autocal.edges.solutions import load_receiver_solution

    receiver = load_receiver_solution("edges2-lowband-2015")
    day = simulate_edges_day(tmp_path / "raw", solution=receiver, n_times=48, seed=5)
    config = CalibrationConfig(
        inputs=[str(p) for p in day.paths],
        beam="edges-low",
        sky="powerlaw:gsm2008@408:-2.55",
        freq_range_mhz=(50.0, 100.0),
        products=[],
    )
    sol = run_calibration(config, tmp_path / "cal").solution
    assert sol.pols == ("ee",) and sol.lsts.size == 48
    expected = expected_auto_model(receiver, 0.0, "q")
    pull_g = (sol.G[0, 0] - np.interp(sol.freqs, expected.freqs, expected.G)) / sol.sigma_G[0, 0]
    pull_t = (
        sol.Trxr[0, 0] - np.interp(sol.freqs, expected.freqs, expected.trxr)
    ) / sol.sigma_Trxr[0, 0]
    for pull in (pull_g, pull_t):
        assert abs(np.mean(pull)) < 0.3
        assert 0.75 < np.std(pull) < 1.25


def test_cli_calibrates_edges_p0_with_a_chosen_binning(data_root, tmp_path, capsys) -> None:
    """``--format edges --edges-r p0 --edges-bin N``: the raw power, N native channels a bin."""
    from autocal.edges.simulated_day import simulate_edges_day
    from autocal.io.products import read_solution

    day = simulate_edges_day(
        tmp_path / "raw", n_times=12, nside=32, n_files=2, bin_factor=128, file_format="hdf5"
    )
    out = tmp_path / "cal"
    argv = ["calibrate", *map(str, day.paths), "--format", "edges", "--beam", "edges-low"]
    argv += ["--sky", day.config["sky"], "--nside", "32", "--freq-range", "50:100"]
    argv += ["--edges-r", "p0", "--edges-bin", "128", "--products", "hdf5", "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err
    sol = read_solution(out / "solution.h5")
    np.testing.assert_allclose(sol.freqs, day.freqs)  # 128 native channels per bin
    expected = day.expected["p0"]
    pull = (sol.Trxr[0, 0] - np.interp(sol.freqs, expected.freqs, expected.trxr)) / sol.sigma_Trxr[
        0, 0
    ]
    assert abs(np.median(pull)) < 0.5 and 0.6 < np.std(pull) < 1.4  # seeds 0-2: 0.19, 0.94
    # the default (Q) calibrates the same files to a different receiver temperature
    q_trxr = np.interp(sol.freqs, day.expected["q"].freqs, day.expected["q"].trxr)
    assert np.all(np.abs(sol.Trxr[0, 0] - q_trxr) > 10 * sol.sigma_Trxr[0, 0])


def test_radiometer_bandwidth_time_is_shared_when_nsamples_are_uniform() -> None:
    import dataclasses

    from autocal.pipeline.partials import bandwidth_time

    obs, _ = simulate(SIM)
    full = obs.bandwidth_time()
    bt = bandwidth_time(obs)
    assert bt.shape == (obs.ntime, obs.nfreq)
    np.testing.assert_array_equal(np.broadcast_to(bt, full.shape), full)
    nsamples = np.array(obs.nsamples)
    nsamples[0, 0, 2, 3] *= 0.5  # one sample with half the integration
    varied = dataclasses.replace(obs, nsamples=nsamples)
    np.testing.assert_array_equal(bandwidth_time(varied), varied.bandwidth_time())


def test_edges_options_on_uvh5_input_are_reported(night, tmp_path, caplog) -> None:
    """A HERA user passing an EDGES-only option is told that it has no effect."""
    config = CalibrationConfig(
        inputs=[str(night[0])], beam="dipole", nside=32, products=[], edges_bin=128
    )
    with caplog.at_level("WARNING", logger="autocal.pipeline.sources"):
        run_calibration(config, tmp_path / "o")
    assert "edges_bin=128: options of EDGES spectra, ignored for uvh5 input" in caplog.text
    caplog.clear()
    dumped = CalibrationConfig(**config.model_dump(mode="json") | {"edges_bin": 64})
    with caplog.at_level("WARNING", logger="autocal.pipeline.sources"):
        run_calibration(dumped, tmp_path / "o2")  # every field set, all at their defaults
    assert "EDGES" not in caplog.text


def test_observations_of_one_night_share_the_tsky_cache(night, tmp_path, monkeypatch) -> None:
    """The night's second observation takes its Tsky from the first one's cache entries."""
    import autocal.tsky.compute as tsky_module

    monkeypatch.setenv("AUTOCAL_CACHE_DIR", str(tmp_path / "cache"))
    config = {"beam": "dipole", "products": ["hdf5"], "passes": 1}
    first = run_calibration(CalibrationConfig(inputs=[str(night[0])], **config), tmp_path / "a")
    assert len(list((tmp_path / "cache").glob("*.h5"))) == 2  # one per polarisation

    def engine(*args, **kwargs):
        raise AssertionError("the second observation recomputed Tsky")

    monkeypatch.setattr(tsky_module, "tsky_harmonics", engine)
    second = run_calibration(CalibrationConfig(inputs=[str(night[1])], **config), tmp_path / "b")
    epochs = [r.summary["provenance"]["epoch_jd"] for r in (first, second)]
    obs = read_uvh5(night[1])
    assert epochs[0] == epochs[1] == night_epoch(obs.jds, obs.site.lon_deg)


def test_radiometer_weights_need_positive_bandwidth_time_where_data_are_used(tmp_path) -> None:
    """An integration with no integration time may be read only if every antenna-pol is
    flagged there (the shared (time, channel) dnu dt is checked against the block's flags
    as if broadcast to it); otherwise radiometer weights are refused with advice."""
    import dataclasses

    import h5py

    obs, _ = simulate(SIM.model_copy(update={"duration_h": 2.0}))
    flags = np.array(obs.flags)
    flags[:, :, 3] = True

    def write(flags: np.ndarray, name: str) -> Path:
        path = write_uvh5(dataclasses.replace(obs, flags=flags), tmp_path / name)
        with h5py.File(path, "r+") as f:  # a file with a dead integration (our writer refuses)
            times = f["Header/time_array"][:]
            f["Header/integration_time"][times == np.unique(times)[3]] = 0.0
        return path

    good = write(flags, "flagged.uvh5")
    result = run_calibration(
        CalibrationConfig(inputs=[str(good)], products=["hdf5"]), tmp_path / "a"
    )
    assert result.solution.count.max() == obs.ntime - 1
    flags[1, 0, 3] = False  # one antenna-pol uses the integration
    bad = write(flags, "used.uvh5")
    with pytest.raises(PipelineError, match="positive channel width, integration time"):
        run_calibration(CalibrationConfig(inputs=[str(bad)], products=["hdf5"]), tmp_path / "b")
    assert not (tmp_path / "b" / "solution.h5").exists()


BAD_PRIORS = [
    ("freq,trxr\n100,150\n200,150\n", "header 'freq,trxr' is not"),
    ("freq_mhz,trxr_k\n100,150\n150,nan\n", "trxr_k is 'nan'"),
    ("freq_mhz,trxr_k\n100,150\n150,150\n140,150\n", "does not increase"),
    ("freq_mhz,trxr_k\n120,150\n180,150\n", "give a table that covers the data band"),
]


@pytest.mark.parametrize(("text", "message"), BAD_PRIORS)
def test_cli_refuses_a_bad_prior_table_and_writes_nothing(
    night, tmp_path, capsys, text, message
) -> None:
    table = tmp_path / "prior.csv"
    table.write_text(text)
    out = tmp_path / "out"
    args = ["calibrate", *map(str, night), "--beam", "dipole", "--out", str(out)]
    assert main([*args, "--trxr-prior", str(table)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists()


def test_a_prior_table_reaches_the_fit(night, tmp_path, capsys) -> None:
    """A per-frequency table is interpolated onto the channels and tightens Trxr to it."""
    table = tmp_path / "prior.csv"
    table.write_text("# the simulated receiver\nfreq_mhz,trxr_k,sigma_k\n100,150,2\n200,150,2\n")
    out = tmp_path / "with"
    # the night's gain drifts linearly: the order-1 model fits it, so data and prior agree
    args = ["calibrate", *map(str, night), "--beam", "dipole", "--products", "hdf5"]
    args += ["--model", "legendre", "--order", "1"]
    assert main([*args, "--trxr-prior", str(table), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["provenance"]["trxr_prior"]["kind"] == "table"
    free = run_calibration(
        CalibrationConfig(
            inputs=[str(p) for p in night], beam="dipole", model="legendre", products=["hdf5"]
        ),
        tmp_path / "free",
    ).solution
    from autocal.io.products import read_solution

    held = read_solution(out / "solution.h5")
    # the prior pulls Trxr towards 150 K and shrinks its error below the prior's 2 K
    assert np.nanmedian(np.abs(held.Trxr - 150)) < np.nanmedian(np.abs(free.Trxr - 150)) + 0.5
    assert np.nanmedian(held.sigma_Trxr_stat) < 2.0


def test_a_per_time_calh5_too_large_for_memory_is_refused_before_reading(
    night, tmp_path, monkeypatch
) -> None:
    """A per-time calh5 larger than the memory (a constant model's needs 1 byte per gain
    value, the per-time flags): refused before any data are read, with what to do, and
    nothing written; hdf5 alone runs."""
    import autocal.pipeline.flag_partials
    import autocal.pipeline.partials
    import autocal.pipeline.products

    ntime = sum(read_uvh5([p]).ntime for p in night)
    per_value = autocal.pipeline.products.PER_TIME_BYTES_PER_VALUE[("calh5", True)]
    value_bytes = per_value * 2 * 2 * ntime
    nfreq = read_uvh5([night[0]]).nfreq
    need = value_bytes * nfreq
    monkeypatch.setattr(autocal.pipeline.products, "available_memory", lambda: 0.5 * need)

    def no_reading(*args, **kwargs):
        raise AssertionError("data were read before the refusal")

    for module in (autocal.pipeline.partials, autocal.pipeline.flag_partials):
        monkeypatch.setattr(module, "read_chunks", no_reading)
    config = CalibrationConfig(inputs=[str(p) for p in night], beam="dipole")
    out = tmp_path / "out"
    with pytest.raises(PipelineError, match=r"per-time calh5 .* calibrate the files one by one"):
        run_calibration(config, out)
    assert not out.exists() or list(out.iterdir()) == []
    monkeypatch.undo()
    monkeypatch.setattr(autocal.pipeline.products, "available_memory", lambda: 0.5 * need)
    hdf5_only = config.model_copy(update={"products": ["hdf5"]})
    run_calibration(hdf5_only, out)
    assert (out / "solution.h5").exists()
