"""Data integrity of UVH5 files (autocal.io.uvh5_integrity): checksummed chunks that fail
are refused; files without checksums are read and reported as unchecked."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from autocal.core.files import file_checksum
from autocal.io.uvh5 import read_uvh5
from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_integrity import DataIntegrityError, file_integrity, input_integrity
from tests.io.test_uvh5 import synthetic_observation
from tests.io.test_uvh5_writer import part_writer


def _plain_file(path: Path, ntime: int = 8) -> Path:
    """A UVH5 file of synthetic autos, uncompressed chunks (no checksum)."""
    obs = synthetic_observation(ntime=ntime)
    with part_writer(obs, path, compression=None) as writer:
        writer.write(0, obs.data, np.zeros(obs.shape, bool), np.ones(obs.shape))
    return path


def _with_fletcher32(plain: Path, path: Path) -> Path:
    """A copy of ``plain`` whose Data sets carry HDF5 Fletcher-32 chunk checksums."""
    with h5py.File(plain, "r") as src, h5py.File(path, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        src.copy("Header", dst)
        data = dst.create_group("Data")
        for name, dset in src["Data"].items():
            data.create_dataset(name, data=dset[()], chunks=dset.chunks or True, fletcher32=True)
    return path


def _flip(path: Path, dataset: str, nbytes: int, chunk: int = 1) -> None:
    """Invert ``nbytes`` bytes in the middle of a stored chunk of ``dataset``."""
    with h5py.File(path, "r") as h5:
        info = h5[dataset].id.get_chunk_info(chunk)
        offset, size = info.byte_offset, info.size
    nbytes = min(nbytes, size - 8)
    start = offset + (size - nbytes) // 2
    with open(path, "r+b") as f:
        f.seek(start)
        raw = f.read(nbytes)
        f.seek(start)
        f.write(bytes(b ^ 0xFF for b in raw))


def test_a_checksummed_file_reads_and_says_so(tmp_path: Path) -> None:
    path = _with_fletcher32(_plain_file(tmp_path / "plain.uvh5"), tmp_path / "sum.uvh5")
    report = file_integrity(path)
    assert report["status"] == "checksummed"
    assert report["checksummed"] == {"visdata": True, "flags": True, "nsamples": True}
    np.testing.assert_array_equal(read_uvh5(path).data, read_uvh5(tmp_path / "plain.uvh5").data)


@pytest.mark.parametrize("dataset", ["Data/visdata", "Data/nsamples"])
def test_a_checksummed_chunk_with_flipped_bytes_is_refused(tmp_path: Path, dataset: str) -> None:
    path = _with_fletcher32(_plain_file(tmp_path / "plain.uvh5"), tmp_path / "sum.uvh5")
    _flip(path, dataset, 16)
    with pytest.raises(DataIntegrityError, match="Fletcher-32 checksum"):
        for _ in iter_uvh5_blocks(path, block_size=2):
            pass
    with pytest.raises(DataIntegrityError, match="checksum"):
        read_uvh5(path)


def test_flipped_bytes_in_a_plain_file_cannot_be_detected(tmp_path: Path, caplog) -> None:
    """The audit's case: 4 KB inverted inside a data chunk of a file without checksums.

    What can honestly be said: the file reads without error, into different numbers;
    the run's provenance says its data were not checkable, and its SHA-256 (also in the
    provenance) differs from the original's, which a user can compare with the archive.
    """
    plain = _plain_file(tmp_path / "plain.uvh5", ntime=64)
    damaged = tmp_path / "damaged.uvh5"
    shutil.copy(plain, damaged)
    _flip(damaged, "Data/visdata", 4096)
    with caplog.at_level(logging.INFO, logger="autocal.io.uvh5_integrity"):
        blocks = list(iter_uvh5_blocks(damaged, block_size=64))
    good = read_uvh5(plain)
    assert not np.array_equal(blocks[0].data, good.data)  # silently different values
    assert "data corruption cannot be detected" in caplog.text
    report = file_integrity(damaged)
    assert report["status"] == "unchecked"
    assert "cannot be detected" in report["note"]
    assert file_checksum(damaged) != file_checksum(plain)
    assert input_integrity("uvh5", [damaged]) == {str(damaged): report}
    assert input_integrity("miriad", [damaged]) is None


def test_a_file_that_is_not_hdf5_is_unknown(tmp_path: Path) -> None:
    path = tmp_path / "x.uvh5"
    path.write_bytes(b"not hdf5")
    assert file_integrity(path)["status"] == "unknown"
