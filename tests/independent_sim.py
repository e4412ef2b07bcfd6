"""An independent forward model of HERA auto-correlations, written as genuine UVH5 files.

autocal's tests use this module to check autocal's claims on data that autocal did not
make. It shares no code with autocal's sky, beam, coordinate, Tsky, simulation or writer
modules; ``import autocal`` is done only for its side effect of making pygdsm and astropy
work offline (GSM2008 registered in astropy's cache, no IERS or site downloads).

Model
-----
* Sky: pygdsm's GSM2008 (``GlobalSkyModel``, Haslam basemap, pchip interpolation) at
  the simulated frequencies, nside 64 RING Galactic, WITHOUT the CMB (pygdsm 1.7's
  default ``include_cmb=False``); 2.725 K is added here once. The maps are averaged down to
  nside 32 with ``healpy.ud_grade`` (a resolution choice of this model; autocal uses 64).
* Coordinates: at each evaluation time the Galactic pixel centres are transformed to
  AltAz at the HERA site (lat -30.7224 deg, lon 21.4278 deg, 1100 m) by astropy's full
  apparent-frame conversion, pixel by pixel, with pressure 0 (no refraction).
* Beam: the Gaussian dipole power beam
  ``A = exp(-(theta/theta0)^2) / (sqrt(pi) theta0) * (cos^2 phi + sin^2 phi cos theta)^2``,
  ``theta`` the zenith angle, ``theta0 = FWHM / (2 sqrt(ln 2))``,
  ``FWHM = 72 deg (nu / 140 MHz)^-1``, ``phi`` the azimuth from north (through east) for
  ``ee`` and from east (``phi = az - 90 deg``) for ``nn``: an east-west dipole's beam is
  wider north-south. Optionally the HERA Fagnoni beam (``beam="hera"``), read with
  pyuvdata and interpolated with ``UVBeam.interp`` (bilinear HEALPix, cubic in frequency);
  it costs ~0.3 s per evaluation time, so use ``node_spacing_s`` for long spans with it
  (spline error measured up to 2.2e-4 at 120 s spacing, median 2e-5).
* Horizon: hard, at the pixel centres (altitude > 0 sees the sky). With the beam
  normalised over the whole sphere and the ground at ``T_gnd`` filling the part of the
  beam below the horizon::

      Tsky(nu, t) = [sum_{alt>0} A T_sky + T_gnd sum_{alt<=0} A] / sum_all A.

* Time sampling: by default Tsky is evaluated exactly at every integration: astropy's
  conversion of the 12288 pixel centres, vectorised over (times x pixels), and the beam
  sums cost ~10 ms per integration for 161 channels, so no approximation is needed.
  Optionally (``node_spacing_s``) it is evaluated exactly at evenly spaced nodes (at least
  :data:`MIN_NODES`, both ends included) and interpolated to the integrations with a cubic
  spline in time. Measured against exact evaluation (dipole, 110-190 MHz, 174 x 10.7 s
  from LST 3.23 h) the spline's relative error has a median of 2e-6 but a maximum of
  0.8-1.4e-4 whatever the spacing (30-300 s), always at the lowest frequency: the hard
  horizon makes the exact Tsky step by up to ~1e-4 each time a pixel centre crosses it,
  which no interpolation in time reproduces. Hence the exact default.
* Data: ``R = G(nu, t) (Tsky(nu, t) + Trxr(nu) (1 + e_1 s(t))) (1 + N(0, 1) / sqrt(dnu_dt))``
  with ``G(nu, t) = G0(nu) (1 + drift(t))``, ``s`` the time mapped linearly onto
  ``[-1, 1]`` over the span (``e_1 = noise_drift``, default 0) and independent seeded
  noise per antenna, polarisation, time and channel.
* A different true sky or beam (the "hidden effects" of the diagnosis tests, see
  ``tests/independent_effects.py``): :class:`SkyChange` replaces the sky above the horizon
  by ``(1 + scale) S (nu / nu0)^dbeta + T_cmb' + offset`` (``S`` the GSM2008 map without
  the CMB, ``T_cmb'`` 2.725 K or 0), and ``beam_width = w`` makes the beam wider
  (``w > 0``) or narrower: by default (``beam_width_mode="fwhm"``) the Gaussian dipole's
  FWHM is multiplied by ``1 + w`` (its azimuthal factor is kept); with
  ``beam_width_mode="stretch"`` the whole pattern is stretched in zenith angle,
  ``A'(za, phi) = A(min(za / (1 + w), pi), phi)``; the HERA beam is always stretched.
  The ground temperature is ``tgnd_k``.

Everything expensive (GSM maps, AltAz coordinates, Tsky) is cached in memory
(:func:`functools.lru_cache`), so the tests of one session share it.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import os
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import autocal  # noqa: F401  (side effect: pygdsm/astropy offline configuration)

logger = logging.getLogger(__name__)

#: HERA site used for the sky rotation and written to the files.
HERA_LAT_DEG = -30.7224
HERA_LON_DEG = 21.4278
HERA_ALT_M = 1100.0

#: CMB temperature added to the GSM2008 maps (which exclude it), kelvin.
T_CMB_K = 2.725
#: Resolution of pygdsm's GSM2008 maps and of this model's computation.
GSM_NSIDE = 64
SIM_NSIDE = 32
#: Dipole beam: FWHM at the reference frequency.
DIPOLE_FWHM_DEG = 72.0
DIPOLE_NU_REF_HZ = 140e6
#: Minimum number of exact Tsky evaluations over a span when interpolating in time.
MIN_NODES = 12
#: Times per astropy transformation / beam-evaluation chunk.
TIME_CHUNK = 48
#: Sidereal days per solar day.
SIDEREAL_RATE = 1.002737909350795
#: Spacing of the toy antenna layout (east-west line), metres.
ANTENNA_SPACING_M = 14.6
#: The HERA Fagnoni beam, relative to the reference data folder.
HERA_BEAM_FILE = Path("hera/beams/HERA_NF_dipole_power.beamfits")

_POL_CODES = {"ee": -5, "nn": -6}


@dataclass(frozen=True)
class SkyChange:
    """A true sky that differs from GSM2008 + CMB (hashable: part of the Tsky cache key).

    Above the horizon the sky is ``(1 + scale) S (nu / nu0_hz)^dbeta + cmb_k + offset_k``
    with ``S`` the GSM2008 map (which has no CMB). The default is GSM2008 + 2.725 K.

    Attributes
    ----------
    scale
        Fractional scale error ``s`` of the Galactic part.
    dbeta
        Spectral-index error of the Galactic part.
    nu0_hz
        Reference frequency of ``dbeta``, Hz.
    offset_k
        Constant added to every pixel above the horizon, kelvin.
    cmb_k
        CMB temperature of the true sky, kelvin (0: a sky without CMB).
    """

    scale: float = 0.0
    dbeta: float = 0.0
    nu0_hz: float = 150e6
    offset_k: float = 0.0
    cmb_k: float = T_CMB_K

    @property
    def is_default(self) -> bool:
        """True for GSM2008 + 2.725 K (no change)."""
        return (
            self.scale == 0.0
            and self.dbeta == 0.0
            and self.offset_k == 0.0
            and self.cmb_k == T_CMB_K
        )


# ---------------------------------------------------------------------------------------
# site, times
# ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def hera_location() -> Any:
    """Return the HERA site as an :class:`astropy.coordinates.EarthLocation`."""
    import astropy.units as u
    from astropy.coordinates import EarthLocation

    return EarthLocation.from_geodetic(
        lon=HERA_LON_DEG * u.deg, lat=HERA_LAT_DEG * u.deg, height=HERA_ALT_M * u.m
    )


def _apparent_lst_hours(jds: np.ndarray | float) -> np.ndarray:
    from astropy.time import Time

    t = Time(np.asarray(jds, dtype=np.float64), format="jd", scale="utc")
    return np.asarray(t.sidereal_time("apparent", longitude=hera_location().lon).hour)


def jd_at_lst(lst_h: float, jd_night: float = 2458116.0) -> float:
    """Return the first JD at or after ``jd_night`` whose apparent LST at HERA is ``lst_h``.

    Parameters
    ----------
    lst_h
        Local apparent sidereal time, hours.
    jd_night
        Start of the search (UTC JD; an integer JD is noon UTC, early afternoon at HERA,
        so the result lies in that afternoon or the following night).

    Returns
    -------
    float
        The JD (UTC), accurate to well below a millisecond.
    """
    lst0 = float(_apparent_lst_hours(jd_night))
    jd = jd_night + ((lst_h - lst0) % 24.0) / 24.0 / SIDEREAL_RATE
    for _ in range(3):
        diff = (lst_h - float(_apparent_lst_hours(jd)) + 12.0) % 24.0 - 12.0
        jd += diff / 24.0 / SIDEREAL_RATE
    return float(jd)


# ---------------------------------------------------------------------------------------
# sky
# ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=4)
def _sky_maps(freqs_key: tuple[float, ...]) -> np.ndarray:
    """GSM2008 + CMB at ``freqs_key`` (Hz): ``(Nfreq, Npix)`` RING Galactic, nside 32."""
    import healpy as hp
    import pygdsm

    gsm = pygdsm.GlobalSkyModel(freq_unit="MHz", include_cmb=False)
    maps = np.atleast_2d(np.asarray(gsm.generate(np.asarray(freqs_key) / 1e6), np.float64))
    if maps.shape[1] != hp.nside2npix(GSM_NSIDE):  # pragma: no cover - pygdsm change
        raise RuntimeError(f"unexpected GSM2008 map size {maps.shape}")
    low = np.atleast_2d(hp.ud_grade(maps, SIM_NSIDE, order_in="RING", order_out="RING"))
    low = np.ascontiguousarray(low + T_CMB_K)
    low.setflags(write=False)
    return low


@functools.lru_cache(maxsize=4)
def _galactic_maps(freqs_key: tuple[float, ...]) -> np.ndarray:
    """GSM2008 without the CMB at ``freqs_key`` (Hz): ``(Nfreq, Npix)``, nside 32."""
    low = np.ascontiguousarray(_sky_maps(freqs_key) - T_CMB_K)
    low.setflags(write=False)
    return low


def _true_sky(freqs_key: tuple[float, ...], change: SkyChange | None) -> np.ndarray:
    """The sky above the horizon: GSM2008 + CMB, or as ``change`` makes it."""
    if change is None or change.is_default:
        return _sky_maps(freqs_key)
    freqs = np.asarray(freqs_key)
    factor = (1.0 + change.scale) * (freqs / change.nu0_hz) ** change.dbeta
    return _galactic_maps(freqs_key) * factor[:, None] + (change.cmb_k + change.offset_k)


def sky_maps(freqs_hz: np.ndarray) -> np.ndarray:
    """Return the model's sky, GSM2008 + CMB, in kelvin.

    Parameters
    ----------
    freqs_hz
        Frequencies in Hz.

    Returns
    -------
    numpy.ndarray
        ``(Nfreq, 12 * 32**2)`` brightness temperatures, HEALPix nside 32, RING, Galactic.
    """
    return _sky_maps(tuple(float(f) for f in np.atleast_1d(freqs_hz))).copy()


# ---------------------------------------------------------------------------------------
# coordinates
# ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _galactic_pixels() -> Any:
    import astropy.units as u
    import healpy as hp
    from astropy.coordinates import SkyCoord

    lon, lat = hp.pix2ang(SIM_NSIDE, np.arange(hp.nside2npix(SIM_NSIDE)), lonlat=True)
    return SkyCoord(l=lon * u.deg, b=lat * u.deg, frame="galactic")


#: The sky frames :func:`independent_tsky` can put the sky in: ``"apparent"`` (astropy's
#: full Galactic -> AltAz transformation, the truth) or ``"J2000"`` (a mistake: the pixels'
#: FK5 J2000 right ascension and declination taken as the apparent ones of the date, i.e.
#: no precession, nutation or aberration since J2000).
SKY_FRAMES = ("apparent", "J2000")


@functools.lru_cache(maxsize=4)
def _altaz(
    jds_key: tuple[float, ...], sky_frame: str = "apparent"
) -> tuple[np.ndarray, np.ndarray]:
    """Altitude and azimuth (N through E) of every pixel centre: ``(Ntime, Npix)`` radians."""
    import astropy.units as u
    from astropy.coordinates import FK5, TETE, AltAz, SkyCoord
    from astropy.time import Time

    if sky_frame not in SKY_FRAMES:
        raise ValueError(f"unknown sky_frame {sky_frame!r}: use one of {SKY_FRAMES}")
    pixels = _galactic_pixels()
    jds = np.asarray(jds_key, dtype=np.float64)
    if sky_frame == "J2000":
        # where each pixel would be if its J2000 place were its apparent one (taken at the
        # data's mean time: the apparent frame moves < 0.4 arcsec in a day)
        j2000 = pixels.transform_to(FK5(equinox="J2000"))
        mean_time = Time(float(jds.mean()), format="jd", scale="utc")
        pixels = SkyCoord(ra=j2000.ra, dec=j2000.dec, frame=TETE(obstime=mean_time)).transform_to(
            pixels.frame
        )
    alt = np.empty((jds.size, len(pixels)))
    az = np.empty_like(alt)
    for start in range(0, jds.size, TIME_CHUNK):
        chunk = slice(start, start + TIME_CHUNK)
        frame = AltAz(
            obstime=Time(jds[chunk, None], format="jd", scale="utc"),
            location=hera_location(),
            pressure=0.0 * u.hPa,
        )
        topo = pixels[None, :].transform_to(frame)
        alt[chunk] = topo.alt.rad
        az[chunk] = topo.az.rad
    alt.setflags(write=False)
    az.setflags(write=False)
    return alt, az


# ---------------------------------------------------------------------------------------
# beams
# ---------------------------------------------------------------------------------------
def dipole_beam(
    freqs_hz: np.ndarray, za: np.ndarray, az: np.ndarray, pol: str = "ee"
) -> np.ndarray:
    """Evaluate the Gaussian dipole power beam.

    Parameters
    ----------
    freqs_hz
        ``(Nfreq,)`` frequencies, Hz.
    za, az
        Zenith angle and azimuth (from north through east), radians, same shape ``S``.
    pol
        ``"ee"`` (phi = az) or ``"nn"`` (phi = az - 90 deg).

    Returns
    -------
    numpy.ndarray
        ``(Nfreq, *S)`` beam values (not normalised).
    """
    za = np.asarray(za, dtype=np.float64)
    phi = _dipole_phi(np.asarray(az, dtype=np.float64), pol)
    theta0 = _dipole_theta0(np.atleast_1d(freqs_hz)).reshape((-1,) + (1,) * za.ndim)
    radial = np.exp(-((za[None] / theta0) ** 2)) / (math.sqrt(math.pi) * theta0)
    return radial * _dipole_azimuthal(za, phi)[None]


def _dipole_theta0(freqs_hz: np.ndarray, width: float = 0.0) -> np.ndarray:
    fwhm = np.radians(DIPOLE_FWHM_DEG) * (np.asarray(freqs_hz, np.float64) / DIPOLE_NU_REF_HZ) ** -1
    return (1.0 + width) * fwhm / (2.0 * math.sqrt(math.log(2.0)))


def _dipole_phi(az: np.ndarray, pol: str) -> np.ndarray:
    if pol == "ee":
        return az
    if pol == "nn":
        return az - np.pi / 2
    raise ValueError(f"unknown polarisation {pol!r}: use 'ee' or 'nn'")


def _dipole_azimuthal(za: np.ndarray, phi: np.ndarray) -> np.ndarray:
    return (np.cos(phi) ** 2 + np.sin(phi) ** 2 * np.cos(za)) ** 2


def data_folder() -> Path:
    """Return the reference data folder (``AUTOCAL_DATA_DIR`` or ``../shared/data``)."""
    env = os.environ.get("AUTOCAL_DATA_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


@functools.lru_cache(maxsize=1)
def _hera_uvbeam() -> Any:
    from pyuvdata import UVBeam

    path = data_folder() / HERA_BEAM_FILE
    if not path.is_file():
        raise FileNotFoundError(f"HERA beam not found: {path}")
    with warnings.catch_warnings():
        # the 2018 file predates UVBeam's mount_type; HERA dishes are fixed (drift scan)
        warnings.filterwarnings("ignore", message="The mount_type parameter must be set")
        beam = UVBeam.from_file(str(path), mount_type="fixed")
    if beam.beam_type != "power":  # pragma: no cover - file is a power beam
        raise ValueError(f"{path} is not a power beam")
    return beam


def hera_beam(freqs_hz: np.ndarray, za: np.ndarray, az: np.ndarray, pol: str = "ee") -> np.ndarray:
    """Evaluate the HERA Fagnoni power beam (read with pyuvdata), smoothly.

    The beam's HEALPix maps at its 26 native frequencies are resampled once through
    spherical harmonics to :data:`SMOOTH_BEAM_NSIDE` and interpolated bilinearly there
    (healpy); a cubic spline in frequency (scipy, not-a-knot) then gives the requested
    channels.

    Parameters
    ----------
    freqs_hz
        ``(Nfreq,)`` frequencies in Hz, within the beam's 100-200 MHz.
    za, az
        ``(Npoint,)`` zenith angle and azimuth (from north through east), radians.
        pyuvdata's azimuth runs from east towards north, i.e. ``pi/2 - az``.
    pol
        ``"ee"`` or ``"nn"``.

    Returns
    -------
    numpy.ndarray
        ``(Nfreq, Npoint)`` peak-normalised power.
    """
    beam = _hera_uvbeam()
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    native = np.asarray(beam.freq_array, np.float64).ravel()
    if freqs.min() < native.min() or freqs.max() > native.max():
        raise ValueError(
            f"the HERA beam covers {native.min() / 1e6:g}-{native.max() / 1e6:g} MHz only"
        )
    import healpy as hp

    smooth = _smooth_hera_maps(pol)  # (Nfreq_native, Npix) at SMOOTH_BEAM_NSIDE, RING
    # pyuvdata's HEALPix beams are in (theta = za, phi = az from east towards north)
    phi = np.mod(np.pi / 2 - np.asarray(az, np.float64), 2 * np.pi)
    theta = np.asarray(za, np.float64)
    values = np.stack([hp.get_interp_val(m, theta, phi) for m in smooth])
    return _freq_spline_matrix(tuple(native), tuple(freqs)) @ values


#: HEALPix resolution the HERA beam maps are resampled to (band-limited, through spherical
#: harmonics up to 3 x the file's nside) before bilinear interpolation: a bilinear
#: interpolation of the file's nside-32 maps has kinks at its pixel edges, which make Tsky
#: rough from one integration to the next as the sky moves across them
#: (``scripts/tsky_roughness.py``); the real beam is smooth.
SMOOTH_BEAM_NSIDE = 128


@functools.lru_cache(maxsize=4)
def _smooth_hera_maps(pol: str) -> np.ndarray:
    """The HERA beam's maps at every native frequency, resampled to a smooth finer grid."""
    import healpy as hp

    beam = _hera_uvbeam()
    if beam.pixel_coordinate_system != "healpix" or beam.ordering != "ring":
        raise ValueError("the HERA beam file is expected as a RING HEALPix power beam")
    pols = [int(p) for p in np.ravel(beam.polarization_array)]
    from pyuvdata import utils as uvutils

    code = int(uvutils.polstr2num(pol, x_orientation="east"))
    maps = np.asarray(beam.data_array)[0, pols.index(code)].real  # (Nfreq, Npix)
    nside = int(beam.nside)
    lmax = 3 * nside - 1
    out = []
    for m in maps:
        alm = hp.map2alm(m, lmax=lmax, iter=3)
        out.append(hp.alm2map(alm, SMOOTH_BEAM_NSIDE, lmax=lmax))
    return np.asarray(out)


@functools.lru_cache(maxsize=8)
def _freq_spline_matrix(native: tuple[float, ...], freqs: tuple[float, ...]) -> np.ndarray:
    """The (linear) cubic-spline map from values at ``native`` to values at ``freqs``."""
    from scipy.interpolate import CubicSpline

    basis = CubicSpline(np.asarray(native), np.eye(len(native)), axis=0)
    return np.asarray(basis(np.asarray(freqs)))


# ---------------------------------------------------------------------------------------
# Tsky
# ---------------------------------------------------------------------------------------
def _exact_tsky(
    freqs_key: tuple[float, ...],
    jds_key: tuple[float, ...],
    pol: str,
    beam: str,
    tgnd_k: float,
    change: SkyChange | None = None,
    beam_width: float = 0.0,
    beam_width_mode: str = "fwhm",
    sky_frame: str = "apparent",
) -> np.ndarray:
    """Beam-weighted Tsky evaluated exactly at every time: ``(Ntime, Nfreq)``."""
    freqs = np.asarray(freqs_key)
    sky = _true_sky(freqs_key, change)
    alt, az = _altaz(jds_key, sky_frame)
    out = np.empty((alt.shape[0], freqs.size))
    stretch = beam_width != 0.0 and (beam_width_mode == "stretch" or beam == "hera")
    if beam == "dipole":
        fwhm_width = 0.0 if stretch else beam_width
        inv_theta0_sq = -1.0 / _dipole_theta0(freqs, fwhm_width) ** 2
        norm = 1.0 / (math.sqrt(math.pi) * _dipole_theta0(freqs, fwhm_width))
        for it in range(alt.shape[0]):
            za = np.pi / 2 - alt[it]
            if stretch:
                za = np.minimum(za / (1.0 + beam_width), np.pi)
            weight = np.exp(np.multiply.outer(inv_theta0_sq, za * za))
            weight *= norm[:, None]
            weight *= _dipole_azimuthal(za, _dipole_phi(az[it], pol))[None, :]
            seen = np.where(alt[it] > 0, sky, tgnd_k)
            out[it] = np.einsum("fp,fp->f", weight, seen) / weight.sum(axis=1)
    elif beam == "hera":
        for start in range(0, alt.shape[0], 4):
            stop = min(start + 4, alt.shape[0])
            za = np.pi / 2 - alt[start:stop]
            if stretch:
                za = np.minimum(za / (1.0 + beam_width), np.pi)
            weight = hera_beam(freqs, za.ravel(), az[start:stop].ravel(), pol)
            weight = weight.reshape(freqs.size, stop - start, -1)
            for k in range(stop - start):
                seen = np.where(alt[start + k] > 0, sky, tgnd_k)
                w = weight[:, k]
                out[start + k] = np.einsum("fp,fp->f", w, seen) / w.sum(axis=1)
    else:
        raise ValueError(f"unknown beam {beam!r}: use 'dipole' or 'hera'")
    return out


def node_times(jds: np.ndarray, node_spacing_s: float | None = None) -> np.ndarray:
    """Return the times at which Tsky is evaluated exactly for integrations at ``jds``.

    Parameters
    ----------
    jds
        Integration times (JD, increasing).
    node_spacing_s
        Largest spacing of the nodes, seconds (``None`` or 0: evaluate at every time).

    Returns
    -------
    numpy.ndarray
        Evenly spaced JDs from ``jds[0]`` to ``jds[-1]``, at least :data:`MIN_NODES` of them;
        ``jds`` itself when that would be no fewer points.
    """
    jds = np.asarray(jds, dtype=np.float64)
    if not node_spacing_s or jds.size <= MIN_NODES:
        return jds
    span_s = (jds[-1] - jds[0]) * 86400.0
    count = max(MIN_NODES, math.ceil(span_s / node_spacing_s) + 1)
    if count >= jds.size:
        return jds
    return np.linspace(jds[0], jds[-1], count)


@functools.lru_cache(maxsize=128)
def _tsky_cached(
    freqs_key: tuple[float, ...],
    jds_key: tuple[float, ...],
    pol: str,
    beam: str,
    tgnd_k: float,
    node_spacing_s: float | None,
    change: SkyChange | None = None,
    beam_width: float = 0.0,
    beam_width_mode: str = "fwhm",
    sky_frame: str = "apparent",
) -> np.ndarray:
    from scipy.interpolate import CubicSpline

    jds = np.asarray(jds_key)
    nodes = node_times(jds, node_spacing_s)
    exact = _exact_tsky(
        freqs_key,
        tuple(float(t) for t in nodes),
        pol,
        beam,
        tgnd_k,
        change,
        beam_width,
        beam_width_mode,
        sky_frame,
    )
    if nodes.size == jds.size:
        result = exact
    else:
        spline = CubicSpline((nodes - jds[0]) * 86400.0, exact, axis=0)
        result = spline((jds - jds[0]) * 86400.0)
    result.setflags(write=False)
    return result


def independent_tsky(
    freqs_hz: np.ndarray,
    jds: np.ndarray,
    pol: str = "ee",
    beam: str = "dipole",
    tgnd_k: float = 300.0,
    *,
    node_spacing_s: float | None = None,
    sky: SkyChange | None = None,
    beam_width: float = 0.0,
    beam_width_mode: str = "fwhm",
    sky_frame: str = "apparent",
) -> np.ndarray:
    """Beam-weighted sky temperature at HERA, computed independently of autocal.

    Parameters
    ----------
    freqs_hz
        ``(Nfreq,)`` frequencies in Hz.
    jds
        ``(Ntime,)`` UTC Julian dates, increasing.
    pol
        ``"ee"`` or ``"nn"``.
    beam
        ``"dipole"`` (Gaussian dipole) or ``"hera"`` (Fagnoni beamfits, 100-200 MHz).
    tgnd_k
        Ground temperature filling the beam below the (hard) horizon, kelvin.
    node_spacing_s
        ``None`` (default): evaluate exactly at every time. Otherwise the largest spacing
        (seconds) of exact evaluations interpolated by a cubic spline in time
        (:func:`node_times`; relative error up to ~1.4e-4, see the module notes).
    sky
        A true sky other than GSM2008 + CMB (:class:`SkyChange`; ``None``: the default).
    beam_width
        Fractional change ``w`` of the beam width.
    beam_width_mode
        ``"fwhm"``: the dipole's FWHM times ``1 + w`` (azimuthal factor unchanged);
        ``"stretch"``: the dipole's whole pattern evaluated at ``za / (1 + w)`` (clipped
        to ``pi``). The HERA beam is always stretched.
    sky_frame
        ``"apparent"`` (the truth) or ``"J2000"`` (the sky put in the wrong frame,
        :data:`SKY_FRAMES`).

    Returns
    -------
    numpy.ndarray
        ``(Ntime, Nfreq)`` Tsky in kelvin (including the CMB and ground pickup).
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    times = np.atleast_1d(np.asarray(jds, dtype=np.float64))
    if times.size > 1 and np.any(np.diff(times) <= 0):
        raise ValueError("jds must be strictly increasing")
    if pol not in _POL_CODES:
        raise ValueError(f"unknown polarisation {pol!r}: use 'ee' or 'nn'")
    if not 1.0 + beam_width > 0.0:
        raise ValueError(f"beam_width {beam_width} must be > -1")
    if beam_width_mode not in ("fwhm", "stretch"):
        raise ValueError(f"unknown beam_width_mode {beam_width_mode!r}: 'fwhm' or 'stretch'")
    spacing = float(node_spacing_s) if node_spacing_s else None
    change = None if sky is None or sky.is_default else sky
    return _tsky_cached(
        tuple(float(f) for f in freqs),
        tuple(float(t) for t in times),
        pol,
        beam,
        float(tgnd_k),
        spacing,
        change,
        float(beam_width),
        beam_width_mode if beam_width else "fwhm",
        sky_frame,
    ).copy()


# ---------------------------------------------------------------------------------------
# instrument
# ---------------------------------------------------------------------------------------
def default_freqs() -> np.ndarray:
    """Return the default channels: 161 from 110 to 190 MHz (0.5 MHz apart), Hz."""
    return np.linspace(110e6, 190e6, 161)


def default_bandpass(freqs_hz: np.ndarray) -> np.ndarray:
    """Return the default smooth bandpass ``G0(nu)``.

    ``G0 = 0.015 (1 + 0.3 x) (1 - 0.2 x^2)`` with ``x = (nu - 150 MHz) / 40 MHz``:
    positive and smooth, 0.0084-0.0185 over 110-190 MHz.

    Parameters
    ----------
    freqs_hz
        Frequencies in Hz.

    Returns
    -------
    numpy.ndarray
        Gains (raw units per kelvin), like ``freqs_hz``.
    """
    x = (np.asarray(freqs_hz, dtype=np.float64) - 150e6) / 40e6
    return 0.015 * (1.0 + 0.3 * x) * (1.0 - 0.2 * x * x)


def _readonly(values: Any, dtype: Any = np.float64) -> np.ndarray:
    arr = np.array(values, dtype=dtype)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Truth:
    """What went into a simulated file.

    Attributes
    ----------
    path
        The UVH5 file.
    freqs
        ``(Nfreq,)`` channel centres, Hz.
    jds
        ``(Ntime,)`` integration centres, UTC JD.
    lsts
        ``(Ntime,)`` apparent LSTs in hours, as pyuvdata computed them for the file.
    antennas, pols
        Antenna numbers and polarisation names, in the file's order.
    tsky
        ``(Npol, Ntime, Nfreq)`` beam-weighted sky temperature used, kelvin.
    G
        ``(Ntime, Nfreq)`` gain at every integration (same for every antenna and pol).
    G0
        ``(Nfreq,)`` reference gain: the time-mean gain for a linear drift.
    Trxr
        ``(Nfreq,)`` receiver temperature, kelvin.
    G_mean
        ``(Nfreq,)`` mean of ``G`` over the integrations.
    drift
        ``(Ntime,)`` fractional gain change ``G / G0 - 1``.
    dnu_dt
        Channel width x integration time x nsamples of every sample (radiometer product).
    settings
        The arguments of :func:`simulate_autos` (scalars and strings).
    trxr_drift
        ``(Ntime,)`` fractional receiver-noise change ``e_1 s(t)`` (``None``: none), so
        that the receiver temperature at integration ``i`` is ``Trxr (1 + trxr_drift[i])``.
    """

    path: Path
    freqs: np.ndarray
    jds: np.ndarray
    lsts: np.ndarray
    antennas: tuple[int, ...]
    pols: tuple[str, ...]
    tsky: np.ndarray
    G: np.ndarray
    G0: np.ndarray
    Trxr: np.ndarray
    G_mean: np.ndarray
    drift: np.ndarray
    dnu_dt: float
    settings: dict[str, Any] = field(default_factory=dict)
    trxr_drift: np.ndarray | None = None

    @property
    def noise_offset(self) -> np.ndarray:
        """``(Nfreq,)`` ``n = G_mean * Trxr``, the offset of the time-mean gain."""
        return self.G_mean * self.Trxr

    def expected(self) -> np.ndarray:
        """Noise-free data ``G (Tsky + Trxr)``: ``(Npol, Ntime, Nfreq)`` (every antenna)."""
        trxr = self.Trxr[None, None, :]
        if self.trxr_drift is not None:
            trxr = trxr * (1.0 + self.trxr_drift[None, :, None])
        return self.G[None] * (self.tsky + trxr)


def _drift_values(
    jds: np.ndarray, drift_total: float, drift: Callable[[np.ndarray], Any] | None
) -> np.ndarray:
    span = jds[-1] - jds[0]
    t_frac = (jds - jds[0]) / span if span > 0 else np.zeros_like(jds)
    if drift is not None:
        if drift_total:
            raise ValueError("give either drift_total or drift, not both")
        values = np.broadcast_to(np.asarray(drift(t_frac), dtype=np.float64), jds.shape)
    else:
        values = float(drift_total) * (t_frac - np.mean(t_frac))
    if np.any(~np.isfinite(values)) or np.any(values <= -1.0):
        raise ValueError("the drift must keep the gain finite and positive")
    return np.array(values)


def _telescope(antennas: Sequence[int]) -> Any:
    from pyuvdata import Telescope
    from pyuvdata import utils as uvutils

    location = hera_location()
    enu = np.zeros((len(antennas), 3))
    enu[:, 0] = ANTENNA_SPACING_M * np.arange(len(antennas))
    ecef = uvutils.ECEF_from_ENU(enu, center_loc=location)
    center = np.array([q.to_value("m") for q in location.geocentric])
    telescope = Telescope.new(
        name="HERA",
        location=location,
        antenna_positions=ecef - center[None, :],
        antenna_names=[f"HH{a}" for a in antennas],
        antenna_numbers=[int(a) for a in antennas],
        instrument="HERA",
        antenna_diameters=np.full(len(antennas), 14.0),
        mount_type="fixed",
        update_from_known=False,
    )
    telescope.set_feeds_from_x_orientation("east", feeds=["x", "y"])
    return telescope


def _write_uvh5(
    path: Path,
    data: np.ndarray,
    freqs: np.ndarray,
    jds: np.ndarray,
    antennas: Sequence[int],
    pols: Sequence[str],
    integration_s: float,
    channel_width: float,
    nsample: float,
    history: str,
) -> np.ndarray:
    """Write ``data`` (Nant, Npol, Ntime, Nfreq) and return pyuvdata's LSTs (hours)."""
    from pyuvdata import UVData

    npol, ntime = data.shape[1], data.shape[2]
    uvd = UVData.new(
        freq_array=freqs,
        polarization_array=[_POL_CODES[p] for p in pols],
        times=jds,
        telescope=_telescope(antennas),
        antpairs=[(int(a), int(a)) for a in antennas],
        do_blt_outer=True,
        integration_time=float(integration_s),
        channel_width=float(channel_width),
        history=history,
        vis_units="uncalib",
        empty=True,
        update_telescope_from_known=False,
    )
    uvd.nsample_array[:] = nsample
    uvd.flag_array[:] = False
    lsts = np.empty(ntime)
    for ia, ant in enumerate(antennas):
        blts = np.arange(uvd.Nblts)[uvd.antpair2ind(int(ant), int(ant))]
        blts = blts[np.argsort(uvd.time_array[blts], kind="stable")]
        if not np.allclose(uvd.time_array[blts], jds, rtol=0, atol=1e-9):
            raise RuntimeError("pyuvdata's baseline-times do not match the integrations")
        for ip in range(npol):
            uvd.data_array[blts, :, ip] = data[ia, ip].astype(np.complex128)
        lsts = np.mod(uvd.lst_array[blts] * 12.0 / np.pi, 24.0)
    uvd.check()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.unlink(missing_ok=True)
    uvd.write_uvh5(str(path))
    return lsts


def simulate_autos(
    path: str | Path,
    *,
    lst_start_h: float,
    duration_min: float,
    freqs_hz: np.ndarray | None = None,
    integration_s: float = 10.7,
    antennas: Sequence[int] = (0,),
    pols: Sequence[str] = ("ee",),
    G0: np.ndarray | None = None,
    trxr_k: float | np.ndarray = 150.0,
    drift_total: float = 0.0,
    drift: Callable[[np.ndarray], Any] | None = None,
    dnu_dt: float = 1e6,
    tgnd_k: float = 300.0,
    beam: str = "dipole",
    seed: int = 0,
    jd_night: float = 2458116,
    node_spacing_s: float | None = None,
    noise_drift: float = 0.0,
    sky: SkyChange | None = None,
    beam_width: float = 0.0,
    beam_width_mode: str = "fwhm",
    feed_gain: np.ndarray | None = None,
    clock_offset_s: float = 0.0,
    sky_frame: str = "apparent",
) -> Truth:
    """Simulate HERA auto-correlations and write them as a UVH5 file.

    Parameters
    ----------
    path
        Output UVH5 file (overwritten).
    lst_start_h
        Apparent LST of the first integration centre, hours.
    duration_min
        Span of the integrations: ``round(duration_min * 60 / integration_s)`` (at least
        one) integrations of ``integration_s`` each, back to back.
    freqs_hz
        Channel centres in Hz, evenly spaced (default :func:`default_freqs`).
    integration_s
        Integration time, seconds.
    antennas
        Antenna numbers (autos ``(a, a)`` only).
    pols
        Polarisations, from ``"ee"`` and ``"nn"``.
    G0
        ``(Nfreq,)`` gain (default :func:`default_bandpass`).
    trxr_k
        Receiver temperature, kelvin (scalar or ``(Nfreq,)``).
    drift_total
        Linear fractional gain drift from the first to the last integration, centred so
        that the time-mean gain is ``G0``.
    drift
        Alternatively, ``drift(t_frac) -> fractional gain change`` with ``t_frac`` from 0
        (first integration) to 1 (last); not centred.
    dnu_dt
        Radiometer product ``channel_width * integration_time * nsamples`` of every
        sample: the relative noise is ``1 / sqrt(dnu_dt)``.
    tgnd_k
        Ground temperature below the horizon, kelvin.
    beam
        ``"dipole"`` or ``"hera"``.
    seed
        Seed of the noise generator.
    jd_night
        The first integration is on the first JD at or after this with LST ``lst_start_h``.
    node_spacing_s
        Time sampling of Tsky (:func:`independent_tsky`; default exact at every
        integration).
    noise_drift
        ``e_1``: the receiver temperature is ``Trxr (1 + e_1 s)`` with ``s`` the time
        mapped linearly from -1 (first integration) to +1 (last); 0 for none.
    sky
        The true sky, if not GSM2008 + CMB (:class:`SkyChange`).
    beam_width, beam_width_mode
        Fractional change of the true beam's width and how it is made
        (:func:`independent_tsky`).
    feed_gain
        ``(Nant, Npol, Ntime)`` achromatic gain factors of each antenna-pol (its own
        jitter), on top of the common gain; ``None`` for none.
    clock_offset_s
        The sky is simulated ``clock_offset_s`` seconds after the times written in the
        file (a clock running behind: the data's sky is that of ``t + dt``).
    sky_frame
        ``"apparent"`` or ``"J2000"``: the sky put in the wrong frame
        (:func:`independent_tsky`).

    Returns
    -------
    Truth
        The inputs and the Tsky that went into the file.
    """
    path = Path(path)
    freqs = default_freqs() if freqs_hz is None else np.atleast_1d(np.asarray(freqs_hz, float))
    if freqs.size < 2:
        raise ValueError("need at least two channels (the channel width is their spacing)")
    steps = np.diff(freqs)
    if np.any(steps <= 0) or not np.allclose(steps, steps[0], rtol=1e-6, atol=0):
        raise ValueError("freqs_hz must be evenly spaced and increasing")
    channel_width = float(steps[0])
    pols = tuple(str(p).lower() for p in pols)
    for pol in pols:
        if pol not in _POL_CODES:
            raise ValueError(f"unknown polarisation {pol!r}: use 'ee' or 'nn'")
    antennas = tuple(int(a) for a in antennas)
    if len(set(antennas)) != len(antennas) or len(set(pols)) != len(pols):
        raise ValueError("antennas and polarisations must be distinct")
    if integration_s <= 0 or duration_min <= 0 or dnu_dt <= 0:
        raise ValueError("integration_s, duration_min and dnu_dt must be positive")

    ntime = max(1, round(duration_min * 60.0 / integration_s))
    jd0 = jd_at_lst(lst_start_h, jd_night)
    jds = jd0 + np.arange(ntime) * (integration_s / 86400.0)

    gain0 = default_bandpass(freqs) if G0 is None else np.asarray(G0, dtype=np.float64)
    gain0 = np.broadcast_to(gain0, freqs.shape).copy()
    trxr = np.broadcast_to(np.asarray(trxr_k, dtype=np.float64), freqs.shape).copy()
    if np.any(gain0 <= 0):
        raise ValueError("G0 must be positive")
    fractional = _drift_values(jds, drift_total, drift)
    gain = gain0[None, :] * (1.0 + fractional[:, None])
    s_time = 2.0 * _drift_values(jds, 1.0, None)  # -1 .. +1 (linear in time)
    trxr_drift = float(noise_drift) * s_time if noise_drift else None
    if trxr_drift is not None and np.any(1.0 + trxr_drift <= 0):
        raise ValueError("noise_drift must keep the receiver temperature positive")
    change = None if sky is None or sky.is_default else sky

    tsky = np.stack(
        [
            independent_tsky(
                freqs,
                jds + clock_offset_s / 86400.0,
                pol,
                beam,
                tgnd_k,
                node_spacing_s=node_spacing_s,
                sky=change,
                beam_width=beam_width,
                beam_width_mode=beam_width_mode,
                sky_frame=sky_frame,
            )
            for pol in pols
        ]
    )
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((len(antennas), len(pols), ntime, freqs.size))
    trxr_t = trxr[None, :] if trxr_drift is None else trxr[None, :] * (1 + trxr_drift[:, None])
    model = gain[None, None] * (tsky[None] + trxr_t[None, None])
    if feed_gain is not None:
        feed_gain = np.asarray(feed_gain, dtype=np.float64)
        if feed_gain.shape != (len(antennas), len(pols), ntime) or np.any(feed_gain <= 0):
            raise ValueError("feed_gain must be positive, (Nant, Npol, Ntime)")
        model = model * feed_gain[..., None]
    data = model * (1.0 + noise / math.sqrt(dnu_dt))

    nsample = dnu_dt / (channel_width * integration_s)
    sky_text = "GSM2008+CMB" if change is None else f"GSM2008 changed ({change})"
    history = (
        "Simulated by tests/independent_sim.py (independent of autocal's Tsky engine): "
        f"{sky_text} nside {SIM_NSIDE}, {beam} beam (width x {1 + beam_width:g}, "
        f"{beam_width_mode}), hard horizon, Tgnd {tgnd_k} K, receiver drift e_1 "
        f"{noise_drift:g}, seed {seed}."
    )
    lsts = _write_uvh5(
        path, data, freqs, jds, antennas, pols, integration_s, channel_width, nsample, history
    )
    logger.info(
        "wrote %s: %d antennas, %s, %d times, %d channels",
        path,
        len(antennas),
        pols,
        ntime,
        freqs.size,
    )
    settings = {
        "lst_start_h": float(lst_start_h),
        "duration_min": float(duration_min),
        "integration_s": float(integration_s),
        "drift_total": float(drift_total),
        "drift": "callable" if drift is not None else "linear",
        "dnu_dt": float(dnu_dt),
        "tgnd_k": float(tgnd_k),
        "beam": beam,
        "seed": int(seed),
        "jd_night": float(jd_night),
        "channel_width": channel_width,
        "nsample": float(nsample),
        "sim_nside": SIM_NSIDE,
        "node_spacing_s": float(node_spacing_s) if node_spacing_s else 0.0,
        "noise_drift": float(noise_drift),
        "beam_width": float(beam_width),
        "beam_width_mode": beam_width_mode,
        "clock_offset_s": float(clock_offset_s),
        "sky_frame": sky_frame,
        "sky": None if change is None else dataclasses.asdict(change),
    }
    return Truth(
        path=path,
        freqs=_readonly(freqs),
        jds=_readonly(jds),
        lsts=_readonly(lsts),
        antennas=antennas,
        pols=pols,
        tsky=_readonly(tsky),
        G=_readonly(gain),
        G0=_readonly(gain0),
        Trxr=_readonly(trxr),
        G_mean=_readonly(gain.mean(axis=0)),
        drift=_readonly(fractional),
        dnu_dt=float(dnu_dt),
        settings=settings,
        trxr_drift=None if trxr_drift is None else _readonly(trxr_drift),
    )
