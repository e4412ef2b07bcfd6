"""UVH5 files written in parts: round trips for every data type and compression, refusals."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from autocal.core.observation import Observation, ObservationError
from autocal.io.uvh5 import read_uvh5
from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_writer import UVH5AutosWriter
from tests.io.test_uvh5 import synthetic_observation


def part_writer(obs: Observation, path: Path, **kwargs) -> UVH5AutosWriter:
    return UVH5AutosWriter(
        path,
        freqs=obs.freqs,
        channel_width=obs.channel_width,
        jds=obs.jds,
        lsts=obs.lsts,
        integration_time=obs.integration_time,
        antennas=obs.antennas,
        pols=obs.pols,
        site=obs.site,
        telescope_name=obs.telescope_name,
        **kwargs,
    )


@pytest.mark.parametrize(
    ("dtype", "compression", "scale"),
    [("c8", "lzf", 1.0), ("c16", "gzip", 1.0), ("c8", None, 1.0), ("int32", "gzip", 1.0)],
)
def test_part_writer_round_trip(tmp_path, dtype, compression, scale):
    obs = synthetic_observation(ntime=7)
    data = np.rint(obs.data) if dtype == "int32" else obs.data
    flags = np.zeros(obs.shape, bool)
    flags[1, 0, 2, 3] = True
    path = tmp_path / "parts.uvh5"
    with part_writer(obs, path, dtype=dtype, compression=compression) as writer:
        for start in (0, 3, 6):  # any order of parts, each written once
            part = slice(start, min(start + 3, 7))
            writer.write(start, data[:, :, part], flags[:, :, part], obs.nsamples[:, :, part])
    back = read_uvh5(path)
    rtol = 1e-7 if dtype == "c8" else 0
    np.testing.assert_allclose(back.data, data, rtol=rtol)
    np.testing.assert_array_equal(back.flags, flags)
    np.testing.assert_allclose(back.lsts, obs.lsts, atol=1 / 3600)
    assert back.pols == obs.pols and back.telescope_name == "HERA"
    with h5py.File(path, "r") as h5:
        vis = h5["Data/visdata"]
        assert vis.shape == (7 * obs.nant, obs.nfreq, 2)
        assert vis.chunks == (obs.nant, obs.nfreq, 1)
        assert vis.compression == compression and vis.shuffle == (compression is not None)
        if dtype == "int32":
            assert vis.dtype.names == ("r", "i")
    blocks = list(iter_uvh5_blocks(path, block_size=2))
    np.testing.assert_array_equal(np.concatenate([b.data for b in blocks], axis=2), back.data)


def test_part_writer_refuses_incomplete_or_bad_parts(tmp_path):
    obs = synthetic_observation(ntime=4)
    path = tmp_path / "incomplete.uvh5"
    with pytest.raises(ObservationError, match="never written"), part_writer(obs, path) as writer:
        writer.write(0, obs.data[:, :, :2])
    assert not path.exists() and not list(tmp_path.iterdir())
    with pytest.raises(ObservationError, match="outside"), part_writer(obs, path) as writer:
        writer.write(3, obs.data[:, :, :2])
    with pytest.raises(ObservationError, match="expected"), part_writer(obs, path) as writer:
        writer.write(0, obs.data[:1])
    assert not list(tmp_path.iterdir())
    with pytest.raises(ObservationError, match="data type"):
        part_writer(obs, path, dtype="f4")
    with pytest.raises(ObservationError, match="compression"):
        part_writer(obs, path, compression="szip")
    path.touch()
    with pytest.raises(FileExistsError):
        part_writer(obs, path)
