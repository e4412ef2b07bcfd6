"""A UVH5 file's header read with h5py alone: what autocal uses of it, without pyuvdata.

Scanning a file used to build a pyuvdata ``UVData`` with ``read_data=False``; importing
pyuvdata (numba, its compiled helpers, astropy's coordinates) cost a fresh process about a
second and a half before the first byte of data was read. :func:`read_plain_header` reads
the same fields straight from the file's ``Header`` group when the header has its usual
plain form (a geodetic telescope location on Earth, LSTs stored, consistent row counts) and
returns ``None`` otherwise, so the caller falls back to pyuvdata, which also gives the
error messages for broken headers.

The values are pyuvdata's own: the site goes through the same WGS84 geodetic -> ECEF ->
geodetic round trip as its ``EarthLocation`` (equal to the bit), the feeds' orientation is
derived from ``feed_array``/``feed_angle`` as ``pyuvdata.utils.pol`` derives it, extra
keywords and ``vis_units`` are decoded as its ``HDF5Meta`` decodes them. One field differs on
purpose: ``history`` is the file's as written, without the "Read/written with pyuvdata"
line pyuvdata appends on reading (autocal did not read it with pyuvdata).
``tests/io/test_uvh5_header.py`` compares both paths field by field on every real UVH5 file
of the shared data and on files pyuvdata writes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal.core.sites import Site

logger = logging.getLogger(__name__)

#: pyuvdata's tolerance on the feed angles (radians, absolute) when its ``Telescope``
#: derives the x orientation.
FEED_ANGLE_ATOL = 1e-6

#: The datasets a plain header needs (those pyuvdata requires, and the LSTs); without one
#: of them the scan goes through pyuvdata, which reads the header or says what is wrong.
REQUIRED = (
    "ant_1_array",
    "ant_2_array",
    "time_array",
    "lst_array",
    "integration_time",
    "freq_array",
    "channel_width",
    "spw_array",
    "polarization_array",
    "latitude",
    "longitude",
    "altitude",
    "telescope_name",
    "instrument",
    "antenna_numbers",
    "antenna_names",
    "antenna_positions",
    "history",
    "Nblts",
    "Nbls",
    "Ntimes",
    "Nfreqs",
    "Npols",
    "Nspws",
    "Nants_data",
    "Nants_telescope",
)


@dataclass(frozen=True)
class UVH5Header:
    """The header fields of one UVH5 file that autocal keeps after the scan.

    Made by :func:`read_plain_header` (h5py) or :func:`header_from_uvdata` (pyuvdata's
    ``UVData`` with ``read_data=False``). Holds nothing per baseline-time row, so the
    headers of every file of a night take little memory.
    """

    telescope_name: str
    site: Site
    antenna_numbers: tuple[int, ...]
    antenna_names: tuple[str, ...]
    x_orientation: str | None
    vis_units: str
    history: str
    extra_keywords: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class HeaderArrays:
    """The per-row and per-axis arrays the scan reduces (time, antennas, channels, pols)."""

    ant_1: np.ndarray
    ant_2: np.ndarray
    times: np.ndarray
    lsts_rad: np.ndarray
    freqs: np.ndarray
    channel_width: np.ndarray
    pol_codes: list[int]


def _text(value: Any) -> str:
    return bytes(value).decode("utf8")


#: astropy's unit scales (``u.deg.to(u.rad)``, ``u.rad.to(u.deg)``) and its 360 degrees in
#: radians (``u.deg.to(u.rad, 360.0)``), as its angles use them.
_D2R = 0.017453292519943295
_R2D = 57.29577951308232
_A360 = _D2R * 360.0


def _wrap_at(angle: float, wrap: float, a360: float) -> float:
    """Wrap ``angle`` into ``[wrap - a360, wrap)`` as astropy's ``Angle.wrap_at`` does."""
    floor = wrap - a360
    if floor <= angle < wrap or not np.isfinite(angle):
        return angle
    angle = angle - ((angle - floor) // a360) * a360
    if angle >= wrap:
        angle -= a360
    if angle < floor:
        angle += a360
    return angle


def geodetic_site(name: str, lat_deg: float, lon_deg: float, alt_m: float) -> Site:
    """Return the :class:`Site` pyuvdata's ``EarthLocation`` gives for a geodetic location.

    pyuvdata builds the location from geodetic coordinates (WGS84, to ECEF) and autocal read
    them back (ECEF to geodetic); the round trip moves them by ~1e-14 deg and ~1e-9 m,
    enough to change a cache key built from them. These are astropy's steps: the longitude
    wrapped at 180 deg and then at 360 deg, ERFA's ``gd2gc``, ``gc2gd``, the longitude wrapped
    at 360 deg in radians and at 180 deg in degrees, with astropy's unit scales; so the
    values are the same to the bit (``tests/io/test_uvh5_header.py``, against astropy for
    sites all round the Earth).
    """
    import erfa

    lon_in = _wrap_at(_wrap_at(lon_deg, 180.0, 360.0), 360.0, 360.0)
    xyz = erfa.gd2gc(1, lon_in * _D2R, lat_deg * _D2R, alt_m)
    elong, phi, height = erfa.gc2gd(1, xyz)
    lon = _wrap_at(_wrap_at(float(elong), _A360, _A360) * _R2D, 180.0, 360.0)
    return Site(name.strip().lower() or "unknown", float(phi) * _R2D, lon, float(height))


def x_orientation_of_feeds(feed_array: np.ndarray, feed_angle: np.ndarray) -> str | None:
    """``"east"``/``"north"`` from the feeds as pyuvdata derives it; None if neither fits."""
    x_mask = np.isin(np.char.decode(np.asarray(feed_array, dtype="S"), "utf8"), ["x", "X"])
    angle = np.mod(np.asarray(feed_angle, dtype=np.float64) + np.pi / 4, np.pi) - np.pi / 4
    if np.allclose(angle, np.where(x_mask, np.pi / 2, 0), rtol=0, atol=FEED_ANGLE_ATOL):
        return "east"
    if np.allclose(angle, np.where(x_mask, 0, np.pi / 2), rtol=0, atol=FEED_ANGLE_ATOL):
        return "north"
    return None


def _x_orientation(header: h5py.Group) -> tuple[bool, str | None]:
    """(plain, orientation): the feeds' orientation, or plain=False for an unusual form.

    Without feed information pyuvdata takes the feeds of a telescope it knows (MWA, ATA,
    OVRO-LWA ... "east"): such a header is left to it.
    """
    if "feed_array" in header and "feed_angle" in header:
        return True, x_orientation_of_feeds(header["feed_array"][()], header["feed_angle"][()])
    if "x_orientation" in header:
        value = _text(header["x_orientation"][()]).lower()
        return value in ("east", "north"), value  # "e", "ew" ...: pyuvdata maps them
    return False, None


def _extra_keywords(header: h5py.Group) -> dict[str, Any]:
    if "extra_keywords" not in header:
        return {}
    out: dict[str, Any] = {}
    for key, dset in header["extra_keywords"].items():
        if dset.dtype.type in (np.bytes_, np.object_):
            out[key] = _text(dset[()])
        else:
            out[key] = None if dset.shape is None else dset[()]
    return out


def read_plain_header(path: Path) -> tuple[UVH5Header, HeaderArrays] | None:
    """Read a UVH5 header with h5py, or return None when it is not in the plain form.

    Parameters
    ----------
    path
        A UVH5 file already checked to be HDF5 with ``Header`` and ``Data`` groups.

    Returns
    -------
    tuple of UVH5Header and HeaderArrays, or None
        None when a field is missing or unusual (no stored LSTs or another field pyuvdata
        requires, an ECEF or lunar telescope location, a latitude beyond +-90 deg, no feed
        information or an x orientation spelt otherwise than east/north, row or channel
        counts that disagree): pyuvdata then reads the header and reports what is wrong
        with it.
    """
    try:
        with h5py.File(path, "r") as h5:
            return _read(h5["Header"])
    except (KeyError, OSError, RuntimeError, ValueError, TypeError, UnicodeDecodeError) as err:
        logger.debug("%s: header read through pyuvdata (%s)", path.name, err)
        return None


def _read(header: h5py.Group) -> tuple[UVH5Header, HeaderArrays] | None:
    if any(name not in header for name in REQUIRED):
        return None
    if "telescope_frame" in header and _text(header["telescope_frame"][()]) != "itrs":
        return None
    plain, orientation = _x_orientation(header)
    if not plain:
        return None
    nblts = int(header["Nblts"][()])
    rows = [np.asarray(header[k][()]) for k in ("ant_1_array", "ant_2_array", "time_array")]
    lsts = np.asarray(header["lst_array"][()], dtype=np.float64)
    if any(a.shape != (nblts,) for a in [*rows, lsts]):
        return None
    freq_array = np.asarray(header["freq_array"][()], dtype=np.float64)
    freqs = freq_array.ravel()
    width = np.asarray(header["channel_width"][()], dtype=np.float64).ravel()
    codes = [int(c) for c in np.asarray(header["polarization_array"][()]).ravel()]
    if freqs.size != int(header["Nfreqs"][()]):
        return None
    # a file of the current form (1-D freq_array) has a width per channel; an older one
    # (2-D, one window) one width
    if width.size != (freqs.size if freq_array.ndim == 1 else 1):
        return None
    if len(codes) != int(header["Npols"][()]):
        return None
    numbers = tuple(int(n) for n in np.asarray(header["antenna_numbers"][()]).ravel())
    names = tuple(_text(n) for n in np.asarray(header["antenna_names"][()]).ravel())
    if len(numbers) != len(names):
        return None
    telescope = _text(header["telescope_name"][()])
    vis_units = _text(header["vis_units"][()]) if "vis_units" in header else "uncalib"
    lat, lon, alt = (float(header[k][()]) for k in ("latitude", "longitude", "altitude"))
    if not (-90.0 <= lat <= 90.0 and np.isfinite(lon) and np.isfinite(alt)):
        return None  # pyuvdata refuses it, and says why
    site = geodetic_site(telescope, lat, lon, alt)
    out = UVH5Header(
        telescope_name=telescope,
        site=site,
        antenna_numbers=numbers,
        antenna_names=names,
        x_orientation=orientation,
        vis_units="uncalib" if vis_units == "UNCALIB" else vis_units,
        history=_text(header["history"][()]),
        extra_keywords=_extra_keywords(header),
    )
    arrays = HeaderArrays(
        ant_1=rows[0],
        ant_2=rows[1],
        times=np.asarray(rows[2], dtype=np.float64),
        lsts_rad=lsts,
        freqs=freqs,
        channel_width=np.broadcast_to(width, freqs.shape).copy(),
        pol_codes=codes,
    )
    return out, arrays


def header_from_uvdata(
    uv: Any, orientation: str | None, history: str | None = None
) -> tuple[UVH5Header, HeaderArrays]:
    """Return the same records from a pyuvdata ``UVData`` read with ``read_data=False``.

    ``history``: the file's own (pyuvdata's has its "Read/written with pyuvdata" line
    appended); pyuvdata's when not given.
    """
    loc = uv.telescope.location
    try:
        lat, lon = float(loc.lat.deg), float(loc.lon.deg)
        alt = float(loc.height.to_value("m"))
    except AttributeError as err:  # pragma: no cover - non-Earth telescopes
        from autocal.io.uvh5_meta import UVH5FormatError

        raise UVH5FormatError(f"telescope location {loc!r} is not a geodetic location") from err
    telescope = uv.telescope
    header = UVH5Header(
        telescope_name=str(telescope.name),
        site=Site(str(telescope.name or "").strip().lower() or "unknown", lat, lon, alt),
        antenna_numbers=tuple(int(n) for n in telescope.antenna_numbers),
        antenna_names=tuple(str(n) for n in telescope.antenna_names),
        x_orientation=orientation,
        vis_units=str(uv.vis_units),
        history=str(uv.history or "") if history is None else history,
        extra_keywords=dict(uv.extra_keywords),
    )
    freqs = np.asarray(uv.freq_array, dtype=np.float64).ravel()
    width = np.asarray(uv.channel_width, dtype=np.float64).ravel()
    arrays = HeaderArrays(
        ant_1=np.asarray(uv.ant_1_array),
        ant_2=np.asarray(uv.ant_2_array),
        times=np.asarray(uv.time_array, dtype=np.float64),
        lsts_rad=np.asarray(uv.lst_array, dtype=np.float64),
        freqs=freqs,
        channel_width=np.broadcast_to(width, freqs.shape).copy(),
        pol_codes=[int(c) for c in np.asarray(uv.polarization_array).ravel()],
    )
    return header, arrays
