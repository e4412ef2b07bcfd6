"""Beams read from files: HEALPix UVBeam files (HERA) and EDGES FEKO files.

Both are tabulated at native frequencies and interpolated in frequency by a cubic spline
(:class:`GriddedFileBeam`); in direction, HEALPix maps are upsampled once by spherical
harmonics and interpolated bilinearly, FEKO grids bilinearly in azimuth and elevation.

pyuvdata's UVBeam measures azimuth from east through north, so ``az_uvbeam = pi/2 - az``;
EDGES FEKO files measure azimuth from the antenna's excitation axis, rotated to true
azimuth by ``rotation_from_north`` (edges-analysis default: 90 deg). Conventions in
:mod:`autocal.sky.beam_base`.
"""

from __future__ import annotations

import logging
from abc import abstractmethod
from functools import cached_property
from pathlib import Path

import numpy as np

from autocal.core.files import file_checksum
from autocal.core.lazy import healpy as hp
from autocal.io.beamfits import HealpixBeamData, read_healpix_power_beam
from autocal.io.feko import BeamFileError, read_feko_beam
from autocal.sky.beam_base import Beam, BeamEvaluator, check_pol

logger = logging.getLogger(__name__)


class GriddedFileBeam(Beam):
    """Common frequency interpolation of beams tabulated at native frequencies.

    A cubic spline in frequency (scipy's ``CubicSpline``, not-a-knot ends) through the
    tabulated values ``y_j``, clipped at zero. It is evaluated in its local form: on the
    interval ``[x_i, x_i+1]`` (width ``h``, ``a = (x_i+1 - x) / h``, ``b = 1 - a``)

        S(x) = a y_i + b y_i+1 + [(a^3 - a) M_i + (b^3 - b) M_i+1] h^2 / 6

    with the knot second derivatives ``M = Q y`` (``Q`` from the spline of the identity).
    So every frequency needs four tabulated rows and a band of neighbouring frequencies a
    handful, whatever the number of native frequencies.
    """

    native_freqs: np.ndarray

    @property
    def freq_range(self):  # noqa: D102
        return float(self.native_freqs[0]), float(self.native_freqs[-1])

    @abstractmethod
    def _spatial(self, az: np.ndarray, za: np.ndarray) -> np.ndarray:
        """Beam at native frequencies ``(Nnative, Ndir)``."""

    def _spatial_t(self, az: np.ndarray, za: np.ndarray) -> np.ndarray:
        """Beam at native frequencies, direction-major ``(Ndir, Nnative)`` float64."""
        return np.ascontiguousarray(self._spatial(az, za).T)

    def _knots(self, native_t: np.ndarray) -> np.ndarray:
        """Interleave values and second derivatives: ``(Ndir, 2 Nnative)`` = y0 M0 y1 M1..."""
        nat = self.native_freqs.size
        out = np.empty((native_t.shape[0], 2 * nat))
        out[:, 0::2] = native_t
        out[:, 1::2] = native_t @ self._curvature.T
        return out

    @cached_property
    def _curvature(self) -> np.ndarray:
        """``(Nnative, Nnative)`` matrix ``Q``: knot second derivatives ``M = Q y``."""
        nat = self.native_freqs.size
        if nat < 3:  # constant or linear: no curvature
            return np.zeros((nat, nat))
        from scipy.interpolate import CubicSpline  # ~0.25 s to import: not for a cache hit

        spline = CubicSpline(self.native_freqs, np.eye(nat), axis=0)
        return spline.derivative(2)(self.native_freqs)  # (knot, basis)

    def _local_weights(self, freqs: np.ndarray) -> tuple[slice, np.ndarray]:
        """Rows of :meth:`_knots` used by ``freqs`` and their ``(Nrows, Nfreq)`` weights."""
        x = self.native_freqs
        if x.size == 1:
            return slice(0, 1), np.ones((1, freqs.size))
        f = np.clip(freqs, *self.freq_range)
        i = np.clip(np.searchsorted(x, f, side="right") - 1, 0, x.size - 2)
        h = x[i + 1] - x[i]
        a = (x[i + 1] - f) / h
        b = 1.0 - a
        first = 2 * int(i.min())
        rows = 2 * int(i.max()) + 4 - first
        weights = np.zeros((rows, f.size))
        cols = np.arange(f.size)
        r = 2 * i - first
        weights[r, cols] = a
        weights[r + 1, cols] = (a**3 - a) * h**2 / 6
        weights[r + 2, cols] = b
        weights[r + 3, cols] = (b**3 - b) * h**2 / 6
        return slice(first, first + rows), weights

    def _interp_freq(self, native: np.ndarray, freqs: np.ndarray) -> np.ndarray:
        rows, weights = self._local_weights(freqs)
        out = weights.T @ self._knots(native.T)[:, rows].T
        return np.maximum(out, 0.0, out=out)

    def power(self, freqs, az, za):  # noqa: D102
        freqs = self.check_freqs(freqs)
        return self._interp_freq(self._spatial(np.asarray(az), np.asarray(za)), freqs)

    def on(self, az, za):  # noqa: D102
        return _GriddedEvaluator(self, az, za)


class _GriddedEvaluator(BeamEvaluator):
    """A gridded file beam bound to directions, with its spline knots precomputed.

    Holds the ``(Ndir, 2 Nnative)`` knot table (values and second derivatives in
    frequency, see :class:`GriddedFileBeam`); a chunk of frequencies costs one thin
    matrix product with the few knot columns it needs, then the clip at zero.
    """

    #: Largest ``rows x Nfreq`` of one matrix product in :meth:`by_direction`: such small
    #: products run single-threaded in OpenBLAS, which avoids its thread hand-offs (they
    #: dominate for these thin memory-bound products, badly so on a busy machine).
    _BLOCK = 16384
    nonnegative = True  # clipped at zero

    def __init__(self, beam: GriddedFileBeam, az: np.ndarray, za: np.ndarray) -> None:
        super().__init__(beam, az, za)
        self.beam: GriddedFileBeam = beam
        self._table = beam._knots(beam._spatial_t(self.az, self.za))
        self._memo: dict[bytes, tuple[slice, np.ndarray]] = {}

    def _weights(self, freqs: np.ndarray) -> tuple[slice, np.ndarray]:
        """Return the checked local spline weights (memoised for recent ``freqs``).

        The engine asks for the same frequency chunk block after block of directions.
        """
        freqs = np.asarray(freqs, dtype=np.float64)
        key = freqs.tobytes()
        hit = self._memo.get(key)
        if hit is None:
            hit = self.beam._local_weights(self.beam.check_freqs(freqs))
            if len(self._memo) >= 16:
                self._memo.clear()
            self._memo[key] = hit
        return hit

    def __call__(self, freqs: np.ndarray) -> np.ndarray:
        """Return ``(Nfreq, Ndir)`` beam values at ``freqs`` (Hz)."""
        rows, weights = self._weights(freqs)
        out = weights.T @ self._table[:, rows].T
        return np.maximum(out, 0.0, out=out)

    def by_direction(self, freqs: np.ndarray, rows: slice | None = None) -> np.ndarray:
        """Return ``(Nrows, Nfreq)`` beam values (see :meth:`BeamEvaluator.by_direction`)."""
        cols, weights = self._weights(freqs)
        table = self._table[:, cols] if rows is None else self._table[rows, cols]
        nf = weights.shape[1]
        out = np.empty((table.shape[0], nf))
        step = max(16, self._BLOCK // nf)
        for start in range(0, table.shape[0], step):
            np.matmul(table[start : start + step], weights, out=out[start : start + step])
        return np.maximum(out, 0.0, out=out)


def _upsampled(path: str, pol: str, nside_out: int, mtime: int, maps: np.ndarray) -> np.ndarray:
    """Harmonic upsampling of beam maps, memoised per file, pol and resolution.

    Returns the direction-major ``(Npix_out, Nfreq)`` float32 maps (bilinear
    interpolation then reads each neighbour's spectrum contiguously).
    """
    key = (path, pol, nside_out, mtime)
    if key not in _UPSAMPLED:
        nside = hp.npix2nside(maps.shape[1])
        lmax = 3 * nside - 1
        fine = np.empty((hp.nside2npix(nside_out), maps.shape[0]), dtype=np.float32)
        for i, m in enumerate(maps):
            fine[:, i] = hp.alm2map(hp.map2alm(m, lmax=lmax, iter=3), nside_out, lmax=lmax)
        _UPSAMPLED.clear()  # keep one beam's maps (~330 MB at nside 512 for 26 freqs)
        _UPSAMPLED[key] = np.maximum(fine, 0.0, out=fine)
    return _UPSAMPLED[key]


_UPSAMPLED: dict[tuple, np.ndarray] = {}


def _header_nside(path: Path) -> int | None:
    """Return the ``NSIDE`` of a beamfits file's primary header (pyuvdata's), or None."""
    from astropy.io import fits

    try:
        value = fits.getval(path, "NSIDE", ext=0)
    except (OSError, KeyError, ValueError, IndexError):
        return None
    return int(value) if isinstance(value, (int, np.integer)) and value > 0 else None


class HealpixFileBeam(GriddedFileBeam):
    """A HEALPix power beam read with pyuvdata (e.g. the HERA Fagnoni beamfits).

    The stored maps (zenith at the pole, pyuvdata azimuth from east through north) are
    upsampled once, on first evaluation, by spherical-harmonic interpolation (band limit
    ``3 nside - 1`` of the file) to ``upsample_nside`` (stored as float32), then
    interpolated bilinearly: the beam is smooth, so evaluating it on rotated grids does
    not add pixel-scale noise. A cubic spline interpolates in frequency.

    The file is read when its values are first needed (a Tsky cache hit never needs them):
    a missing file is reported at construction, a file without the polarisation or with
    unreadable values when the beam is first evaluated or its frequency range asked for.
    """

    def __init__(self, path: str | Path, pol: str = "ee", upsample_nside: int = 512) -> None:
        self.path = Path(path)
        self.pol = check_pol(pol)
        self.name = self.path.name
        if self.path.is_dir():
            raise BeamFileError(
                f"beam {self.path} is a folder: give a beam file (UVBeam beamfits, FEKO .txt) "
                "or a named beam (dipole, airy, hera, edges-low, ...)"
            )
        if not self.path.is_file():
            raise BeamFileError(f"beam file {self.path} does not exist")
        # The file is read (through pyuvdata, ~1 s with its import) when its values are
        # first needed: naming the beam for a Tsky cache hit needs only its nside, from
        # the primary FITS header. Without one the file is read now, with its errors.
        nside = _header_nside(self.path)
        if nside is None:
            nside = self.data.nside
        self.upsample_nside = max(int(upsample_nside), nside)

    @cached_property
    def data(self) -> HealpixBeamData:
        """The file's beam at its native frequencies and pixels."""
        return read_healpix_power_beam(self.path, self.pol)

    @property
    def native_freqs(self) -> np.ndarray:  # type: ignore[override]
        """The file's frequencies (Hz)."""
        return self.data.freqs

    @cached_property
    def _native_maps(self) -> np.ndarray:
        """``(Nfreq, Npix)`` RING maps at the file's nside (zero where it has no pixel)."""
        nside = self.data.nside
        full = np.zeros((self.data.freqs.size, hp.nside2npix(nside)))
        pix = self.data.pixels
        if self.data.nest:
            pix = hp.nest2ring(nside, pix)
        full[:, pix] = self.data.data
        if pix.size != hp.nside2npix(nside):
            logger.warning(
                "%s covers %d of %d pixels; missing ones are zero",
                self.path,
                pix.size,
                hp.nside2npix(nside),
            )
        return full

    @cached_property
    def _maps_t(self) -> np.ndarray:
        """Direction-major ``(Npix, Nfreq)`` maps, upsampled on first evaluation.

        Not at construction: naming the beam (:meth:`describe`, the Tsky cache key) and
        checking frequencies need only the file, so a Tsky cache hit skips the harmonic
        upsampling (~1.7 s and ~330 MB per polarisation for the HERA beam).
        """
        nside = hp.npix2nside(self._native_maps.shape[1])
        if self.upsample_nside > nside:
            return _upsampled(
                str(self.path.resolve()),
                self.pol,
                self.upsample_nside,
                self.path.stat().st_mtime_ns,
                self._native_maps,
            )
        return np.ascontiguousarray(self._native_maps.T)  # (Npix, Nfreq)

    def _spatial(self, az, za):
        return self._spatial_t(az, za).T

    def _spatial_t(self, az, za):
        phi = np.mod(np.pi / 2 - np.asarray(az), 2 * np.pi)  # pyuvdata: east to north
        theta = np.clip(za, 0.0, np.pi)
        theta, phi = np.atleast_1d(theta).ravel(), np.atleast_1d(phi).ravel()
        # healpy's bilinear interpolation (as hp.get_interp_val), with the neighbours and
        # weights found once for all native frequencies
        nside = hp.npix2nside(self._maps_t.shape[0])
        pix, wgt = hp.get_interp_weights(nside, theta, phi)
        out = self._maps_t[pix[0]] * wgt[0][:, None]
        for k in range(1, 4):
            out += self._maps_t[pix[k]] * wgt[k][:, None]
        return out

    def describe(self):  # noqa: D102
        return {
            "beam": "uvbeam_healpix",
            "file": str(self.path),
            "pol": self.pol,
            "upsample_nside": self.upsample_nside,
            "sha256": file_checksum(self.path),
        }


class FekoFileBeam(GriddedFileBeam):
    """An EDGES FEKO beam (gain on a 1-degree azimuth x elevation grid above the horizon).

    The file's azimuth is measured from the antenna excitation axis; true azimuth (east of
    north) = file azimuth + ``rotation_from_north``. The pattern is bilinear in azimuth
    and elevation, cubic in frequency, and zero below the horizon (the files do not cover
    it). Polarisation: the single excitation of the file (``pol`` is recorded only).
    """

    def __init__(
        self, path: str | Path, rotation_from_north: float = 90.0, pol: str = "ee"
    ) -> None:
        self.path = Path(path)
        self.pol = check_pol(pol)
        self.rotation_from_north = float(rotation_from_north)
        self.data = read_feko_beam(self.path)
        self.native_freqs = self.data.freqs
        self.name = f"feko:{self.path.parent.name}/{self.path.name}"

    def _spatial(self, az, za):
        gain = self.data.gain  # (Nf, 360, 91)
        file_az = np.mod(np.degrees(az) - self.rotation_from_north, 360.0)
        el = 90.0 - np.degrees(za)
        above = el >= 0
        el_c = np.clip(el, 0.0, 90.0)
        i0 = np.floor(file_az).astype(int) % 360
        i1 = (i0 + 1) % 360
        wa = file_az - np.floor(file_az)
        j0 = np.minimum(np.floor(el_c).astype(int), 89)
        wb = el_c - j0
        out = (
            (1 - wa) * (1 - wb) * gain[:, i0, j0]
            + wa * (1 - wb) * gain[:, i1, j0]
            + (1 - wa) * wb * gain[:, i0, j0 + 1]
            + wa * wb * gain[:, i1, j0 + 1]
        )
        return np.where(above[None, :], out, 0.0)

    def describe(self):  # noqa: D102
        return {
            "beam": "feko",
            "file": str(self.path),
            "pol": self.pol,
            "rotation_from_north_deg": self.rotation_from_north,
            "sha256": file_checksum(self.path),
        }
