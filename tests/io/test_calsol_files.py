"""Calibration files recognised by content: corrupt, foreign and non-calibration files refused."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest

import autocal  # noqa: F401  (offline configuration first)
from autocal.io.calsol_files import CalsolFormatError
from autocal.io.calsol_read import read_reference_gains
from autocal.io.calsol_write import write_calfits, write_calh5
from tests.io.test_calsol import H1C_ABS, REF, make_solution


def test_corrupt_and_foreign_files_raise_clear_errors(tmp_path):
    empty = tmp_path / "empty.calfits"
    empty.write_bytes(b"")
    junk = tmp_path / "junk.calh5"
    junk.write_bytes(b"this is not a calibration file\n" * 10)
    other_h5 = tmp_path / "other.h5"
    with h5py.File(other_h5, "w") as h5:
        h5["x"] = np.arange(3)
    good = write_calh5(make_solution(), tmp_path / "good.calh5")
    truncated = tmp_path / "truncated.calh5"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    good_fits = write_calfits(make_solution(), tmp_path / "good.calfits")
    truncated_fits = tmp_path / "truncated.calfits"
    truncated_fits.write_bytes(good_fits.read_bytes()[: good_fits.stat().st_size // 2])
    cases = {
        tmp_path / "missing.calfits": "does not exist",
        tmp_path: "directory",
        empty: "empty",
        junk: "neither FITS nor HDF5",
        other_h5: "not calh5",
        truncated: "truncated or corrupt",
        truncated_fits: "corrupt|truncated",
    }
    for path, message in cases.items():
        with pytest.raises(CalsolFormatError, match=message):
            read_reference_gains(path)
    assert issubclass(CalsolFormatError, ValueError)


@pytest.mark.data
def test_visibility_beam_and_product_files_are_not_calibration(data_root, tmp_path):
    from autocal.io.products import write_solution

    with pytest.raises(CalsolFormatError, match="UVH5"):
        read_reference_gains(data_root / "hera/autos/zen.2458116.30448.HH.uvh5")
    with pytest.raises(CalsolFormatError, match="not calfits"):
        read_reference_gains(data_root / "hera/beams/HERA_NF_dipole_power.beamfits")
    product = write_solution(make_solution(), tmp_path / "sol.h5")
    with pytest.raises(CalsolFormatError, match="autocal product"):
        read_reference_gains(product)
    # a truncated real calfits
    src = data_root / REF / H1C_ABS[0]
    cut = tmp_path / "cut.calfits"
    shutil.copyfile(src, cut)
    with open(cut, "r+b") as handle:
        handle.truncate(src.stat().st_size // 3)
    with pytest.raises(CalsolFormatError, match=r"corrupt|truncated"):
        read_reference_gains(cut)
