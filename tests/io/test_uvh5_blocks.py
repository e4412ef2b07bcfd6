"""UVH5 files read block by block: values, prefetch and buffers, threads and files, errors."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from autocal.core.observation import ObservationError
from autocal.io.uvh5 import read_uvh5, write_uvh5
from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_chunks import ReadStats
from autocal.io.uvh5_meta import UVH5FormatError
from tests.io.test_uvh5 import AUTOS, REAL_FILES, synthetic_observation
from tests.io.test_uvh5_writer import part_writer


def test_block_reader_matches_pyuvdata_on_real_files(data_root):
    """Every real file (complex64/128, old and new shapes, with crosses, imaginary autos)."""
    for name in REAL_FILES:
        path = data_root / AUTOS / name
        whole = read_uvh5(path)
        stats = ReadStats()
        blocks = list(iter_uvh5_blocks(path, block_size=7, stats=stats))
        for key in ("data", "flags", "nsamples"):
            np.testing.assert_array_equal(
                np.concatenate([getattr(b, key) for b in blocks], axis=2), getattr(whole, key)
            )
        np.testing.assert_array_equal(
            np.concatenate([b.integration_time for b in blocks]), whole.integration_time
        )
        assert stats.largest_array <= 7 * whole.nant * 4 * whole.nfreq * 16
    # selections: antennas in any order, one pol, a channel range, an LST range
    path = data_root / AUTOS / "zen.2458098.43124.subband.uvh5"
    whole = read_uvh5(path)
    sel = {
        "antennas": whole.antennas[::-1][:3].tolist(),
        "pols": ["nn"],
        "freq_range": (120e6, 130e6),
        "lst_range": (whole.lsts[5], whole.lsts[40]),
    }
    expected = read_uvh5(path, **sel)
    blocks = list(iter_uvh5_blocks(path, block_size=4, **sel))
    np.testing.assert_array_equal(np.concatenate([b.data for b in blocks], axis=2), expected.data)
    assert blocks[0].antennas.tolist() == sel["antennas"]


def _block_copies(path: Path, **kwargs) -> tuple[list[dict], dict]:
    """Copies of every block's arrays and meta (taken before the next block is asked for)."""
    stats = ReadStats()
    out = []
    for b in iter_uvh5_blocks(path, stats=stats, **kwargs):
        out.append(
            {
                "data": b.data.copy(),
                "flags": b.flags.copy(),
                "nsamples": np.array(b.nsamples),
                "integration_time": b.integration_time.copy(),
                "meta": dict(b.meta),
            }
        )
    return out, stats.as_dict()


def _reader_threads() -> list:
    import threading

    return [t for t in threading.enumerate() if t.name.startswith("autocal-uvh5")]


@pytest.mark.parametrize(
    "name, selection",
    [
        ("zen.2458098.43124.subband.uvh5", {}),
        ("zen.2458098.43124.subband.uvh5", {"pols": ["nn"], "freq_range": (120e6, 130e6)}),
        ("zen.2458042.60288.HH.uvRXLS.uvh5_downselected", {}),  # crosses: point selection
        ("zen.2458116.30448.HH.uvh5", {}),  # imaginary autos
    ],
)
def test_prefetch_and_reused_buffers_give_the_same_blocks(data_root, name, selection):
    path = data_root / AUTOS / name
    kw = {"block_size": 3, **selection}
    expected, expected_stats = _block_copies(path, prefetch=False, **kw)
    assert len(expected) > 2 and "sha256" in expected[0]["meta"]
    for prefetch, reuse in ((True, False), (False, True), (True, True)):
        got, stats = _block_copies(path, prefetch=prefetch, reuse_buffers=reuse, **kw)
        assert stats == expected_stats
        assert len(got) == len(expected)
        for g, e in zip(got, expected, strict=True):
            assert g["meta"] == e["meta"]
            for key in ("data", "flags", "nsamples", "integration_time"):
                np.testing.assert_array_equal(g[key], e[key])
    assert not _reader_threads()


def test_reused_buffers_alternate_between_two_sets(tmp_path):
    obs = synthetic_observation(ntime=7)
    path = tmp_path / "obs.uvh5"
    write_uvh5(obs, path)
    fresh = list(iter_uvh5_blocks(path, block_size=2))
    assert not np.shares_memory(fresh[0].data, fresh[2].data)
    seen = []
    for block in iter_uvh5_blocks(path, block_size=2, reuse_buffers=True):
        seen.append(block.data)
    assert np.shares_memory(seen[0], seen[2]) and np.shares_memory(seen[1], seen[3])
    assert not np.shares_memory(seen[0], seen[1])


def test_block_reader_early_close_and_errors_leave_no_thread_or_open_file(tmp_path, monkeypatch):
    import autocal.io.uvh5_blocks as uvh5_blocks

    obs = synthetic_observation(ntime=9)
    path = tmp_path / "obs.uvh5"
    write_uvh5(obs, path)
    opened: list = []

    class Tracked(uvh5_blocks.CountingFile):
        def __init__(self, p):
            super().__init__(p)
            opened.append(self)

    monkeypatch.setattr(uvh5_blocks, "CountingFile", Tracked)
    blocks = iter_uvh5_blocks(path, block_size=2)
    first = next(blocks)  # the second block is being read meanwhile
    blocks.close()
    assert first.ntime == 2 and opened[-1].closed and not _reader_threads()

    real_read = uvh5_blocks.read_rows
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) > 6:  # 3 data sets per block: the third block fails
            raise OSError("simulated read error")
        return real_read(*args, **kwargs)

    monkeypatch.setattr(uvh5_blocks, "read_rows", failing)
    got = []
    with pytest.raises(UVH5FormatError, match="simulated read error"):
        for block in iter_uvh5_blocks(path, block_size=2):
            got.append(block.meta["block"])
    assert got == [0, 1]  # the error surfaces at the block it belongs to
    assert opened[-1].closed and not _reader_threads()


def test_block_reader_decodes_repeated_flag_and_nsample_chunks_once(tmp_path):
    obs = synthetic_observation(ntime=9)
    path = tmp_path / "parts.uvh5"
    flags = np.zeros(obs.shape, bool)
    flags[2, 1, 4, 1:3] = True  # a few flagged samples: their chunk is decoded, not reused
    nsamples = np.ones(obs.shape)  # uniform, as in raw HERA files
    with part_writer(obs, path, compression="gzip") as writer:
        writer.write(0, obs.data, flags, nsamples)
    whole = read_uvh5(path)  # pyuvdata
    stats = ReadStats()
    blocks = list(iter_uvh5_blocks(path, block_size=2, stats=stats))
    for key in ("data", "flags", "nsamples"):
        np.testing.assert_array_equal(
            np.concatenate([getattr(b, key) for b in blocks], axis=2), getattr(whole, key)
        )
    assert whole.flags.sum() == 2
    plain_stats = ReadStats()
    plain = list(iter_uvh5_blocks(path, block_size=2, stats=plain_stats, decode_repeats_once=False))
    for b, c in zip(blocks, plain, strict=True):
        np.testing.assert_array_equal(b.flags, c.flags)
        np.testing.assert_array_equal(b.nsamples, c.nsamples)
    assert plain_stats.bytes_reused == 0
    # one chunk per integration and pol (all antennas and channels): every chunk is a copy
    # except the first of each data set and the one with the flags
    with h5py.File(path, "r") as h5:
        assert h5["Data/flags"].chunks == (obs.nant, obs.nfreq, 1)
        per_chunk = {
            k: obs.nant * obs.nfreq * h5[f"Data/{k}"].dtype.itemsize for k in ("flags", "nsamples")
        }
    nchunks = obs.ntime * len(obs.pols)
    assert (
        stats.bytes_reused
        == (nchunks - 2) * per_chunk["flags"] + (nchunks - 1) * per_chunk["nsamples"]
    )


@pytest.mark.parametrize("dataset", ["Data/visdata", "Data/flags"])
def test_a_chunk_that_does_not_decode_is_a_clear_error(tmp_path, dataset, capsys):
    from autocal.cli.main import main

    obs = synthetic_observation(ntime=9)
    path = tmp_path / "corrupt.uvh5"
    with part_writer(obs, path, compression="gzip") as writer:
        writer.write(0, obs.data, np.zeros(obs.shape, bool), np.ones(obs.shape))
    with h5py.File(path, "r+") as h5:  # the chunk of integration 5, pol 0: garbage bytes
        dset = h5[dataset]
        mask, _ = dset.id.read_direct_chunk((obs.nant * 5, 0, 0))
        dset.id.write_direct_chunk((obs.nant * 5, 0, 0), b"\x00garbage" * 4, mask)
    with pytest.raises(UVH5FormatError, match=r"integrations 4-5 .*corrupt or truncated"):
        for _ in iter_uvh5_blocks(path, block_size=2):
            pass
    assert not _reader_threads()
    out = tmp_path / "cal"
    argv = ["calibrate", str(path), "--beam", "dipole", "--nside", "16", "--out", str(out)]
    assert main(argv) == 2
    assert "corrupt or truncated" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("prefetch", [True, False])
def test_uniform_nsamples_are_one_value_and_others_every_bit(tmp_path, prefetch):
    """A block whose stored nsamples all have the same bits gets them as one value
    broadcast (no block-sized float64 array); a block with one other value, or a ``-0.0``
    among zeros, gets every sample's value bit for bit, as h5py reads them."""
    obs = synthetic_observation(ntime=6)
    nsamples = np.ones(obs.shape)
    nsamples[1, 0, 4, 2] = 0.5  # the third block (two integrations each) is not uniform
    zeros = np.zeros(obs.shape)
    zeros[0, 1, 1, 3] = -0.0
    for name, values, uniform in (
        ("mixed.uvh5", nsamples, [True, True, False]),
        ("zeros.uvh5", zeros, [False, True, True]),
    ):
        path = tmp_path / name
        with part_writer(obs, path, compression="gzip") as writer:
            writer.write(0, obs.data, np.zeros(obs.shape, bool), values)
        blocks = list(iter_uvh5_blocks(path, block_size=2, prefetch=prefetch))
        assert [not any(b.nsamples.strides) for b in blocks] == uniform
        got = np.concatenate([b.nsamples for b in blocks], axis=2)
        np.testing.assert_array_equal(got.view(np.uint64), values.view(np.uint64))
        np.testing.assert_array_equal(got, read_uvh5(path).nsamples)  # pyuvdata


def test_a_uniform_negative_or_nan_nsamples_is_still_refused(tmp_path):
    """One stored value broadcast is checked as the whole array was."""
    obs = synthetic_observation(ntime=2)
    for value in (-1.0, np.nan):
        path = tmp_path / f"bad{value}.uvh5"
        with part_writer(obs, path) as writer:
            writer.write(0, obs.data, np.zeros(obs.shape, bool), np.full(obs.shape, value))
        with pytest.raises(ObservationError, match="nsamples must be finite and >= 0"):
            list(iter_uvh5_blocks(path))


def test_one_value_chunks_fill_blocks_with_a_missing_row(tmp_path):
    """A block that is not every antenna's row at every time (an antenna-time row
    missing) takes one-value flags and nsamples through the scatter, as pyuvdata reads
    them; the missing sample is flagged with no samples."""
    from pyuvdata import UVData

    obs = synthetic_observation(ntime=6)
    path = tmp_path / "time.uvh5"
    write_uvh5(obs, path)
    uv = UVData.from_file(path)
    uv.nsample_array[:] = 2.0
    uv.flag_array[:] = False
    keep = np.ones(uv.Nblts, bool)
    keep[4] = False  # one antenna-time row missing (the second integration's)
    uv.select(blt_inds=np.flatnonzero(keep))
    odd = tmp_path / "missing.uvh5"
    uv.write_uvh5(
        str(odd), data_compression="gzip", flags_compression="gzip", nsample_compression="gzip"
    )
    stats = ReadStats()
    blocks = list(iter_uvh5_blocks(odd, block_size=2, stats=stats))
    assert stats.bytes_reused > 0  # the one-value chunks were used
    assert [not any(b.nsamples.strides) for b in blocks] == [False, True, True]
    whole = read_uvh5(odd)  # pyuvdata
    for key in ("data", "flags", "nsamples"):
        np.testing.assert_array_equal(
            np.concatenate([getattr(b, key) for b in blocks], axis=2), getattr(whole, key)
        )
    nsamples = np.concatenate([b.nsamples for b in blocks], axis=2)
    flags = np.concatenate([b.flags for b in blocks], axis=2)
    assert (nsamples == 0).sum() == len(obs.pols) * obs.nfreq and flags[nsamples == 0].all()
    assert set(np.unique(nsamples)) == {0.0, 2.0}


@pytest.mark.parametrize("block_size", [2, None])
def test_complex64_same_feed_imaginary_autos_are_their_modulus_as_pyuvdata_reads(
    tmp_path, block_size
):
    """The compiled power (``autocal.io.power_kernel``) leaves a complex64 block with a
    same-feed imaginary part to numpy's modulus; the other blocks it writes itself; every
    value as pyuvdata reads the file (``fix_autos``)."""
    from pyuvdata import UVData

    obs = synthetic_observation(ntime=6)
    write_uvh5(obs, tmp_path / "c16.uvh5")
    path = tmp_path / "imag.uvh5"
    UVData.from_file(tmp_path / "c16.uvh5").write_uvh5(str(path), data_write_dtype="c8")
    with h5py.File(path, "r+") as h5:
        vis = h5["Data/visdata"]
        assert vis.dtype == np.complex64
        values = vis[()]
        values[3, 2, 0] += 3e5j  # a same-feed auto in the second integration
        vis[...] = values
    blocks = list(iter_uvh5_blocks(path, block_size=block_size))
    got = np.concatenate([b.data for b in blocks], axis=2)
    expected = read_uvh5(path).data
    np.testing.assert_array_equal(got, expected)
    assert np.count_nonzero(got != obs.data.astype(np.float32)) == 1  # its modulus
