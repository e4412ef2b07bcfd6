"""``autocal diagnose`` flags band edges and RFI before its fits, as ``autocal calibrate`` does.

A simulated day (dipole beam, one antenna, 1 MHz channels) written as two UVH5 files, with
rolled-off channels at the low end of the band and an RFI spike injected: the observation
the search receives has them flagged, ``diagnosis.json``, ``summary.json`` and
``summary.txt`` count them, ``--no-rfi-flagging`` leaves them in, and the flags are those the
calibration's own reads get (:func:`autocal.pipeline.flagging.scan_flags`).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from autocal.cli.main import main
from autocal.diagnosis import run as diagnose_run
from autocal.diagnosis.reading import read_observation
from autocal.io.uvh5 import write_uvh5
from autocal.pipeline.config import CalibrationConfig, read_selection
from autocal.pipeline.flagging import TURNED_OFF, flag_observation, scan_flags
from autocal.pipeline.partials import read_chunks
from autocal.pipeline.sources import open_source
from autocal.simulate.mock import SimulationConfig, simulate
from tests.diagnosis.simulated import BT, SKY

#: Channels at the low end of the band rolled off to 2 % of their level (band edges).
EDGE = 3
#: The RFI spike: integration, channel and factor.
SPIKE = (40, 50, 1.2)
#: Options of a fast diagnosis of the simulated day.
FAST = ["--sky", SKY, "--beam", "dipole", "--nside", "32", "--max-steps", "0"]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """The simulated day with a band edge and a spike, in two UVH5 files (two halves)."""
    obs, _ = simulate(
        SimulationConfig(
            sky=SKY,
            beam="dipole",
            channel_width_khz=1000,
            cadence_s=600,
            nside=32,
            noise_dnu_hz=BT,
        )
    )
    data = obs.data.copy()
    data[..., :EDGE] *= 0.02
    t, f, factor = SPIKE
    data[0, 0, t, f] *= factor
    obs = dataclasses.replace(obs, data=data)
    folder = tmp_path_factory.mktemp("rfi")
    paths = []
    half = obs.ntime // 2
    split = float(obs.lsts[half - 1] + obs.lsts[half]) / 2
    for i, lsts in enumerate([(0.0, split), (split, 24.0)]):
        path = folder / f"zen.2458098.{i}.sim.uvh5"
        write_uvh5(obs.select(lst_range=lsts), path)
        paths.append(path)
    return paths


def _searched(monkeypatch: pytest.MonkeyPatch) -> list[np.ndarray]:
    """Record the flags of every observation the search (``diagnose``) is given."""
    seen: list[np.ndarray] = []
    search = diagnose_run.diagnose

    def spy(obs, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(obs.flags.copy())
        return search(obs, *args, **kwargs)

    monkeypatch.setattr(diagnose_run, "diagnose", spy)
    return seen


def test_band_edges_and_rfi_are_flagged_before_the_fits(
    files: list[Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    """The search sees the band edge and the spike flagged; the counts are reported; with
    --no-rfi-flagging it sees neither flagged and the reports say it was turned off."""
    seen = _searched(monkeypatch)
    inputs = [str(p) for p in files]
    t, f, _ = SPIKE
    on = tmp_path / "on"
    assert main(["diagnose", *inputs, *FAST, "--out", str(on)]) == 0, capsys.readouterr().err
    flags = seen[-1]
    assert flags[..., :EDGE].all()  # band edges: whole channels
    assert flags[0, 0, t, f]
    assert not flags[..., EDGE:].all(axis=2).any()  # no in-band channel flagged whole
    doc = json.loads((on / "diagnosis.json").read_text())
    counts = doc["rfi_flagging"]
    assert counts["applied"] is True
    assert counts["band_edge_channels"] == EDGE
    assert counts["samples"]["band_edge"] == EDGE * flags.shape[2]
    assert counts["samples"]["rfi_frequency"] >= 1
    assert json.loads((on / "summary.json").read_text())["rfi_flagging"] == counts
    text = (on / "summary.txt").read_text()
    assert f"{EDGE} band-edge channel(s)" in text and "outliers flagged in the residuals" in text
    assert doc["config"]["outlier_flagging"]["enabled"] is True  # the residual rounds stay

    off = tmp_path / "off"
    argv = ["diagnose", *inputs, *FAST, "--no-rfi-flagging", "--out", str(off)]
    assert main(argv) == 0, capsys.readouterr().err
    flags = seen[-1]
    assert not flags[..., :EDGE].any() and not flags[0, 0, t, f]
    assert json.loads((off / "diagnosis.json").read_text())["rfi_flagging"] == TURNED_OFF
    assert json.loads((off / "summary.json").read_text())["config"]["rfi_flagging"] is False
    assert "flagged before the fit: nothing; turned off" in (off / "summary.txt").read_text()


def test_diagnose_flags_what_calibrate_flags(files: list[Path]) -> None:
    """The in-memory observation's flags are those the calibration's block reads get,
    whatever the blocks; the observation read is left as it was."""
    obs = read_observation(files)
    before = obs.flags.copy()
    flagged, counts = flag_observation(obs)
    assert np.array_equal(obs.flags, before) and flagged.data is obs.data
    one, _ = flag_observation(obs, block_size=1)
    assert np.array_equal(one.flags, flagged.flags)

    config = CalibrationConfig(inputs=[str(p) for p in files], beam="dipole")
    source = open_source(config)
    tsky = np.zeros((1, source.lsts.size, source.freqs.size))  # only to build the tasks
    mask, calibrate_counts = scan_flags(config, source, tsky, 7, lambda *_: None)
    reads = calibrate_counts.pop("io")  # the calibration's flagging reads (files, not memory)
    assert mask is not None and counts == calibrate_counts
    assert reads["integrations"] == 2 * source.lsts.size
    parts = []
    for task in source.tasks(tsky):
        offset = task.offset
        for chunk in read_chunks(read_selection(config), 5, task):
            parts.append(mask.apply(chunk.data, chunk.flags, offset))
            offset += chunk.ntime
    assert np.array_equal(flagged.flags, np.concatenate(parts, axis=2))
    assert flagged.flags.sum() > before.sum()


def test_a_selection_too_narrow_is_refused_with_the_band(files, tmp_path, capsys) -> None:
    """Four 1 MHz channels: the reflection fit's least squares were empty (a LinAlgError
    traceback), one channel an IndexError; now a usage error that says what to do."""
    argv = ["diagnose", *map(str, files), "--out", str(tmp_path / "d"), *FAST]
    for band, nchan in (("150:153.5", 4), ("150:150.5", 1)):
        assert main([*argv, "--freq-range", band]) == 2
        err = capsys.readouterr().err
        assert f"has {nchan} channel(s)" in err and "widen --freq-range" in err
    assert not (tmp_path / "d").exists()
