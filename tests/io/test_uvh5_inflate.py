"""Chunks inflated on threads outside HDF5 equal what HDF5 decodes, bit for bit."""

from __future__ import annotations

import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest

from autocal.core.sites import HERA
from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_inflate import InflatingReader
from autocal.io.uvh5_writer import UVH5AutosWriter

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "hera" / "autos"


def _values(shape: tuple[int, ...], dtype: str, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=shape) * 1e3
    if np.dtype(dtype).kind == "c":
        x = x + 1j * rng.normal(size=shape)
    return x.astype(dtype)


def _dataset(tmp_path: Path, shape, chunks, dtype="<c8", **filters) -> h5py.Dataset:
    f = h5py.File(tmp_path / "d.h5", "w")
    return f.create_dataset("visdata", data=_values(shape, dtype), chunks=chunks, **filters)


# slabs that start and end inside chunks, subsets of channels and pols, the edges
SLABS = [
    (0, 40, slice(0, 50), slice(0, 2)),
    (7, 33, slice(3, 41), slice(1, 2)),
    (35, 40, slice(45, 50), slice(0, 1)),
]


@pytest.mark.parametrize("threads", ["1", "2"])
@pytest.mark.parametrize(
    ("dtype", "filters"),
    [
        ("<c8", {"compression": "gzip", "compression_opts": 1, "shuffle": True}),
        ("<c8", {"compression": "gzip", "compression_opts": 6}),
        (">c8", {"compression": "gzip", "shuffle": True}),
        ("<f4", {"compression": "gzip", "shuffle": True}),
        ("|b1", {"compression": "gzip", "shuffle": True}),
    ],
)
def test_slabs_equal_hdf5s_decoding(tmp_path, monkeypatch, threads, dtype, filters):
    monkeypatch.setenv("AUTOCAL_FIT_THREADS", threads)
    dset = _dataset(tmp_path, (40, 50, 2), (9, 16, 1), dtype, **filters)
    reader = InflatingReader(dset)
    assert reader.active
    for lo, hi, chans, pols in SLABS:
        expected = dset[lo:hi, chans, pols]
        out = np.full(expected.shape, 7, dset.dtype)
        assert reader.fill(out, lo, hi, chans, pols)
        assert out.tobytes() == expected.tobytes()


def test_the_legacy_four_dimensional_layout(tmp_path):
    dset = _dataset(tmp_path, (30, 1, 24, 2), (8, 1, 10, 1), compression="gzip", shuffle=True)
    reader = InflatingReader(dset)
    out = np.empty((19, 20, 2), dset.dtype)
    assert reader.fill(out, 5, 24, slice(2, 22), slice(0, 2))
    assert out.tobytes() == dset[5:24, 0, 2:22, :].tobytes()


@pytest.mark.parametrize(
    "filters",
    [
        {},
        {"chunks": (8, 10, 1)},
        {"compression": "lzf"},
        {"compression": "gzip", "fletcher32": True},
        {"compression": "gzip", "scaleoffset": 0, "dtype": "<i4"},
    ],
)
def test_other_filters_are_left_to_hdf5(tmp_path, filters):
    filters = dict(filters)
    dtype = filters.pop("dtype", "<c8")
    chunks = filters.pop("chunks", None if not filters else (8, 10, 1))
    dset = _dataset(tmp_path, (30, 24, 2), chunks, dtype, **filters)
    reader = InflatingReader(dset)
    assert not reader.active
    assert not reader.fill(np.empty((30, 24, 2), dset.dtype), 0, 30, slice(0, 24), slice(0, 2))


def test_a_chunk_stored_without_its_filter_or_not_stored_goes_back_to_hdf5(tmp_path):
    f = h5py.File(tmp_path / "d.h5", "w")
    dset = f.create_dataset(
        "x", shape=(16, 8, 1), dtype="<f4", chunks=(8, 8, 1), compression="gzip"
    )
    plain = np.arange(64, dtype="<f4").reshape(8, 8, 1)
    dset.id.write_direct_chunk((8, 0, 0), plain.tobytes(), filter_mask=1)  # deflate skipped
    reader = InflatingReader(dset)
    out = np.empty((16, 8, 1), "<f4")
    assert reader.active and not reader.fill(out, 0, 16, slice(0, 8), slice(0, 1))
    assert not reader.active  # the rest of the file is HDF5's
    np.testing.assert_array_equal(dset[8:16], plain)
    unwritten = f.create_dataset(
        "y", shape=(16, 8, 1), dtype="<f4", chunks=(8, 8, 1), compression="gzip"
    )
    reader = InflatingReader(unwritten)
    assert reader.active and not reader.fill(out, 0, 16, slice(0, 8), slice(0, 1))


def test_a_corrupt_chunk_is_an_os_error_naming_it(tmp_path):
    f = h5py.File(tmp_path / "d.h5", "w")
    dset = f.create_dataset("x", shape=(8, 8, 1), dtype="<f4", chunks=(8, 8, 1), compression="gzip")
    dset.id.write_direct_chunk((0, 0, 0), b"not a deflate stream")
    with pytest.raises(OSError, match=r"/x: the chunk at \(0, 0, 0\) does not inflate"):
        InflatingReader(dset).fill(np.empty((8, 8, 1), "<f4"), 0, 8, slice(0, 8), slice(0, 1))
    dset.id.write_direct_chunk((0, 0, 0), zlib.compress(b"short"))
    with pytest.raises(OSError, match="inflates to 5 bytes, not 256"):
        InflatingReader(dset).fill(np.empty((8, 8, 1), "<f4"), 0, 8, slice(0, 8), slice(0, 1))


@pytest.fixture(scope="module")
def night_file(tmp_path_factory) -> Path:
    """A file as benchmarks/night.py writes them (gzip 1, shuffle, 256-channel chunks):
    5 antennas x 2 pols x 600 channels (the last chunk partial) x 10 integrations, with
    flags and varying nsamples."""
    path = tmp_path_factory.mktemp("inflate") / "zen.gzip.uvh5"
    rng = np.random.default_rng(4)
    nant, ntime, nfreq = 5, 10, 600
    data = 1e4 + rng.normal(size=(nant, 2, ntime, nfreq)) * 30
    flags = rng.random(data.shape) < 0.01
    nsamples = rng.integers(1, 4, size=data.shape).astype(float)
    from pyuvdata.utils import get_lst_for_time

    jds = 2458098.3 + np.arange(ntime) * 10.7 / 86400
    lsts = get_lst_for_time(jds, telescope_loc=HERA.location) * 12 / np.pi
    with UVH5AutosWriter(
        path,
        freqs=np.linspace(100e6, 200e6, nfreq),
        channel_width=100e6 / nfreq,
        jds=jds,
        lsts=lsts,
        integration_time=10.7,
        antennas=[0, 1, 2, 11, 12],
        pols=["ee", "nn"],
        site=HERA,
        compression="gzip",
    ) as writer:
        writer.write(0, data, flags=flags, nsamples=nsamples)
    return path


def _blocks(path: Path, inflate: bool, **kwargs):
    return [
        (obs.data.copy(), obs.flags.copy(), obs.nsamples.copy())
        for obs in iter_uvh5_blocks(path, checksum=False, inflate=inflate, **kwargs)
    ]


def test_blocks_of_a_gzip_file_equal_hdf5s(night_file):
    """A night file as benchmarks/night.py writes it (gzip 1 with shuffle): every block
    the same, with and without selections that cut chunks."""
    with h5py.File(night_file) as f:
        assert InflatingReader(f["Data/visdata"]).active
    for kwargs in ({}, {"freq_range": (120e6, 170e6), "pols": ["nn"], "block_size": 3}):
        for (d1, f1, n1), (d2, f2, n2) in zip(
            _blocks(night_file, True, **kwargs), _blocks(night_file, False, **kwargs), strict=True
        ):
            assert d1.tobytes() == d2.tobytes()
            np.testing.assert_array_equal(f1, f2)
            np.testing.assert_array_equal(n1, n2)


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_real_hera_files_are_uncompressed_and_read_as_before():
    path = DATA / "zen.2458116.30448.HH.uvh5"
    with h5py.File(path) as f:
        assert not InflatingReader(f["Data/visdata"]).active
    for a, b in zip(_blocks(path, True), _blocks(path, False), strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
