"""Coordinate conventions and transforms used by the sky and Tsky modules.

Conventions (used everywhere in autocal):

* Sky maps are HEALPix, RING ordering, in the *apparent equatorial frame of the
  observation epoch* (astropy ``TETE``: true equator and equinox of date), the frame in
  which the apparent local sidereal time stored in UVH5 files is defined. HEALPix
  ``theta`` is the colatitude (90 deg - Dec) and ``phi`` is the right ascension.
* Topocentric directions are (azimuth, altitude) with the azimuth measured from north
  through east (astropy's convention). pyuvdata's UVBeam uses azimuth from east through
  north; conversions are explicit in :mod:`autocal.sky`.
* Hour angle H = LST - RA, positive west of the meridian.
"""

from __future__ import annotations

from functools import lru_cache

import healpy as hp
import numpy as np
from astropy.time import Time

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


@lru_cache(maxsize=32)
def _galactic_to_tete(jd: float) -> np.ndarray:
    from astropy import units as u
    from astropy.coordinates import TETE, Galactic, SkyCoord

    epoch = Time(jd, format="jd", scale="utc")
    # Fit the rotation on a set of directions (TETE includes annual aberration, a
    # ~20 arcsec deformation, so the best orthogonal matrix is used).
    rng = np.random.default_rng(0)
    vec = rng.normal(size=(3, 200))
    vec /= np.linalg.norm(vec, axis=0)
    lon = np.arctan2(vec[1], vec[0])
    lat = np.arcsin(vec[2])
    gal = SkyCoord(l=lon * u.rad, b=lat * u.rad, frame=Galactic())
    eq = gal.transform_to(TETE(obstime=epoch))
    ra, dec = eq.ra.rad, eq.dec.rad
    out = np.array([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])
    # Orthogonal Procrustes: R = argmin ||R vec - out||, R orthogonal.
    u_, _, vt = np.linalg.svd(out @ vec.T)
    rot = u_ @ vt
    if np.linalg.det(rot) < 0:  # pragma: no cover - cannot happen for a proper frame
        raise RuntimeError("Galactic->equatorial fit gave an improper rotation")
    return rot


def galactic_to_equatorial_matrix(epoch: str | float | Time | None = None) -> np.ndarray:
    """Rotation matrix taking Galactic unit vectors to apparent equatorial ones of ``epoch``.

    Parameters
    ----------
    epoch
        Observation epoch (see :func:`parse_epoch`).

    Returns
    -------
    numpy.ndarray
        ``(3, 3)`` matrix ``R`` with ``v_eq = R @ v_gal``.
    """
    return _galactic_to_tete(float(parse_epoch(epoch).jd)).copy()


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


def resample_galactic_to_equatorial(
    maps: np.ndarray, nside_out: int, rotation: np.ndarray
) -> np.ndarray:
    """Rotate Galactic HEALPix maps into an equatorial frame at a chosen resolution.

    Maps are first area-averaged to ``nside_out`` if they are finer (so no aliasing),
    then bilinearly interpolated at the Galactic position of every output pixel centre.

    Parameters
    ----------
    maps
        ``(Ncomp, Npix_in)`` Galactic RING maps.
    nside_out
        Output HEALPix resolution.
    rotation
        ``(3, 3)`` Galactic-to-equatorial rotation (:func:`galactic_to_equatorial_matrix`).

    Returns
    -------
    numpy.ndarray
        ``(Ncomp, 12 nside_out^2)`` equatorial RING maps.
    """
    maps = np.atleast_2d(np.asarray(maps, dtype=np.float64))
    nside_in = hp.npix2nside(maps.shape[1])
    if nside_in > nside_out:
        maps = np.asarray(hp.ud_grade(maps, nside_out, order_in="RING", order_out="RING"))
        maps = np.atleast_2d(maps)
        nside_in = nside_out
    vec_eq = np.array(hp.pix2vec(nside_out, np.arange(hp.nside2npix(nside_out))))
    vec_gal = rotation.T @ vec_eq
    theta, phi = hp.vec2ang(vec_gal.T)
    out = np.empty((maps.shape[0], theta.size))
    for i, m in enumerate(maps):
        checkpoint("rotating a sky map")
        out[i] = hp.get_interp_val(m, theta, phi)
    return out
