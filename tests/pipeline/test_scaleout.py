"""Streaming within files, data read once, and the Dask scale-out (autocal.pipeline.scaleout)."""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

import autocal.pipeline.passes
import autocal.pipeline.scaleout
from autocal.cli.main import main
from autocal.core.coords import night_epoch
from autocal.fit.passes import fit
from autocal.io.uvh5 import read_uvh5
from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_chunks import ReadStats
from autocal.io.uvh5_meta import scan_uvh5
from autocal.io.uvh5_writer import UVH5AutosWriter
from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig, PipelineError, read_selection
from autocal.pipeline.decoded import BUDGET_ENV
from autocal.pipeline.partials import PartialSpec, compute_partial
from autocal.pipeline.passes import PassesResult
from autocal.pipeline.products import waterfall_residuals
from autocal.pipeline.sources import open_source
from autocal.simulate.mock import SimulationConfig, simulate
from autocal.tsky.compute import compute_tsky

#: dnu dt of the noise = 1e6: data-derived weights bias G by 2e-6, so one pass.
SIM = SimulationConfig(
    beam="dipole",
    antennas=[0, 1, 2],
    pols=["ee", "nn"],
    channel_width_khz=4000.0,
    duration_h=6.0,
    cadence_s=600.0,
    noise_dnu_hz=1e6,
    nside=16,
    seed=3,
)
NSIDE = 16


@pytest.fixture(scope="module")
def night(tmp_path_factory) -> Iterator[list[Path]]:
    """Three consecutive files written in parts (shuffle + gzip), 12 integrations each.

    The module shares a private Tsky cache: every run computes the same table.
    """
    folder = tmp_path_factory.mktemp("scaleout")
    saved = os.environ.get("AUTOCAL_CACHE_DIR")
    os.environ["AUTOCAL_CACHE_DIR"] = str(folder / "tsky-cache")
    obs, _ = simulate(SIM)
    paths = []
    for i in range(3):
        window = slice(12 * i, 12 * (i + 1))
        path = folder / f"zen.part{i}.uvh5"
        with UVH5AutosWriter(
            path,
            freqs=obs.freqs,
            channel_width=obs.channel_width,
            jds=obs.jds[window],
            lsts=obs.lsts[window],
            integration_time=obs.integration_time[window],
            antennas=obs.antennas,
            pols=obs.pols,
            site=obs.site,
            compression="gzip",
        ) as writer:
            for start in range(0, 12, 5):
                part = slice(12 * i + start, 12 * i + min(start + 5, 12))
                writer.write(start, obs.data[:, :, part], nsamples=obs.nsamples[:, :, part])
        paths.append(path)
    yield paths
    if saved is None:
        os.environ.pop("AUTOCAL_CACHE_DIR", None)
    else:
        os.environ["AUTOCAL_CACHE_DIR"] = saved


def _config(paths: list[Path], **kwargs) -> CalibrationConfig:
    kwargs.setdefault("products", ["hdf5"])
    return CalibrationConfig(inputs=[str(p) for p in paths], beam="dipole", nside=NSIDE, **kwargs)


def test_block_streaming_equals_whole_file_reading(night, tmp_path) -> None:
    whole = read_uvh5(night)
    blocks = [b for f in scan_uvh5(night) for b in iter_uvh5_blocks(f, block_size=5)]
    assert [b.ntime for b in blocks] == [5, 5, 2] * 3
    for key in ("data", "flags", "nsamples"):
        np.testing.assert_array_equal(
            np.concatenate([getattr(b, key) for b in blocks], axis=2), getattr(whole, key)
        )
    np.testing.assert_array_equal(np.concatenate([b.lsts for b in blocks]), whole.lsts)

    streamed = run_calibration(_config(night), tmp_path / "blocks", block_size=2).solution
    filewise = run_calibration(_config(night), tmp_path / "auto").solution
    tsky = np.stack(
        [
            compute_tsky(
                "gsm2008",
                "dipole",
                whole.site,
                whole.freqs,
                whole.lsts,
                nside=NSIDE,
                epoch=night_epoch(whole.jds, whole.site.lon_deg),
                pol=p,
            ).tsky
            for p in whole.pols
        ]
    )
    in_memory = fit(whole, tsky, passes=1)
    # the in-memory fit sees the data's own flags only: so does this streamed run
    unflagged = run_calibration(
        _config(night, rfi_flagging=False), tmp_path / "off", block_size=2
    ).solution
    # flagging before the fit does not depend on the block size either
    for mine, other in ((streamed, filewise), (unflagged, in_memory)):
        np.testing.assert_allclose(mine.coeffs, other.coeffs, rtol=1e-10, atol=0)
        # chi2 = yty - 2 x.aty + x.ata.x from sums: cancellation costs digits
        np.testing.assert_allclose(mine.chi2, other.chi2, rtol=1e-5, atol=0)
    np.testing.assert_allclose(streamed.cov, filewise.cov, rtol=1e-6, atol=0)


def test_block_memory_is_bounded_by_the_block(night) -> None:
    file = scan_uvh5(night[:1])[0]
    nant, npol, nfreq = len(file.antennas), len(file.pols), file.freqs.size
    itemsize = 8  # complex64 written by UVH5AutosWriter
    sizes = {}
    for block in (1, 4, 12):
        stats = ReadStats()
        for _ in iter_uvh5_blocks(file, block_size=block, stats=stats):
            pass
        sizes[block] = stats.largest_array
        assert stats.largest_array == block * nant * nfreq * npol * itemsize
        assert stats.integrations == 12 and stats.blocks == -(-12 // block)
    assert sizes[1] < sizes[4] < sizes[12]
    # the automatic block size follows the value budget
    stats = ReadStats()
    blocks = list(iter_uvh5_blocks(file, max_block_samples=3 * nant * npol * nfreq, stats=stats))
    assert [b.ntime for b in blocks] == [3, 3, 3, 3]
    assert stats.largest_array == 3 * nant * nfreq * npol * itemsize
    with pytest.raises(ValueError, match="block_size"):
        next(iter_uvh5_blocks(file, block_size=0))


def test_data_are_read_once_and_the_waterfall_needs_no_second_read(
    night, tmp_path, monkeypatch
) -> None:
    monkeypatch.setattr(
        autocal.pipeline.passes, "MAX_WATERFALL_ROWS", 10
    )  # 36 integrations -> bins
    # the fit's own passes; flagging before the fit reads the data twice more (off here);
    # streamed: no decoded blocks kept between reads (autocal.pipeline.decoded)
    monkeypatch.setenv(BUDGET_ENV, "0")
    config = _config(night, products=["hdf5", "png"], rfi_flagging=False)
    result = run_calibration(config, tmp_path / "out", block_size=4)
    execution = result.summary["execution"]
    io = execution["io"]
    disk = sum(p.stat().st_size for p in night)
    stored = 0  # compressed bytes of the three data sets (the rest is the header)
    for path in night:
        with h5py.File(path, "r") as h5:
            stored += sum(h5["Data"][k].id.get_storage_size() for k in h5["Data"])
    assert execution["passes"] == 1 and result.summary["provenance"]["passes"] == 1
    assert stored <= io["bytes_read"] <= disk  # every data chunk once, nothing twice
    assert io["checksum_bytes"] == disk
    assert io["integrations"] == 36 and io["files"] == 3
    assert (tmp_path / "out" / "residuals.png").stat().st_size > 0

    # a second, model-weighted pass reads everything twice
    twice = run_calibration(
        _config(night, passes=2, rfi_flagging=False), tmp_path / "two", block_size=4
    )
    assert twice.summary["execution"]["io"]["bytes_read"] == pytest.approx(
        2 * io["bytes_read"], rel=0.01
    )
    # unless the observation fits in memory: then the second pass replays the first's blocks
    monkeypatch.setenv(BUDGET_ENV, "1")
    kept = run_calibration(
        _config(night, passes=2, rfi_flagging=False), tmp_path / "kept", block_size=4
    )
    kept_io = kept.summary["execution"]["io"]
    assert kept_io["bytes_read"] == io["bytes_read"] and kept_io["files"] == 3
    assert kept_io["blocks_from_memory"] == kept_io["blocks"] == io["blocks"]
    for name in ("coeffs", "cov", "chi2", "count"):
        np.testing.assert_array_equal(getattr(kept.solution, name), getattr(twice.solution, name))


def test_waterfall_rows_are_the_normalised_residuals(night, tmp_path) -> None:
    result = run_calibration(_config(night), tmp_path / "out", block_size=5)
    run = PassesResult(
        result.solution, None, None, 1, 1, result.solution.antennas, (), {}, {}
    )  # only .waterfall and .bin_size are used below
    spec = PartialSpec(
        result.solution.model,
        "radiometer",
        read_selection(_config(night)),
        2,
        1,
    )
    source = open_source(_config(night))
    whole = read_uvh5(night)
    tsky = np.stack(
        [
            compute_tsky(
                "gsm2008",
                "dipole",
                whole.site,
                whole.freqs,
                whole.lsts,
                nside=NSIDE,
                epoch=night_epoch(whole.jds, whole.site.lon_deg),
                pol=p,
            ).tsky
            for p in whole.pols
        ]
    )
    partials = [compute_partial(spec, t) for t in source.tasks(tsky)]
    run.waterfall = np.concatenate([p.waterfall for p in partials], axis=2)
    labels, resid, lsts = waterfall_residuals(result.solution, run, _config(night), source.lsts)
    pred = result.solution.predict(tsky)[:2]
    expected = (whole.data[:2] - pred) * np.sqrt(whole.bandwidth_time()[:2]) / whole.data[:2]
    np.testing.assert_allclose(resid, expected.reshape(resid.shape), rtol=1e-9, atol=1e-9)
    assert labels == ["ant 0 ee", "ant 0 nn", "ant 1 ee", "ant 1 nn"]
    np.testing.assert_array_equal(lsts, whole.lsts)


def test_dask_local_cluster_equals_serial_bit_for_bit(night, tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(autocal.pipeline.scaleout, "LOCAL_PROCESSES", False)  # threads: quick
    monkeypatch.setenv(BUDGET_ENV, "0")  # the serial run decodes every read, as Dask does
    serial = run_calibration(_config(night), tmp_path / "serial", block_size=5)
    dask = run_calibration(
        _config(night), tmp_path / "dask", block_size=5, dask_scheduler="local", dask_workers=2
    )
    for name in ("coeffs", "cov", "chi2", "dof", "count", "nflagged", "flag_reason"):
        np.testing.assert_array_equal(getattr(dask.solution, name), getattr(serial.solution, name))
    execution = dask.summary["execution"]
    assert execution["executor"] == "dask" and execution["dask"]["workers"] == 2
    assert execution["io"]["bytes_read"] == serial.summary["execution"]["io"]["bytes_read"]
    assert dask.summary["provenance"]["inputs"] == serial.summary["provenance"]["inputs"]


def test_bad_scheduler_addresses_fail_clearly_without_hanging(night, tmp_path, monkeypatch):
    monkeypatch.setattr(autocal.pipeline.scaleout, "CONNECT_TIMEOUT_S", 1.0)
    start = time.perf_counter()
    with pytest.raises(
        PipelineError, match=r"cannot reach the Dask scheduler at tcp://127\.0\.0\.1:9"
    ):
        run_calibration(_config(night), tmp_path / "a", dask_scheduler="127.0.0.1:9")
    assert time.perf_counter() - start < 20
    for bad, message in [
        ("not-an-address", "not HOST:PORT"),
        ("http://127.0.0.1:8786", "unknown protocol"),
        ("   ", "empty"),
    ]:
        with pytest.raises(PipelineError, match=message):
            run_calibration(_config(night), tmp_path / "b", dask_scheduler=bad)
    monkeypatch.setattr(autocal.pipeline.scaleout, "WORKER_TIMEOUT_S", 1.0)
    from distributed import LocalCluster

    with (
        LocalCluster(n_workers=0, processes=True, host="127.0.0.1", dashboard_address=None) as c,
        pytest.raises(PipelineError, match="has no workers"),
    ):
        run_calibration(_config(night), tmp_path / "e", dask_scheduler=c.scheduler_address)
    with pytest.raises(PipelineError, match="at least 1"):
        run_calibration(_config(night), tmp_path / "c", dask_scheduler="local", dask_workers=0)
    with pytest.raises(PipelineError, match="block_size"):
        run_calibration(_config(night), tmp_path / "d", block_size=0)
    assert not (tmp_path / "a" / "summary.json").exists()


def test_cli_dask_options(night, tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(autocal.pipeline.scaleout, "CONNECT_TIMEOUT_S", 1.0)
    base = [
        "calibrate",
        *map(str, night),
        "--beam",
        "dipole",
        "--nside",
        str(NSIDE),
        "--products",
        "hdf5",
        "--out",
        str(tmp_path / "cli"),
    ]
    assert main([*base, "--dask", "not-an-address"]) == 2
    assert "not HOST:PORT" in capsys.readouterr().err
    assert main([*base, "--dask-workers", "2"]) == 2
    assert "--dask-workers needs --dask local" in capsys.readouterr().err
    assert main([*base, "--block-size", "0"]) == 2
    capsys.readouterr()
    assert main([*base, "--block-size", "7"]) == 0
    summary = json.loads((tmp_path / "cli" / "summary.json").read_text())
    io = summary["execution"]["io"]  # the fit's blocks replay the flagging's first read
    assert summary["execution"]["block_size"] == 7 and io["blocks"] + io["blocks_from_memory"] == 6


def test_local_workers_start_without_the_nannys_malloc_trim_setting(monkeypatch, caplog) -> None:
    """MALLOC_TRIM_THRESHOLD_ (Dask nanny default) makes every large array fault in afresh."""
    from distributed import LocalCluster

    from autocal.pipeline.scaleout import MALLOC_TRIM_ENV, _worker_malloc_env, dask_client

    # the nanny also sets it in the process that starts it: restore this one afterwards
    monkeypatch.setenv(MALLOC_TRIM_ENV, "0")
    monkeypatch.delenv(MALLOC_TRIM_ENV)
    with dask_client("local", 1) as executor:  # worker processes, as in production
        assert list(executor.client.run(_worker_malloc_env).values()) == [None]
        assert "worker_malloc_trim_threshold" not in executor.describe()
    with (
        LocalCluster(n_workers=1, processes=True, host="127.0.0.1", dashboard_address=None) as c,
        caplog.at_level(logging.WARNING, logger="autocal.pipeline.scaleout"),
        dask_client(c.scheduler_address) as executor,
    ):  # a cluster started with Dask's defaults, as `dask worker` does
        assert executor.describe()["worker_malloc_trim_threshold"] == ["65536"]
    assert "MALLOC_TRIM_THRESHOLD_=65536" in caplog.text and "--no-nanny" in caplog.text
