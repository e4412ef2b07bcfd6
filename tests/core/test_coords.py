"""The apparent sky frame against astropy's full transformation (issue 21: aberration)."""

from __future__ import annotations

import astropy.units as u
import healpy as hp
import numpy as np
import pytest
from astropy.coordinates import TETE, Galactic, SkyCoord
from astropy.time import Time

from autocal.core.coords import (
    apparent_to_galactic,
    galactic_to_equatorial_matrix,
    resample_galactic_to_equatorial,
)

ARCSEC = np.pi / 180 / 3600


def _astropy_galactic(vec_eq: np.ndarray, jd: float) -> np.ndarray:
    """Galactic unit vectors of apparent (TETE) directions by astropy's frame graph."""
    theta, phi = hp.vec2ang(vec_eq.T)
    apparent = SkyCoord(
        ra=phi * u.rad,
        dec=(np.pi / 2 - theta) * u.rad,
        frame=TETE(obstime=Time(jd, format="jd", scale="utc")),
    )
    gal = apparent.transform_to(Galactic())
    return np.array(hp.ang2vec(np.pi / 2 - gal.b.rad, gal.l.rad)).T


@pytest.mark.parametrize("jd", [2451545.0, 2458116.71, 2460000.3])
def test_apparent_to_galactic_matches_astropy(jd: float) -> None:
    vec = np.array(hp.pix2vec(16, np.arange(hp.nside2npix(16))))
    ours = apparent_to_galactic(vec, jd)
    reference = _astropy_galactic(vec, jd)
    assert np.max(np.linalg.norm(ours - reference, axis=0)) < 1e-3 * ARCSEC
    # the rotation alone misses the annual aberration (~20 arcsec), which is why the
    # sky frame is not a rotation: the check above would fail with it
    rotated = galactic_to_equatorial_matrix(jd).T @ vec
    missed = np.linalg.norm(rotated - reference, axis=0) / ARCSEC
    assert 19.0 < missed.max() < 24.0


def test_apparent_sky_maps_follow_astropy() -> None:
    """Each apparent pixel holds the Galactic map interpolated where astropy places it."""
    nside, jd = 128, 2458116.71
    gradient = np.array([0.3, -0.5, 0.8])  # a dipole map, T = gradient . n_gal
    gal = gradient @ np.array(hp.pix2vec(nside, np.arange(hp.nside2npix(nside))))
    eq = resample_galactic_to_equatorial(gal, nside, jd)[0]
    pixels = np.arange(0, hp.nside2npix(nside), 37)
    vec = np.array(hp.pix2vec(nside, pixels))
    at_astropy = hp.get_interp_val(gal, *hp.vec2ang(_astropy_galactic(vec, jd).T))
    rotated = galactic_to_equatorial_matrix(jd).T @ vec
    at_rotated = hp.get_interp_val(gal, *hp.vec2ang(rotated.T))
    assert np.max(np.abs(eq[pixels] - at_astropy)) < 1e-8
    assert np.max(np.abs(at_rotated - at_astropy)) > 5e-5  # what the aberration moves


def test_tilt_rotation_turns_about_the_equatorial_axes() -> None:
    """A tilt about x moves the point at RA 6 h in declination; about y, the one at 0 h."""
    from autocal.core.coords import tilt_rotation

    rot = tilt_rotation(30.0, 0.0)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-15)
    moved = rot @ np.array([0.0, 1.0, 0.0])  # RA 6 h, Dec 0
    assert np.degrees(np.arcsin(moved[2])) * 60 == pytest.approx(30.0)
    moved = tilt_rotation(0.0, 30.0) @ np.array([1.0, 0.0, 0.0])  # RA 0 h, Dec 0
    assert np.degrees(np.arcsin(-moved[2])) * 60 == pytest.approx(30.0)
    np.testing.assert_array_equal(tilt_rotation(0.0, 0.0), np.eye(3))


def test_a_tilted_sky_is_the_sky_sampled_at_turned_directions() -> None:
    """``M'(n) = M(R^T n)``: the tilted map at each pixel is the map at the turned place."""
    from autocal.core.coords import tilt_rotation

    nside, jd = 64, 2458116.71
    gradient = np.array([0.3, -0.5, 0.8])
    gal = gradient @ np.array(hp.pix2vec(nside, np.arange(hp.nside2npix(nside))))
    rot = tilt_rotation(40.0, -25.0)
    tilted = resample_galactic_to_equatorial(gal, nside, jd, rot)[0]
    pixels = np.arange(0, hp.nside2npix(nside), 53)
    turned = rot.T @ np.array(hp.pix2vec(nside, pixels))
    expected = hp.get_interp_val(gal, *hp.vec2ang(apparent_to_galactic(turned, jd).T))
    np.testing.assert_allclose(tilted[pixels], expected, atol=1e-12)
    plain = resample_galactic_to_equatorial(gal, nside, jd)[0]
    assert np.max(np.abs(tilted - plain)) > 1e-3  # 47 arcmin moves the dipole map
