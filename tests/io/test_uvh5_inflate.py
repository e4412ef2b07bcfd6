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


@pytest.mark.parametrize("threads", ["1", "2"])
def test_a_chunk_that_does_not_inflate_goes_back_to_hdf5(tmp_path, monkeypatch, threads):
    """Not a deflate stream, or one of the wrong length (e.g. an edge chunk HDF5 stored
    unfiltered): the slab goes to HDF5, which decodes what it can (it takes a short
    stream as it is) and reports the rest."""
    monkeypatch.setenv("AUTOCAL_FIT_THREADS", threads)
    path = tmp_path / "d.h5"
    for stored in (b"not a deflate stream", zlib.compress(b"short")):
        with h5py.File(path, "w") as f:
            f.create_dataset(
                "x", data=_values((32, 8, 1), "<f4"), chunks=(8, 8, 1), compression="gzip"
            )
            f["x"].id.write_direct_chunk((16, 0, 0), stored)
        with h5py.File(path, "r") as f:
            reader = InflatingReader(f["x"])
            out = np.empty((32, 8, 1), "<f4")
            assert reader.active and not reader.fill(out, 0, 32, slice(0, 8), slice(0, 1))
            assert not reader.active
            if stored.startswith(b"not"):
                with pytest.raises(OSError, match="filter returned failure"):
                    f["x"].read_direct(out)  # HDF5 reports the corrupt chunk itself


def test_a_corrupt_chunk_in_a_file_is_a_clear_read_error(night_file, tmp_path):
    """A visibility chunk whose stored bytes are damaged: the block reader hands the slab
    to HDF5, whose error names the file and the integrations."""
    from autocal.io.uvh5_meta import UVH5FormatError

    broken = tmp_path / "broken.uvh5"
    broken.write_bytes(night_file.read_bytes())
    with h5py.File(broken, "r+") as f:
        dset = f["Data/visdata"]
        mask, stored = dset.id.read_direct_chunk((5, 0, 0))
        dset.id.write_direct_chunk((5, 0, 0), stored[: len(stored) // 2], mask)
    with pytest.raises(UVH5FormatError, match=r"broken\.uvh5"):
        _blocks(broken, True)


def test_complex_stored_as_another_compound_is_left_to_hdf5(tmp_path):
    """h5py reads a compound of two floats as complex whatever its layout; stored with
    the imaginary part first, or padded, its stored bytes are not the values' bytes."""
    values = _values((16, 8, 1), "<c8")
    for fields in (
        {"names": ["r", "i"], "formats": ["<f4", "<f4"], "offsets": [4, 0], "itemsize": 8},
        {"names": ["r", "i"], "formats": ["<f4", "<f4"], "offsets": [0, 4], "itemsize": 12},
    ):
        f = h5py.File(tmp_path / "c.h5", "w")
        stored = np.empty(values.shape, np.dtype(fields))
        stored["r"], stored["i"] = values.real, values.imag
        dset = f.create_dataset("x", data=stored, chunks=(8, 8, 1), compression="gzip")
        del f["x"]
        tid = h5py.h5t.py_create(np.dtype(fields))
        space = h5py.h5s.create_simple(values.shape)
        plist = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        plist.set_chunk((8, 8, 1))
        plist.set_deflate(1)
        h5py.h5d.create(f.id, b"x", tid, space, dcpl=plist).write(
            h5py.h5s.ALL, h5py.h5s.ALL, stored
        )
        dset = f["x"]
        assert dset.dtype == np.complex64  # how h5py reads it
        np.testing.assert_array_equal(dset[()], values)
        assert not InflatingReader(dset).active
        f.close()


def test_the_memory_check_of_per_time_products_knows_the_time_model(monkeypatch):
    """A constant model's per-time calh5 holds one integration's gains (1 byte per value,
    the per-time flags), a time-varying one holds them all (14): refused only then."""
    import autocal.pipeline.products as products
    from autocal.pipeline.config import PipelineError

    shape = (350, 2, 1536, 192)
    values = 350 * 2 * 1536 * 192
    monkeypatch.setattr(products, "available_memory", lambda: 5 * values)
    products.check_per_time_memory(["calh5", "hdf5"], shape, constant=True)
    with pytest.raises(PipelineError, match=r"per-time calh5 .* needs about"):
        products.check_per_time_memory(["calh5", "hdf5"], shape, constant=False)
    with pytest.raises(PipelineError, match="per-time calfits"):
        products.check_per_time_memory(["calfits"], shape, constant=True)
    products.check_per_time_memory(["hdf5", "png"], shape, constant=False)


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


def test_blocks_of_a_gzip_file_equal_hdf5s(night_file, monkeypatch):
    """A night file as benchmarks/night.py writes it (gzip 1 with shuffle): every block
    the same, with and without selections that cut chunks."""
    with h5py.File(night_file) as f:
        assert InflatingReader(f["Data/visdata"]).active
    filled = []
    real_fill = InflatingReader.fill

    def counting_fill(self, *args):
        done = real_fill(self, *args)
        filled.append((self.name, done))
        return done

    monkeypatch.setattr(InflatingReader, "fill", counting_fill)
    for kwargs in ({}, {"freq_range": (120e6, 170e6), "pols": ["nn"], "block_size": 3}):
        for (d1, f1, n1), (d2, f2, n2) in zip(
            _blocks(night_file, True, **kwargs), _blocks(night_file, False, **kwargs), strict=True
        ):
            assert d1.tobytes() == d2.tobytes()
            np.testing.assert_array_equal(f1, f2)
            np.testing.assert_array_equal(n1, n2)
    assert ("/Data/visdata", True) in filled and all(done for _, done in filled)


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_real_hera_files_are_uncompressed_and_read_as_before():
    path = DATA / "zen.2458116.30448.HH.uvh5"
    with h5py.File(path) as f:
        assert not InflatingReader(f["Data/visdata"]).active
    for a, b in zip(_blocks(path, True), _blocks(path, False), strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
