"""autocal's calfits/calh5 read, applied and smoothed by hera_cal 3.8 and pyuvdata.

hera_cal (``hera-calibration``) is a dev dependency that CI installs; on a machine without
it these tests are skipped with that reason.
"""

from __future__ import annotations

import numpy as np
import pytest
from pyuvdata import UVCal, UVData
from pyuvdata.utils import uvcalibrate

from tests.io.real_solution import real_products

hera_io = pytest.importorskip(
    "hera_cal.io", reason="hera_cal is not installed (pip install -e .[dev] installs it)"
)
apply_cal = pytest.importorskip("hera_cal.apply_cal", reason="hera_cal is not installed")
smooth_cal = pytest.importorskip("hera_cal.smooth_cal", reason="hera_cal is not installed")

pytestmark = [pytest.mark.slow, pytest.mark.data]


@pytest.fixture(scope="module")
def real(data_root, tmp_path_factory):
    return real_products(data_root, tmp_path_factory.mktemp("real"))


def test_heracal_reads_the_calfits(real) -> None:
    uvc = UVCal.from_file(str(real.calfits))
    hc = hera_io.HERACal(str(real.calfits))
    gains, flags, quals, total = hc.read()
    assert sorted(gains) == [(23, "Jee"), (23, "Jnn")]
    data_times = np.unique(UVData.from_file(str(real.band)).time_array)
    assert hc.times.size == data_times.size > 1
    np.testing.assert_allclose(hc.times, data_times, atol=1e-8)
    np.testing.assert_allclose(hc.freqs, uvc.freq_array)
    for j, name in enumerate(uvc.jones_array):
        key = (23, "Jee" if name == -5 else "Jnn")
        np.testing.assert_array_equal(gains[key], uvc.gain_array[0, :, :, j].T)
        np.testing.assert_array_equal(flags[key], uvc.flag_array[0, :, :, j].T)
        np.testing.assert_array_equal(quals[key], uvc.quality_array[0, :, :, j].T)
        assert gains[key].shape == (hc.times.size, hc.freqs.size)
        assert np.mean(flags[key]) < 0.5 and np.all(quals[key][~flags[key]] > 0)
    assert set(total) == {"Jee", "Jnn"}


def test_heracal_reads_calfits_only(real) -> None:
    """hera_cal 3.8's HERACal reads calfits; calh5 is for pyuvdata (documented)."""
    with pytest.raises(Exception, match="SIMPLE"):
        hera_io.HERACal(str(real.calh5)).read()


def test_hera_cal_and_pyuvdata_calibrate_alike(real, tmp_path) -> None:
    out = tmp_path / "hera_cal.uvh5"
    apply_cal.apply_cal(
        str(real.band),
        str(out),
        str(real.calfits),
        filetype_in="uvh5",
        filetype_out="uvh5",
    )
    by_hera = UVData.from_file(str(out))
    raw = UVData.from_file(str(real.band))
    for solution in (real.calfits, real.calh5):
        by_pyuvdata = uvcalibrate(raw, UVCal.from_file(str(solution)), inplace=False)
        by_pyuvdata.check()
        assert by_pyuvdata.vis_units == "K str" and by_pyuvdata.pol_convention == "avg"
        written = tmp_path / f"pyuvdata_{solution.suffix[1:]}.uvh5"
        by_pyuvdata.write_uvh5(str(written))
        back = UVData.from_file(str(written))
        assert by_hera.vis_units == back.vis_units == "K str"
        for pol in ("ee", "nn"):
            flags = back.get_flags(23, 23, pol)
            np.testing.assert_array_equal(by_hera.get_flags(23, 23, pol), flags)
            np.testing.assert_allclose(
                by_hera.get_data(23, 23, pol)[~flags], back.get_data(23, 23, pol)[~flags]
            )
            assert not np.allclose(back.get_data(23, 23, pol), raw.get_data(23, 23, pol))


def test_smooth_cal_smooths_the_calfits(real, tmp_path) -> None:
    cal = tmp_path / "solution.calfits"
    cal.write_bytes(real.calfits.read_bytes())
    smoother = smooth_cal.CalibrationSmoother([str(cal)])
    smoother.time_freq_2D_filter(freq_scale=10.0, time_scale=1800.0)
    smoother.write_smoothed_cal(output_replace=(".calfits", ".smooth.calfits"))
    smoothed = tmp_path / "solution.smooth.calfits"
    gains, _, _, _ = hera_io.HERACal(str(smoothed)).read()
    original, oflags, _, _ = hera_io.HERACal(str(cal)).read()
    for key, gain in gains.items():
        assert gain.shape == original[key].shape
        ok = ~oflags[key]
        assert np.all(np.isfinite(gain[ok]))
        # smoothing keeps the level of the gains and removes channel-to-channel scatter
        ratio = np.abs(gain[ok]) / np.abs(original[key][ok])
        assert abs(np.median(ratio) - 1) < 0.05
        rough = np.nanmedian(np.abs(np.diff(np.where(ok, np.abs(original[key]), np.nan), axis=1)))
        smooth = np.nanmedian(np.abs(np.diff(np.where(ok, np.abs(gain), np.nan), axis=1)))
        assert smooth < 0.5 * rough
    smoothed_uvc = UVCal.from_file(str(smoothed))  # pyuvdata reads hera_cal's output too
    assert smoothed_uvc.gain_scale == "K str"
