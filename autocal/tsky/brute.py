"""The references the ring-FFT engine is checked against.

* :func:`tsky_brute` (the physics reference). For each LST the beam is evaluated afresh at
  every pixel's (az, alt) and the sums of :mod:`autocal.tsky.ringfft`'s formula are taken
  directly. Cost grows linearly with the number of LSTs; the ground truth of the tests.
* :class:`BruteForceTsky` (the benchmark baseline): beam precomputed once, sky rotated
  per LST, one matrix product per LST.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sp_fft
from tqdm.auto import tqdm

from autocal.core.coords import hadec_to_altaz, healpix_ra_dec
from autocal.core.lazy import healpy as hp
from autocal.core.sites import Site
from autocal.core.stopping import checkpoint
from autocal.sky.beam_base import Beam
from autocal.sky.models import SkyComponents
from autocal.tsky.horizon import HORIZON_WIDTH_DEG, horizon_weight, topocentric_at_lst0
from autocal.tsky.result import T_GROUND, TskyResult, check_grid, tgnd_array
from autocal.tsky.ringfft import progress_disabled
from autocal.tsky.synthesis import lst_radians


def tsky_brute(
    sky: SkyComponents,
    beam: Beam,
    site: Site,
    lsts: np.ndarray,
    tgnd: float | np.ndarray = T_GROUND,
    horizon_width_deg: float = HORIZON_WIDTH_DEG,
    progress: bool | None = None,
) -> TskyResult:
    """Compute Tsky by brute force: the beam is evaluated afresh at every pixel and LST.

    Parameters are as for :func:`~autocal.tsky.ringfft.tsky_fft`. Cost grows linearly
    with the number of LSTs; used in tests and benchmarks as the ground truth.
    """
    freqs = beam.check_freqs(sky.freqs)
    lsts = check_grid(lsts, "LST")
    tg = tgnd_array(tgnd, freqs.size)
    ra, dec = healpix_ra_dec(sky.nside)
    lat = np.radians(site.lat_deg)
    tmap = sky.temperature()  # (Nf, Npix)
    out = np.empty((lsts.size, freqs.size))
    f_below = np.empty((lsts.size, freqs.size))
    for i, lst in enumerate(
        tqdm(lst_radians(lsts), desc="Tsky (brute force)", disable=progress_disabled(progress))
    ):
        checkpoint("a brute-force Tsky LST")
        alt, az = hadec_to_altaz(lst - ra, dec, lat)
        bvals = beam.power(freqs, az, np.pi / 2 - alt)
        w_above = horizon_weight(alt, horizon_width_deg)
        total = bvals.sum(axis=1)
        below = bvals @ (1.0 - w_above)
        out[i] = (np.einsum("fp,fp,p->f", bvals, tmap, w_above) + tg * below) / total
        f_below[i] = below / total
    fb = f_below.mean(axis=0)
    return TskyResult(tsky=out, freqs=freqs, lsts=lsts, f_above=1 - fb, f_below=fb)


class BruteForceTsky:
    """Vectorised per-LST brute force: the reference the engine is benchmarked against.

    What is precomputed once (:meth:`__init__`, "preparation"):

    * the beam at every frequency on the equatorial HEALPix grid at LST 0 (each pixel's
      azimuth and zenith angle at LST 0, one :meth:`Beam.on` evaluator), its integral
      and below-horizon part per frequency, and the horizon-weighted beam ``A w`` on the
      pixels where the weight is positive, stored as one C-contiguous
      ``(Nfreq, Nabove)`` matrix of ``dtype``;
    * the Fourier transforms along each iso-latitude ring of the sky's spatial
      components (``Ncomp``, 4 for GSM2008 with the CMB).

    What is done per LST ``L`` (:meth:`__call__`): the sky components are rotated about
    the celestial pole by ``L``: on every ring the map is shifted by ``L`` in right
    ascension *exactly* for a ring-band-limited map (phase factor ``exp(i m L)`` on
    each ring harmonic, inverse FFT), then one matrix product
    ``(Nfreq, Nabove) @ (Nabove, Ncomp)`` (BLAS) gives every frequency's overlap with
    every component, combined with the component spectra. The beam fixed in the
    topocentric frame and the sky turning under it is the same physics as
    :func:`tsky_brute` (which instead evaluates the beam afresh at each LST on the fixed
    sky pixels); the two differ only by pixelisation (mK at nside 128, tested).

    The ring rotation is the same band-limited interpolation the ring-FFT engine
    implies, so :func:`~autocal.tsky.ringfft.tsky_fft` and this class agree to rounding:
    the comparison checks the engine's implementation, :func:`tsky_brute` its physics.

    Parameters
    ----------
    sky, beam, site, tgnd, horizon_width_deg
        As for :func:`~autocal.tsky.ringfft.tsky_fft`.
    dtype
        Precision of the beam matrix and of the per-LST products.
    freq_chunk
        Frequencies evaluated together while building the beam matrix (memory bound).
    """

    def __init__(
        self,
        sky: SkyComponents,
        beam: Beam,
        site: Site,
        tgnd: float | np.ndarray = T_GROUND,
        horizon_width_deg: float = HORIZON_WIDTH_DEG,
        dtype: type = np.float64,
        freq_chunk: int = 64,
    ) -> None:
        self.freqs = beam.check_freqs(sky.freqs)
        self.tgnd = tgnd_array(tgnd, self.freqs.size)
        self.spectra = sky.spectra
        self.dtype = np.dtype(dtype)
        nside, nfreq = sky.nside, self.freqs.size
        az, za = topocentric_at_lst0(nside, site)
        w_above = horizon_weight(np.pi / 2 - za, horizon_width_deg)
        self.above = np.flatnonzero(w_above > 0)
        evaluator = beam.on(az, za)
        self.beam_matrix = np.empty((nfreq, self.above.size), dtype=self.dtype)
        self.sum_all = np.empty(nfreq)
        self.sum_below = np.empty(nfreq)
        w_sel = w_above[self.above]
        for start in range(0, nfreq, freq_chunk):
            sel = slice(start, min(start + freq_chunk, nfreq))
            vals = evaluator(self.freqs[sel])  # (Nf, Npix)
            self.sum_all[sel] = vals.sum(axis=1)
            self.sum_below[sel] = vals @ (1.0 - w_above)
            self.beam_matrix[sel] = vals[:, self.above] * w_sel
        # ring transforms of the sky components that move (not the constant CMB map)
        nring = 4 * nside - 1
        start, length, _, _, _ = hp.ringinfo(nside, np.arange(1, nring + 1))
        self._maps = sky.maps
        self._moving = np.flatnonzero(np.ptp(sky.maps, axis=1) > 0)
        moving = sky.maps[self._moving]
        self._eq = (int(start[nside - 1]), 2 * nside + 1, 4 * nside)  # first, rings, n
        first, rings, n = self._eq
        block = moving[:, first : first + rings * n].reshape(moving.shape[0], rings, n)
        self._eq_hat = sp_fft.rfft(block, axis=-1)
        eq_rings = range(nside - 1, 3 * nside)
        self._caps = [
            (int(start[r]), int(length[r]), sp_fft.rfft(moving[:, start[r] : start[r] + length[r]]))
            for r in range(nring)
            if r not in eq_rings
        ]
        self._ncomp = sky.ncomp

    def rotated_sky(self, lst_rad: float) -> np.ndarray:
        """Sky components turned by the LST: ``(Ncomp, Npix)``, value at pixel p = S(RA_p + L)."""
        out = self._maps.copy()
        if self._moving.size == 0:
            return out
        rot = np.empty((self._moving.size, self._maps.shape[1]))
        first, rings, n = self._eq
        phase = np.exp(1j * lst_rad * np.arange(n // 2 + 1))
        eq = sp_fft.irfft(self._eq_hat * phase, n=n, axis=-1)
        rot[:, first : first + rings * n] = eq.reshape(self._moving.size, -1)
        for start, length, s_hat in self._caps:
            phase = np.exp(1j * lst_rad * np.arange(length // 2 + 1))
            rot[:, start : start + length] = sp_fft.irfft(s_hat * phase, n=length)
        out[self._moving] = rot
        return out

    def __call__(
        self, lsts: np.ndarray, lsts_per_product: int = 1, progress: bool | None = None
    ) -> TskyResult:
        """Tsky at ``lsts`` (hours).

        Parameters
        ----------
        lsts
            LSTs in hours.
        lsts_per_product
            LSTs whose rotated skies share one matrix product (1: one product per LST;
            more trades memory for BLAS efficiency).
        progress
            Progress bar (``None``: only on a terminal).

        Returns
        -------
        TskyResult
            The table (``f_above``/``f_below`` as for :func:`~autocal.tsky.ringfft.tsky_fft`).
        """
        lsts = check_grid(lsts, "LST")
        lst_rad = lst_radians(lsts)
        out = np.empty((lsts.size, self.freqs.size))
        batch = max(1, int(lsts_per_product))
        ncomp = self._ncomp
        starts = range(0, lsts.size, batch)
        for i0 in tqdm(
            starts, desc="Tsky (vectorised brute force)", disable=progress_disabled(progress)
        ):
            sel = lst_rad[i0 : i0 + batch]
            sky_rot = np.empty((self.above.size, ncomp * sel.size), dtype=self.dtype)
            for j, lst in enumerate(sel):
                sky_rot[:, j * ncomp : (j + 1) * ncomp] = self.rotated_sky(lst)[:, self.above].T
            overlap = self.beam_matrix @ sky_rot  # (Nf, Ncomp * Nbatch): the per-LST product
            overlap = overlap.reshape(self.freqs.size, sel.size, ncomp)
            numerator = np.einsum("fc,flc->lf", self.spectra, overlap)
            out[i0 : i0 + sel.size] = (numerator + self.tgnd * self.sum_below) / self.sum_all
        f_below = self.sum_below / self.sum_all
        return TskyResult(
            tsky=out, freqs=self.freqs, lsts=lsts, f_above=1 - f_below, f_below=f_below
        )
