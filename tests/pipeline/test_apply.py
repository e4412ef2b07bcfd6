"""``apply_solution``: real HERA autos calibrated with autocal's own solution, and refusals."""

from __future__ import annotations

import numpy as np
import pytest
from pyuvdata import UVCal, UVData

from autocal.core.files import file_checksum
from autocal.errors import AutocalError
from autocal.pipeline.apply import HISTORY_MARK, ApplyError, apply_solution
from tests.io.real_solution import real_products

pytestmark = [pytest.mark.slow, pytest.mark.data]


@pytest.fixture(scope="module")
def real(data_root, tmp_path_factory):
    return real_products(data_root, tmp_path_factory.mktemp("real"))


@pytest.mark.parametrize("kind", ["calh5", "calfits"])
def test_calibrated_autos_are_raw_over_gain_squared(real, tmp_path, kind) -> None:
    out = tmp_path / "calibrated.uvh5"
    solution = real.calh5 if kind == "calh5" else real.calfits
    result = apply_solution(solution, [real.band], out)
    assert result.path == out and result.vis_units == "K str"
    cal = UVData.from_file(str(out))  # pyuvdata reads it back with its checks
    raw = UVData.from_file(str(real.band))
    uvc = UVCal.from_file(str(solution))
    assert cal.vis_units == "K str" and cal.pol_convention == "avg"
    for jones, pol in zip(uvc.jones_array, ("ee", "nn"), strict=True):
        j = list(uvc.jones_array).index(jones)
        gain = uvc.gain_array[0, :, :, j].T  # (Ntime, Nfreq) of antenna 23
        gflag = uvc.flag_array[0, :, :, j].T
        expect = raw.get_data(23, 23, pol) / np.abs(gain) ** 2
        flags = cal.get_flags(23, 23, pol)
        np.testing.assert_array_equal(flags, raw.get_flags(23, 23, pol) | gflag)
        ok = ~flags
        assert ok.mean() > 0.5
        np.testing.assert_allclose(cal.get_data(23, 23, pol)[ok], expect[ok], rtol=1e-6)
        # the calibrated auto is Tsky + Trxr: hundreds of kelvin at 150-160 MHz
        assert 100 < np.median(cal.get_data(23, 23, pol)[ok].real) < 3000
    assert HISTORY_MARK in cal.history and file_checksum(solution) in cal.history
    assert str(real.band) in cal.history


def test_refuses_data_the_solution_does_not_cover(real, tmp_path) -> None:
    out = tmp_path / "x.uvh5"
    with pytest.raises(ApplyError, match=r"antenna\(s\) \[24, 25\]"):
        apply_solution(real.calh5, [real.raw], out)  # the file's crosses need 24 and 25
    with pytest.raises(ApplyError, match="not channels of the solution"):
        apply_solution(real.calh5, [real.auto], out)  # the whole band
    uvc = UVCal.from_file(str(real.calh5))
    uvc.select(jones=[-5])
    ee_only = tmp_path / "ee.calh5"
    uvc.write_calh5(str(ee_only))
    with pytest.raises(ApplyError, match=r"polarisation\(s\) \['nn'\]"):
        apply_solution(ee_only, [real.band], out)
    uvd = UVData.from_file(str(real.band))
    uvd.time_array = uvd.time_array + 1.0  # the next night
    uvd.set_lsts_from_time_array()
    other_night = tmp_path / "other.uvh5"
    uvd.write_uvh5(str(other_night))
    with pytest.raises(ApplyError, match="not times of the solution"):
        apply_solution(real.calh5, [other_night], out)
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == [
        "ee.calh5",
        "other.uvh5",
    ]


def test_refuses_corrupt_solution_and_foreign_output(real, tmp_path) -> None:
    out = tmp_path / "calibrated.uvh5"
    for kind, solution in (("calfits", real.calfits), ("calh5", real.calh5)):
        corrupt = tmp_path / f"corrupt.{kind}"
        corrupt.write_bytes(solution.read_bytes()[: solution.stat().st_size // 2])
        with pytest.raises(AutocalError):
            apply_solution(corrupt, [real.band], out)
        assert not out.exists()
    with pytest.raises(ApplyError, match="does not exist"):
        apply_solution(real.calh5, [tmp_path / "missing.uvh5"], out)
    foreign = tmp_path / "notes.uvh5"
    foreign.write_text("my notes")
    with pytest.raises(ApplyError, match="not a UVH5 file autocal wrote"):
        apply_solution(real.calh5, [real.band], foreign, overwrite=True)
    assert foreign.read_text() == "my notes"
    with pytest.raises(ApplyError, match="not written by autocal apply"):
        apply_solution(real.calh5, [real.band], real.band, overwrite=True)
    apply_solution(real.calh5, [real.band], out)
    first = out.read_bytes()
    with pytest.raises(ApplyError, match="--overwrite"):
        apply_solution(real.calfits, [real.band], out)
    assert out.read_bytes() == first
    apply_solution(real.calfits, [real.band], out, overwrite=True)
    assert file_checksum(real.calfits) in UVData.from_file(str(out)).history
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_freq_range_applies_a_solution_of_part_of_the_band(real, tmp_path) -> None:
    """The solution covers 150-160 MHz of a 100-200 MHz file: refused as it is, calibrated
    with --freq-range on the solution's band (the output holds those channels only), the
    same numbers as the band-matched file gives; a range outside the data names its band."""
    whole = tmp_path / "whole.uvh5"
    result = apply_solution(real.calh5, [real.auto], whole, freq_range_mhz=(150.0, 160.0))
    matched = apply_solution(real.calh5, [real.band], tmp_path / "matched.uvh5")
    assert result.nfreqs == matched.nfreqs < UVData.from_file(str(real.auto)).Nfreqs
    got, want = UVData.from_file(str(whole)), UVData.from_file(str(tmp_path / "matched.uvh5"))
    np.testing.assert_array_equal(got.freq_array, want.freq_array)
    np.testing.assert_array_equal(got.data_array, want.data_array)
    np.testing.assert_array_equal(got.flag_array, want.flag_array)
    with pytest.raises(ApplyError, match=r"keeps no channel of the data \(100\.000-199\.902 MHz\)"):
        apply_solution(real.calh5, [real.auto], tmp_path / "x.uvh5", freq_range_mhz=(250, 300))
    assert not (tmp_path / "x.uvh5").exists()
