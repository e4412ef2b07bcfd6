"""The h5py header scan against pyuvdata's, field by field (real files and pyuvdata's own)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from autocal.io.pyuvdata_helpers import uvdata_class
from autocal.io.pyuvdata_helpers import x_orientation as feed_orientation
from autocal.io.uvh5 import write_uvh5
from autocal.io.uvh5_header import header_from_uvdata, read_plain_header
from autocal.io.uvh5_meta import read_file_meta, scan_uvh5
from tests.io.test_uvh5 import AUTOS, synthetic_observation

PYUVDATA_NOTE = "Read/written with pyuvdata version"


def _through_pyuvdata(path):
    uv = uvdata_class().from_file(str(path), file_type="uvh5", read_data=False)
    return header_from_uvdata(uv, feed_orientation(uv.telescope))


def _assert_same(path) -> None:
    plain = read_plain_header(path)
    assert plain is not None, f"{path.name}: the plain h5py scan gave up"
    fast, fast_arrays = plain
    slow, slow_arrays = _through_pyuvdata(path)
    assert fast.site == slow.site  # to the bit: the Tsky cache key is built from it
    assert fast.telescope_name == slow.telescope_name
    assert fast.antenna_numbers == slow.antenna_numbers
    assert fast.antenna_names == slow.antenna_names
    assert fast.x_orientation == slow.x_orientation
    assert fast.vis_units == slow.vis_units
    # pyuvdata appends its own line on reading (unless the file has it): the rest is equal
    assert slow.history.startswith(fast.history)
    assert slow.history == fast.history or PYUVDATA_NOTE in slow.history[len(fast.history) :]
    assert fast.extra_keywords.keys() == slow.extra_keywords.keys()
    for key, value in fast.extra_keywords.items():
        np.testing.assert_array_equal(value, slow.extra_keywords[key])
    for name in ("ant_1", "ant_2", "times", "lsts_rad", "freqs", "channel_width"):
        np.testing.assert_array_equal(getattr(fast_arrays, name), getattr(slow_arrays, name))
    assert fast_arrays.pol_codes == slow_arrays.pol_codes


@pytest.mark.data
def test_every_real_uvh5_file_scans_as_pyuvdata_reads_it(data_root) -> None:
    """Old (2017, ``x_orientation``, 2-D ``freq_array``) and newer HERA headers alike."""
    paths = sorted((data_root / AUTOS).glob("*.uvh5*"))
    assert len(paths) >= 10
    for path in paths:
        _assert_same(path)


def test_files_pyuvdata_writes_scan_as_pyuvdata_reads_them(tmp_path) -> None:
    """Newer headers (``feed_array``/``feed_angle``), extra keywords of every kind."""
    keywords = {"int": 3, "float": 2.5, "text": "night 1", "flag": True}
    path = write_uvh5(synthetic_observation(), tmp_path / "a.uvh5", extra_keywords=keywords)
    _assert_same(path)
    fast, _ = read_plain_header(path)
    assert fast.extra_keywords["text"] == "night 1" and fast.extra_keywords["int"] == 3


def _edit_header(path, edit) -> None:
    with h5py.File(path, "r+") as h5:
        edit(h5["Header"])


def _replace(header, name, value) -> None:
    if name in header:
        del header[name]
    header[name] = value


def _no_feeds(header) -> None:
    for name in ("feed_array", "feed_angle", "x_orientation"):
        if name in header:
            del header[name]


@pytest.mark.parametrize(
    "edit",
    [
        lambda h: h.__delitem__("lst_array"),  # pyuvdata computes LSTs (astropy)
        lambda h: h.__delitem__("latitude"),  # an old ECEF location
        lambda h: _replace(h, "telescope_frame", np.bytes_("mcmf")),  # on the Moon
        lambda h: _replace(h, "latitude", 100.0),  # pyuvdata refuses it
        lambda h: h.__delitem__("history"),  # pyuvdata requires one
        lambda h: h.__delitem__("integration_time"),
        lambda h: _replace(h, "channel_width", 97656.25),  # 1-D freq_array: one per channel
        _no_feeds,  # pyuvdata takes a known telescope's feeds
    ],
    ids=[
        "no-lsts",
        "no-latitude",
        "lunar-frame",
        "latitude-100",
        "no-history",
        "no-integration-time",
        "scalar-width",
        "no-feeds",
    ],
)
def test_unusual_headers_go_through_pyuvdata(tmp_path, edit) -> None:
    """Anything but the plain form is left to pyuvdata (which reads it or says why not)."""
    path = write_uvh5(synthetic_observation(), tmp_path / "a.uvh5")
    _edit_header(path, edit)
    assert read_plain_header(path) is None


def test_a_header_without_lsts_is_scanned_through_pyuvdata(tmp_path) -> None:
    """The fallback gives the same scan as the plain path gave before the edit (the site,
    the names, the file's own history without pyuvdata's line)."""
    path = write_uvh5(synthetic_observation(), tmp_path / "a.uvh5")
    before = scan_uvh5([path])[0]
    _edit_header(path, lambda h: h.__delitem__("lst_array"))
    after = scan_uvh5([path])[0]
    assert after.site == before.site and after.pols == before.pols
    assert after.header.header == before.header.header
    np.testing.assert_allclose(after.lsts, before.lsts, atol=1e-6)  # pyuvdata's LSTs, hours


def test_without_feeds_the_orientation_is_pyuvdatas(tmp_path) -> None:
    """A header without feed information is read through pyuvdata, which may know the
    telescope's feeds: the scan names the polarisations as pyuvdata does."""
    path = write_uvh5(synthetic_observation(), tmp_path / "a.uvh5")
    _edit_header(path, _no_feeds)
    assert read_plain_header(path) is None
    meta = read_file_meta(path)
    slow, slow_arrays = _through_pyuvdata(path)
    assert meta.x_orientation == slow.x_orientation
    assert meta.pol_codes == slow_arrays.pol_codes


def test_the_site_is_astropys_all_round_the_earth() -> None:
    """West and east, across the date line, beyond +-180 deg: EarthLocation's values, bit
    for bit (they key the Tsky cache)."""
    import astropy.units as u
    from astropy.coordinates import EarthLocation

    from autocal.io.uvh5_header import geodetic_site

    rng = np.random.default_rng(5)
    lons = [-360.0, -180.0, -118.2817, -107.6184, -0.0, 0.0, 21.4278, 180.0, 359.999]
    lons += rng.uniform(-360.0, 360.0, 400).tolist()
    for lon in lons:
        lat, alt = float(rng.uniform(-90.0, 90.0)), float(rng.uniform(-400.0, 5000.0))
        loc = EarthLocation.from_geodetic(lon=lon * u.deg, lat=lat * u.deg, height=alt * u.m)
        site = geodetic_site("x", lat, lon, alt)
        want = (float(loc.lat.deg), float(loc.lon.deg), float(loc.height.to_value("m")))
        assert (site.lat_deg, site.lon_deg, site.alt_m) == want, (lat, lon, alt)


def test_inconsistent_row_counts_leave_the_error_to_pyuvdata(tmp_path) -> None:
    """A header whose rows disagree is not read by h5py; pyuvdata's error reaches the user."""
    from autocal.io.uvh5_meta import UVH5FormatError

    path = write_uvh5(synthetic_observation(), tmp_path / "a.uvh5")

    _edit_header(path, lambda h: _replace(h, "time_array", h["time_array"][()][:-1]))
    assert read_plain_header(path) is None
    with pytest.raises(UVH5FormatError, match="pyuvdata cannot read the UVH5 header"):
        read_file_meta(path)
