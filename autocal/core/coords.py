"""Coordinate conventions and transforms used by the sky and Tsky modules.

Conventions (used everywhere in autocal):

* Sky maps are HEALPix, RING ordering, in the *apparent equatorial frame of the
  observation epoch* (astropy ``TETE``: true equator and equinox of date, sources at their
  apparent places, i.e. with annual aberration), the frame in which the apparent local
  sidereal time stored in UVH5 files is defined. HEALPix
  ``theta`` is the colatitude (90 deg - Dec) and ``phi`` is the right ascension.
* Topocentric directions are (azimuth, altitude) with the azimuth measured from north
  through east (astropy's convention). pyuvdata's UVBeam uses azimuth from east through
  north; conversions are explicit in :mod:`autocal.sky`.
* Hour angle H = LST - RA, positive west of the meridian.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from astropy.time import Time

from autocal.core.lazy import healpy as hp
from autocal.core.stopping import checkpoint
from autocal.errors import AutocalError

J2000 = "J2000"


class EpochError(AutocalError):
    """An epoch or a set of times that is not a usable date."""


def parse_epoch(epoch: str | float | Time | None) -> Time:
    """Parse an epoch given as a :class:`~astropy.time.Time`, ``"J2000"``, an ISO date or a JD.

    Parameters
    ----------
    epoch
        ``None`` or ``"J2000"`` gives J2000.0; a number > 2e6 is a Julian date.

    Returns
    -------
    astropy.time.Time
        The epoch (UTC scale).
    """
    if isinstance(epoch, Time):
        return epoch
    if epoch is None or (isinstance(epoch, str) and epoch.strip().upper() == J2000):
        return Time("J2000", scale="utc")
    if isinstance(epoch, (int, float, np.floating)):
        if epoch < 2e6:
            raise EpochError(f"epoch {epoch} is not a Julian date (expected > 2e6)")
        return Time(float(epoch), format="jd", scale="utc")
    try:
        value = float(epoch)
    except ValueError:
        try:
            return Time(epoch, scale="utc")
        except ValueError as err:
            raise EpochError(
                f"cannot parse epoch {epoch!r}: give 'J2000', an ISO date such as "
                "'2018-01-01T00:00:00' or a Julian date"
            ) from err
    return parse_epoch(value)


#: Longest span of data (days) given the frame of their night by :func:`night_epoch`.
NIGHT_SPAN_DAYS = 0.5


def night_epoch(jds: np.ndarray | list[float] | float, lon_deg: float) -> float:
    """Return the epoch of the sky frame for data taken at ``jds``: their night's local midnight.

    The night is the one containing the data's mean time, counted from local mean noon to
    the next local mean noon at longitude ``lon_deg``; the epoch is that night's local
    mean midnight (a JD). Every observation of one night therefore gets the same epoch,
    so their Tsky share one set of LST harmonics (:func:`autocal.tsky.compute.compute_tsky`'s
    cache), and a night is never split however its files are grouped. Data spanning more
    than :data:`NIGHT_SPAN_DAYS` (an EDGES day file, several nights) have nothing to share
    and keep their mean time, so the frame stays within half their span. For a night's
    data the frame is within ~12 h of every sample; precession and nutation move it by
    < 0.1 arcsec in that time, which changes a HERA-beam GSM2008 Tsky by at most 4.9 mK
    (2e-6 of Tsky) at nside 128 over a day of LSTs (``python benchmarks/observations.py
    --parts frame``; tested at a coarser resolution in ``tests/tsky/test_tsky_harmonics.py``).

    Parameters
    ----------
    jds
        Julian dates (UTC) of the data.
    lon_deg
        Site longitude, degrees east.

    Returns
    -------
    float
        The JD of the night's local mean midnight (or the data's mean time for spans
        over :data:`NIGHT_SPAN_DAYS`).

    Raises
    ------
    EpochError
        If ``jds`` is empty or not finite, or not a Julian date.
    """
    arr = np.asarray(jds, dtype=np.float64).ravel()
    if arr.size == 0 or not np.all(np.isfinite(arr)):
        raise EpochError("the epoch needs at least one finite Julian date")
    mean = float(arr.mean())
    if mean < 2e6:
        raise EpochError(f"time {mean} is not a Julian date (expected > 2e6)")
    if np.ptp(arr) > NIGHT_SPAN_DAYS:
        return mean
    # local mean solar time as a "local JD" (integer at local mean noon, like the JD at
    # Greenwich noon): the night is its integer part, its midnight that + 0.5
    offset = lon_deg / 360.0
    return float(np.floor(mean + offset) + 0.5 - offset)


@lru_cache(maxsize=1)
def _icrs_to_galactic() -> np.ndarray:
    """Return the fixed rotation from ICRS to Galactic unit vectors (astropy's definition)."""
    from astropy import units as u
    from astropy.coordinates import ICRS, Galactic, SkyCoord

    axes = SkyCoord(
        ra=[0.0, 90.0, 0.0] * u.deg, dec=[0.0, 0.0, 90.0] * u.deg, frame=ICRS()
    ).transform_to(Galactic())
    return np.array(axes.cartesian.xyz.value)  # column k: the image of ICRS axis k


@lru_cache(maxsize=32)
def _apparent_context(jd: float) -> tuple[np.ndarray, np.void]:
    """Return the precession-nutation matrix (GCRS -> TETE) and ERFA's geocentric astrometry."""
    import erfa

    epoch = Time(jd, format="jd", scale="utc")
    rbpn = erfa.pnm06a(epoch.tt.jd1, epoch.tt.jd2)
    astrom = erfa.apcg13(epoch.tdb.jd1, epoch.tdb.jd2)
    return np.asarray(rbpn), astrom


def galactic_to_equatorial_matrix(epoch: str | float | Time | None = None) -> np.ndarray:
    """Rotation taking Galactic unit vectors to the true equator and equinox of ``epoch``.

    This is the frame's rotation only (frame bias, precession, nutation); the apparent
    place of a source also has annual aberration (up to 20.5 arcsec) and light deflection,
    which are not rotations: :func:`apparent_to_galactic` includes them.

    Parameters
    ----------
    epoch
        Observation epoch (see :func:`parse_epoch`).

    Returns
    -------
    numpy.ndarray
        ``(3, 3)`` matrix ``R`` with ``v_eq = R @ v_gal``.
    """
    rbpn, _ = _apparent_context(float(parse_epoch(epoch).jd))
    return rbpn @ _icrs_to_galactic().T


def apparent_to_galactic(vec_eq: np.ndarray, epoch: str | float | Time | None = None) -> np.ndarray:
    """Galactic directions of the sources seen in apparent equatorial directions at ``epoch``.

    The apparent frame is astropy's ``TETE`` (geocentric, true equator and equinox of
    date): the inverse of the bias-precession-nutation rotation (ERFA ``pnm06a``) is
    applied, then the annual aberration and the Sun's light deflection are removed
    (ERFA ``aticq``, the inverse of what astropy applies from ICRS to GCRS), then ICRS is
    rotated to Galactic. Diurnal aberration (< 0.32 arcsec) and polar motion are left
    out, as in the apparent sidereal time of UVH5 files. Agrees with astropy's
    ``TETE -> Galactic`` transformation to < 1 mas (``tests/core/test_coords.py``) at
    a fraction of its cost.

    Parameters
    ----------
    vec_eq
        ``(3, N)`` unit vectors in the apparent equatorial frame.
    epoch
        Observation epoch (see :func:`parse_epoch`).

    Returns
    -------
    numpy.ndarray
        ``(3, N)`` Galactic unit vectors.
    """
    import erfa

    rbpn, astrom = _apparent_context(float(parse_epoch(epoch).jd))
    gcrs = rbpn.T @ np.asarray(vec_eq, dtype=np.float64).reshape(3, -1)
    ra, dec = erfa.c2s(gcrs.T)
    ri, di = erfa.aticq(ra, dec, astrom)
    return _icrs_to_galactic() @ erfa.s2c(ri, di).T


def healpix_ra_dec(nside: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the (RA, Dec) in radians of every RING pixel of an equatorial map."""
    theta, phi = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    return phi, np.pi / 2 - theta


def hadec_to_altaz(ha: np.ndarray, dec: np.ndarray, lat: float) -> tuple[np.ndarray, np.ndarray]:
    """Convert hour angle and declination to altitude and azimuth (east of north).

    Parameters
    ----------
    ha, dec
        Hour angle and declination in radians (broadcastable).
    lat
        Site latitude in radians.

    Returns
    -------
    alt, az
        Altitude and azimuth in radians; azimuth in ``[0, 2 pi)`` from north through east.
    """
    sin_lat, cos_lat = np.sin(lat), np.cos(lat)
    sin_dec, cos_dec = np.sin(dec), np.cos(dec)
    cos_ha = np.cos(ha)
    sin_alt = sin_dec * sin_lat + cos_dec * cos_ha * cos_lat
    alt = np.arcsin(np.clip(sin_alt, -1.0, 1.0))
    # east component, north component of the direction in the local tangent plane
    east = -cos_dec * np.sin(ha)
    north = sin_dec * cos_lat - cos_dec * cos_ha * sin_lat
    az = np.mod(np.arctan2(east, north), 2 * np.pi)
    return alt, az


def resample_healpix(maps: np.ndarray, nside_out: int, source_vec: np.ndarray) -> np.ndarray:
    """Sample HEALPix maps at given directions of their own frame, one per output pixel.

    Maps are first area-averaged to ``nside_out`` if they are finer (so no aliasing),
    then bilinearly interpolated at ``source_vec``.

    Parameters
    ----------
    maps
        ``(Ncomp, Npix_in)`` RING maps.
    nside_out
        Output HEALPix resolution.
    source_vec
        ``(3, 12 nside_out^2)`` unit vectors, in the maps' frame, of the output pixels.

    Returns
    -------
    numpy.ndarray
        ``(Ncomp, 12 nside_out^2)`` RING maps.
    """
    maps = np.atleast_2d(np.asarray(maps, dtype=np.float64))
    nside_in = hp.npix2nside(maps.shape[1])
    if nside_in > nside_out:
        maps = np.asarray(hp.ud_grade(maps, nside_out, order_in="RING", order_out="RING"))
        maps = np.atleast_2d(maps)
    theta, phi = hp.vec2ang(np.asarray(source_vec).T)
    out = np.empty((maps.shape[0], theta.size))
    for i, m in enumerate(maps):
        checkpoint("rotating a sky map")
        out[i] = hp.get_interp_val(m, theta, phi)
    return out


def resample_galactic_to_equatorial(
    maps: np.ndarray,
    nside_out: int,
    epoch: str | float | Time | None = None,
    rotation: np.ndarray | None = None,
) -> np.ndarray:
    """Galactic HEALPix maps as seen in the apparent equatorial frame of ``epoch``.

    Every output pixel centre (an apparent direction) is traced back to the Galactic
    direction of its source by :func:`apparent_to_galactic` (precession, nutation, annual
    aberration and light deflection), where the maps are interpolated
    (:func:`resample_healpix`).

    Parameters
    ----------
    maps
        ``(Ncomp, Npix_in)`` Galactic RING maps.
    nside_out
        Output HEALPix resolution.
    epoch
        Observation epoch (see :func:`parse_epoch`).
    rotation
        ``(3, 3)`` rotation of the sky in the apparent frame (``None``: none): the map
        returned is ``M(R^T n)``, the sky turned by ``R`` (a sky in a wrong frame).

    Returns
    -------
    numpy.ndarray
        ``(Ncomp, 12 nside_out^2)`` apparent equatorial RING maps.
    """
    vec_eq = np.array(hp.pix2vec(nside_out, np.arange(hp.nside2npix(nside_out))))
    if rotation is not None:
        vec_eq = np.asarray(rotation, dtype=np.float64).T @ vec_eq
    return resample_healpix(maps, nside_out, apparent_to_galactic(vec_eq, epoch))


def tilt_rotation(tilt_x_arcmin: float, tilt_y_arcmin: float) -> np.ndarray:
    """Return the rotation by ``tilt_x`` about the equatorial x axis, then ``tilt_y`` about y.

    The x axis points to right ascension 0 h, y to 6 h (declination 0); turns about the
    pole (z) are a time offset. Positive angles turn counter-clockwise seen from the axis.
    """
    ax, ay = np.radians(np.array([tilt_x_arcmin, tilt_y_arcmin], dtype=np.float64) / 60.0)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(ax), -np.sin(ax)], [0.0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0.0, np.sin(ay)], [0.0, 1.0, 0.0], [-np.sin(ay), 0.0, np.cos(ay)]])
    return ry @ rx
