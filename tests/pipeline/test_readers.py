"""Reader processes without Dask (autocal.pipeline.readers): the same flags and solution as
the in-process run and as Dask, bit for bit; clear errors for a dead worker or a corrupt
file; the automatic choice; the CLI's ``--readers``."""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import autocal.pipeline.readers
import autocal.pipeline.scaleout
from autocal.cli.main import main
from autocal.diagnosis.reading import read_observation
from autocal.errors import AutocalError
from autocal.io.uvh5_writer import UVH5AutosWriter
from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig, PipelineError
from autocal.pipeline.decoded import BUDGET_ENV
from autocal.pipeline.flagging import flag_observation, scan_flags
from autocal.pipeline.readers import ProcessReaders, process_readers, reader_count
from autocal.pipeline.sources import open_source
from autocal.simulate.mock import SimulationConfig, simulate
from tests.io.test_uvh5_integrity import _flip

SIM = SimulationConfig(
    beam="dipole",
    antennas=[0, 1, 2],
    pols=["ee", "nn"],
    channel_width_khz=4000.0,
    duration_h=6.0,
    cadence_s=600.0,
    noise_dnu_hz=1e6,
    nside=16,
    seed=5,
)
NSIDE = 16
#: Spikes ``(antenna, pol, integration, channel, factor)`` in every file, a broadband burst
#: ``(antenna, pol, integration, factor)`` and two rolled-off channels at the low end.
SPIKES = [(0, 0, 5, 10, 3.0), (1, 1, 14, 7, 2.0), (2, 0, 27, 16, 1.5), (0, 1, 33, 12, 4.0)]
BURST = (2, 1, 20, 1.3)
EDGE = 2


@pytest.fixture(scope="module")
def night(tmp_path_factory) -> Iterator[list[Path]]:
    """Three files of 12 integrations (gzip) with RFI in each; a private Tsky cache."""
    folder = tmp_path_factory.mktemp("readers")
    saved = os.environ.get("AUTOCAL_CACHE_DIR")
    os.environ["AUTOCAL_CACHE_DIR"] = str(folder / "tsky-cache")
    obs, _ = simulate(SIM)
    data = obs.data.copy()
    data[..., :EDGE] *= 0.02
    for a, p, t, f, factor in SPIKES:
        data[a, p, t, f] *= factor
    a, p, t, factor = BURST
    data[a, p, t] *= factor
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
            writer.write(0, data[:, :, window], nsamples=obs.nsamples[:, :, window])
        paths.append(path)
    yield paths
    if saved is None:
        os.environ.pop("AUTOCAL_CACHE_DIR", None)
    else:
        os.environ["AUTOCAL_CACHE_DIR"] = saved


def _config(paths: list[Path], **kwargs) -> CalibrationConfig:
    kwargs.setdefault("products", ["hdf5"])
    return CalibrationConfig(inputs=[str(p) for p in paths], beam="dipole", nside=NSIDE, **kwargs)


SOLUTION = ("coeffs", "cov", "chi2", "dof", "count", "nflagged", "flag_reason", "time_flags")


def test_reader_processes_equal_the_in_process_run_and_dask_bit_for_bit(
    night, tmp_path, monkeypatch
) -> None:
    monkeypatch.setattr(autocal.pipeline.scaleout, "LOCAL_PROCESSES", False)  # threads: quick
    messages: list[tuple[float, str]] = []
    monkeypatch.setenv(BUDGET_ENV, "0")  # the serial run decodes every read, as the others do
    serial = run_calibration(_config(night), tmp_path / "serial", block_size=5, readers=1)
    pool = run_calibration(
        _config(night),
        tmp_path / "pool",
        block_size=5,
        readers=2,
        progress=lambda f, m: messages.append((f, m)),
    )
    dask = run_calibration(
        _config(night), tmp_path / "dask", block_size=5, dask_scheduler="local", dask_workers=2
    )
    counts = serial.summary["rfi_flagging"]
    assert counts["rfi_channels"] + counts["samples"]["rfi_frequency"] > 0  # RFI was found
    assert counts["band_edge_channels"] == EDGE and counts["rfi_integrations"] >= 1
    for other in (pool, dask):
        for name in SOLUTION:
            np.testing.assert_array_equal(
                getattr(other.solution, name), getattr(serial.solution, name), err_msg=name
            )
        assert other.summary["rfi_flagging"] == counts  # the flagging's reads counted alike
        assert other.summary["execution"]["io"] == serial.summary["execution"]["io"]
        assert other.summary["provenance"]["inputs"] == serial.summary["provenance"]["inputs"]
    execution = pool.summary["execution"]
    assert serial.summary["execution"]["executor"] == "serial"
    assert execution["executor"] == "readers"
    readers = execution["readers"]
    assert readers["processes"] == 2 and readers["start_method"] == "forkserver"
    peaks = readers["worker_peak_rss_bytes"]
    assert 1 <= len(peaks) <= 2 and all(v > 10 * 1024**2 for v in peaks.values())
    assert all(int(pid) != os.getpid() for pid in peaks)
    # progress: both flagging reads and the fit, file by file, never backwards
    fractions = [f for f, _ in messages]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    texts = [m for _, m in messages]
    for expected in ("time-mean spectra, file 3/3", "outliers, file 3/3", "file 3/3 summed"):
        assert any(expected in m for m in texts), expected


def test_the_flags_are_the_same_in_processes_and_in_memory(night) -> None:
    """The mask (and the hits kept for the fit) of reader processes is the in-process
    one; diagnose's in-memory observation, scanned in its files' stretches, gets it too."""
    config = _config(night)
    source = open_source(config)
    tsky = np.ones((2, source.lsts.size, source.freqs.size))  # only to build the tasks
    serial, counts = scan_flags(config, source, tsky, 5, lambda *_: None)
    with process_readers(2) as pool:
        pooled, pool_counts = scan_flags(config, source, tsky, 5, lambda *_: None, pool)
    assert serial is not None and pooled is not None
    assert pool_counts == counts
    for name in ("band_edge", "channels", "integrations", "level"):
        np.testing.assert_array_equal(getattr(pooled, name), getattr(serial, name), name)
    assert serial.hits.keys() == pooled.hits.keys() and serial.hits
    for key, where in serial.hits.items():
        np.testing.assert_array_equal(pooled.hits[key], where)
    obs = read_observation(night)
    assert obs.meta["file_starts"] == [0, 12, 24]
    flagged, memory_counts = flag_observation(obs, block_size=7)  # blocks span the files
    assert flagged.flags.sum() > obs.flags.sum()
    counts = {k: v for k, v in counts.items() if k != "io"}
    assert memory_counts == counts


def _die(shared: object, task: int) -> int:
    """A task that kills its worker process at the second file."""
    if task == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    return task


def test_a_worker_that_dies_is_a_clear_error_not_a_hang() -> None:
    start = time.perf_counter()
    with process_readers(2) as pool:
        assert list(pool.map_ordered(_die, None, [0, 2, 4])) == [0, 2, 4]
    with (
        pytest.raises(PipelineError, match=r"reader process ended unexpectedly.*--readers 1"),
        process_readers(2) as pool,
    ):
        list(pool.map_ordered(_die, None, [0, 1, 2, 3]))
    assert time.perf_counter() - start < 60


def test_a_corrupt_file_is_a_clear_error_and_the_cli_shows_no_traceback(
    night, tmp_path, capsys
) -> None:
    damaged = tmp_path / "zen.part1.uvh5"
    damaged.write_bytes(night[1].read_bytes())
    _flip(damaged, "Data/visdata", 64, chunk=0)
    inputs = [night[0], damaged, night[2]]
    with pytest.raises(AutocalError, match=str(damaged)):
        run_calibration(_config(inputs), tmp_path / "api", readers=2)
    argv = ["calibrate", *map(str, inputs), "--beam", "dipole", "--nside", str(NSIDE)]
    argv += ["--products", "hdf5", "--readers", "2", "--out", str(tmp_path / "cli")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert str(damaged) in err and "Traceback" not in err
    assert not (tmp_path / "cli" / "summary.json").exists()


def test_cli_readers_option(night, tmp_path, capsys) -> None:
    base = ["calibrate", *map(str, night), "--beam", "dipole", "--nside", str(NSIDE)]
    base += ["--products", "hdf5"]
    assert main([*base, "--readers", "0", "--out", str(tmp_path / "a")]) == 2
    assert "--readers must be at least 1" in capsys.readouterr().err
    assert main([*base, "--readers", "2", "--dask", "local", "--out", str(tmp_path / "a")]) == 2
    assert "exclude each other" in capsys.readouterr().err
    runs = {}
    for n in (1, 2):
        assert main([*base, "--readers", str(n), "--out", str(tmp_path / f"r{n}")]) == 0
        capsys.readouterr()
        runs[n] = json.loads((tmp_path / f"r{n}" / "summary.json").read_text())
    assert runs[1]["execution"]["executor"] == "serial" and "readers" not in runs[1]["execution"]
    assert runs[2]["execution"]["executor"] == "readers"
    assert runs[1]["solution"] == runs[2]["solution"]


def test_the_automatic_choice(night, monkeypatch) -> None:
    """One process per core for a large enough night of UVH5 files on >= 4 cores; else in
    this process."""
    size = sum(p.stat().st_size for p in night)
    monkeypatch.setattr(autocal.pipeline.readers, "MIN_AUTO_BYTES", size)
    assert reader_count(None, "uvh5", night, cpus=2) == 1  # one process: faster on 2 cores
    assert reader_count(None, "uvh5", night, cpus=4) == 3  # at most one per file
    assert reader_count(None, "uvh5", night, cpus=16) == 3
    assert reader_count(None, "uvh5", night, cpus=1) == 1
    assert reader_count(None, "uvh5", night[:1], cpus=4) == 1
    assert reader_count(None, "miriad", night, cpus=4) == 1
    assert reader_count(1, "uvh5", night, cpus=2) == 1
    assert reader_count(2, "uvh5", night, cpus=1) == 2  # asked for
    assert reader_count(2, "edges", night, cpus=2) == 1
    monkeypatch.setattr(autocal.pipeline.readers, "MIN_AUTO_BYTES", size + 1)
    assert reader_count(None, "uvh5", night, cpus=4) == 1
    with pytest.raises(PipelineError, match="at least 1"):
        reader_count(0, "uvh5", night)


def test_pool_describes_itself_and_maps_in_order() -> None:
    with process_readers(2, start_method="spawn") as pool:
        assert isinstance(pool, ProcessReaders)
        assert pool.describe() == {
            "processes": 2,
            "start_method": "spawn",
            "threads_per_process": 1,
            "read_ahead": False,
        }
        assert pool.startup_seconds() > 0
        assert list(pool.map_ordered(_die, None, [4, 3, 2, 0], window=1)) == [4, 3, 2, 0]
        assert len(pool.worker_peak_rss()) >= 1
