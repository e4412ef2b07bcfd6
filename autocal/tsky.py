"""Beam-weighted sky temperature Tsky(nu, LST) of a drift-scan antenna.

    Tsky(nu, t) = [ sum_above A Tmap + Tgnd sum_below A ] / sum_all A

The beam ``A`` is fixed in topocentric coordinates; ``Tmap`` includes the CMB exactly
once (see :mod:`autocal.sky`); the ground below the horizon radiates ``Tgnd`` (300 K by
default, scalar or per frequency).

Two implementations:

* :func:`tsky_fft` (the engine). For a drift scan the sky seen at LST ``L`` is the sky
  rotated about the celestial pole by ``L``. On HEALPix iso-latitude rings both the
  above-horizon beam (in equatorial coordinates at LST 0) and each sky component are
  Fourier-transformed along the ring once; the overlap at every LST is then
  ``Re sum_m D_m exp(-i m L)`` with ``D_m = sum_rings w_m B_m conj(T_m) / n_ring``: a
  ring-wise circular cross-correlation, exact up to pixelisation (band-limited
  interpolation in LST). The cost is independent of the number of LSTs; sky components
  are transformed once whatever the number of frequencies.
* :func:`tsky_brute` (the reference). For each LST the beam is evaluated afresh at every
  pixel's (az, alt) and the sums above are taken directly.

:func:`compute_tsky` is the public entry point: it resolves names, checks the grids,
chooses the method, and reads/writes the on-disk cache (:mod:`autocal.tsky_cache`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import healpy as hp
import numpy as np
from tqdm.auto import tqdm

from autocal.beams import Beam, get_beam
from autocal.coords import hadec_to_altaz, healpix_ra_dec, parse_epoch
from autocal.sites import Site, get_site
from autocal.sky import SkyComponents, SkyModel, get_sky

logger = logging.getLogger(__name__)

#: Default ground temperature in kelvin.
T_GROUND = 300.0
#: Bump when the numerical method changes, so cached tables are recomputed.
ENGINE_VERSION = "ringfft-1"


class TskyError(ValueError):
    """Invalid input to the Tsky computation."""


@dataclass(frozen=True)
class TskyResult:
    """A Tsky table.

    Attributes
    ----------
    tsky
        ``(Nlst, Nfreq)`` beam-weighted sky temperature in kelvin (CMB and ground included).
    freqs
        ``(Nfreq,)`` Hz.
    lsts
        ``(Nlst,)`` local sidereal times in hours.
    f_above, f_below
        ``(Nfreq,)`` fractions of the beam integral above / below the horizon.
    meta
        Description of the sky, beam, site, ground temperature, resolution, epoch, method.
    components
        Optional ``(Nlst, Nfreq, Ncomp)`` contribution of each sky component's *spatial
        map* (unit spectrum) to Tsky; ``tsky = sum_c spectra[f, c] components[..., c] +
        Tgnd f_below``. Lets a caller change component spectra without recomputing.
    spectra
        ``(Nfreq, Ncomp)`` the sky's component spectra, when ``components`` is given.
    """

    tsky: np.ndarray
    freqs: np.ndarray
    lsts: np.ndarray
    f_above: np.ndarray
    f_below: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    components: np.ndarray | None = None
    spectra: np.ndarray | None = None


def check_grid(values: np.ndarray | list[float] | float, what: str) -> np.ndarray:
    """Return a finite 1-D float array, raising :class:`TskyError` if empty or non-finite."""
    arr = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if arr.ndim != 1:
        raise TskyError(f"the {what} grid must be one-dimensional")
    if arr.size == 0:
        raise TskyError(f"the {what} grid is empty: give at least one value")
    if not np.all(np.isfinite(arr)):
        raise TskyError(f"the {what} grid has non-finite values")
    return arr


def _tgnd_array(tgnd: float | np.ndarray, nfreq: int) -> np.ndarray:
    arr = np.asarray(tgnd, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(nfreq, float(arr))
    if arr.shape != (nfreq,):
        raise TskyError(
            f"ground temperature must be a scalar or have one value per frequency "
            f"({nfreq}), got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise TskyError("ground temperature must be finite and >= 0 K")
    return arr


#: Default width of the soft horizon, degrees (see :func:`horizon_weight`).
HORIZON_WIDTH_DEG = 2.0


def horizon_weight(alt: np.ndarray, width_deg: float = HORIZON_WIDTH_DEG) -> np.ndarray:
    """Fraction of the beam weight at altitude ``alt`` (radians) that sees the sky.

    The horizon is a soft edge: the weight rises from 0 to 1 as a C1 smoothstep over
    ``width_deg`` centred on altitude 0 (real horizons are not a perfect plane, and a
    HEALPix pixel straddling the horizon sees partly sky and partly ground). Both Tsky
    implementations use it; a hard cut at pixel centres would add pixel-edge noise as
    the sky rotates. ``width_deg = 0`` gives the hard cut.
    """
    alt = np.asarray(alt, dtype=np.float64)
    if width_deg <= 0:
        return (alt > 0).astype(np.float64)
    x = np.clip(0.5 + alt / np.radians(width_deg), 0.0, 1.0)
    return x * x * (3 - 2 * x)


def topocentric_at_lst0(nside: int, site: Site) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth (east of north) and zenith angle of every equatorial pixel at LST 0.

    Returns
    -------
    az, za
        Radians, ``(Npix,)`` each.
    """
    ra, dec = healpix_ra_dec(nside)
    alt, az = hadec_to_altaz(-ra, dec, np.radians(site.lat_deg))
    return az, np.pi / 2 - alt


@dataclass(frozen=True)
class _RingGroup:
    """Rings of one length: ``pix`` is ``(Nring, n)`` RING indices."""

    pix: np.ndarray

    @property
    def n(self) -> int:
        return self.pix.shape[1]


def ring_groups(nside: int) -> list[_RingGroup]:
    """Group the HEALPix rings of ``nside`` by length (north and south caps paired)."""
    nring = 4 * nside - 1
    start, npix_ring, _, _, _ = hp.ringinfo(nside, np.arange(1, nring + 1))
    groups = []
    for i in range(1, nside):
        north, south = i - 1, nring - i
        rows = [np.arange(start[r], start[r] + npix_ring[r]) for r in (north, south)]
        groups.append(_RingGroup(np.array(rows)))
    eq = np.arange(nside - 1, 3 * nside)  # 2 nside + 1 equatorial rings of 4 nside pixels
    groups.append(_RingGroup(np.array([np.arange(start[r], start[r] + npix_ring[r]) for r in eq])))
    return groups


def _ring_weights(n: int) -> np.ndarray:
    """Weights turning one-sided rfft products into the two-sided sum (even ``n``)."""
    w = np.full(n // 2 + 1, 2.0)
    w[0] = 1.0
    if n % 2 == 0:
        w[-1] = 1.0
    return w


def _lst_radians(lsts_hours: np.ndarray) -> np.ndarray:
    return np.mod(lsts_hours, 24.0) * (2 * np.pi / 24.0)


def tsky_fft(
    sky: SkyComponents,
    beam: Beam,
    site: Site,
    lsts: np.ndarray,
    tgnd: float | np.ndarray = T_GROUND,
    horizon_width_deg: float = HORIZON_WIDTH_DEG,
    freq_chunk: int = 32,
    keep_components: bool = False,
    progress: bool | None = None,
) -> TskyResult:
    """Tsky at all LSTs by ring-wise FFT cross-correlation (see module docstring).

    Parameters
    ----------
    sky
        Low-rank equatorial sky (:meth:`autocal.sky.SkyModel.components`).
    beam
        Power beam.
    site
        Observatory.
    lsts
        LSTs in hours.
    tgnd
        Ground temperature in kelvin (scalar or per frequency).
    horizon_width_deg
        Width of the soft horizon (:func:`horizon_weight`).
    freq_chunk
        Frequencies processed together (bounds memory to ~``freq_chunk * Npix`` floats).
    keep_components
        Also return the per-component contributions (``TskyResult.components``).
    progress
        Show a progress bar (``None``: only on a terminal).

    Returns
    -------
    TskyResult
        The table.
    """
    freqs = beam.check_freqs(sky.freqs)
    lsts = check_grid(lsts, "LST")
    tg = _tgnd_array(tgnd, freqs.size)
    nside = sky.nside
    az, za = topocentric_at_lst0(nside, site)
    w_above = horizon_weight(np.pi / 2 - za, horizon_width_deg)
    evaluator = beam.on(az, za)
    groups = ring_groups(nside)
    mmax = 2 * nside
    # sky side: one FFT per component per ring group
    sky_hat = [np.conj(np.fft.rfft(sky.maps[:, g.pix], axis=-1)) for g in groups]
    ncomp, nfreq = sky.ncomp, freqs.size
    overlap = np.zeros((ncomp, nfreq, mmax + 1), dtype=np.complex128)
    sum_all = np.empty(nfreq)
    sum_below = np.empty(nfreq)
    chunks = range(0, nfreq, freq_chunk)
    for start in tqdm(chunks, desc="Tsky (ring FFT)", unit="chunk", disable=_no_bar(progress)):
        sel = slice(start, min(start + freq_chunk, nfreq))
        bvals = evaluator(freqs[sel])  # (Nf, Npix)
        if np.any(~np.isfinite(bvals)) or np.any(bvals < 0):
            raise TskyError(f"beam {beam.name} gave negative or non-finite values")
        sum_all[sel] = bvals.sum(axis=1)
        sum_below[sel] = bvals @ (1.0 - w_above)
        b_above = bvals * w_above[None, :]
        for g, s_hat in zip(groups, sky_hat, strict=True):
            b_hat = np.fft.rfft(b_above[:, g.pix], axis=-1)  # (Nf, Nr, m)
            b_hat *= _ring_weights(g.n) / g.n
            # sum over rings for every (component, freq, m): batched over m
            contrib = np.einsum("frm,crm->cfm", b_hat, s_hat, optimize=True)
            overlap[:, sel, : g.n // 2 + 1] += contrib
    if np.any(sum_all <= 0):
        bad = freqs[sum_all <= 0] / 1e6
        raise TskyError(f"beam {beam.name} integrates to zero at {bad[:5]} MHz")
    mvec = np.arange(mmax + 1)
    phase = np.outer(_lst_radians(lsts), mvec)  # (Nlst, M)
    cos_m, sin_m = np.cos(phase), np.sin(phase)
    total = np.einsum("fc,cfm->fm", sky.spectra, overlap)
    numerator = total.real @ cos_m.T + total.imag @ sin_m.T  # (Nf, Nlst)
    tsky = (numerator + (tg * sum_below)[:, None]) / sum_all[:, None]
    comps = None
    if keep_components:
        comps = (
            np.einsum("cfm,lm->lfc", overlap.real, cos_m)
            + np.einsum("cfm,lm->lfc", overlap.imag, sin_m)
        ) / sum_all[None, :, None]
    return TskyResult(
        tsky=tsky.T.copy(),
        freqs=freqs,
        lsts=lsts,
        f_above=1 - sum_below / sum_all,
        f_below=sum_below / sum_all,
        components=comps,
    )


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

    Parameters are as for :func:`tsky_fft`. Cost grows linearly with the number of LSTs;
    used in tests and benchmarks as the ground truth.
    """
    freqs = beam.check_freqs(sky.freqs)
    lsts = check_grid(lsts, "LST")
    tg = _tgnd_array(tgnd, freqs.size)
    ra, dec = healpix_ra_dec(sky.nside)
    lat = np.radians(site.lat_deg)
    tmap = sky.temperature()  # (Nf, Npix)
    out = np.empty((lsts.size, freqs.size))
    f_below = np.empty((lsts.size, freqs.size))
    for i, lst in enumerate(
        tqdm(_lst_radians(lsts), desc="Tsky (brute force)", disable=_no_bar(progress))
    ):
        alt, az = hadec_to_altaz(lst - ra, dec, lat)
        bvals = beam.power(freqs, az, np.pi / 2 - alt)
        w_above = horizon_weight(alt, horizon_width_deg)
        total = bvals.sum(axis=1)
        below = bvals @ (1.0 - w_above)
        out[i] = (np.einsum("fp,fp,p->f", bvals, tmap, w_above) + tg * below) / total
        f_below[i] = below / total
    fb = f_below.mean(axis=0)
    return TskyResult(tsky=out, freqs=freqs, lsts=lsts, f_above=1 - fb, f_below=fb)


def _no_bar(progress: bool | None) -> bool | None:
    """Tqdm's ``disable`` argument: ``None`` disables on non-terminals."""
    if progress is None:
        return None
    return not progress


def compute_tsky(
    sky: SkyModel | str,
    beam: Beam | str,
    site: Site | str,
    freqs: np.ndarray,
    lsts: np.ndarray,
    tgnd: float | np.ndarray = T_GROUND,
    nside: int = 64,
    epoch: Any = None,
    pol: str = "ee",
    horizon_width_deg: float = HORIZON_WIDTH_DEG,
    method: str = "fft",
    cache: bool = True,
    keep_components: bool = False,
    progress: bool | None = None,
) -> TskyResult:
    """Compute (or load from the cache) Tsky(nu, LST) for a sky, a beam and a site.

    Parameters
    ----------
    sky
        Sky model or its name (:func:`autocal.sky.get_sky`).
    beam
        Beam or its name/path (:func:`autocal.beams.get_beam`).
    site
        Site or its name (:func:`autocal.sites.get_site`).
    freqs
        Frequencies in Hz.
    lsts
        LSTs in hours.
    tgnd
        Ground temperature in kelvin (scalar or per frequency).
    nside
        HEALPix resolution of the computation.
    epoch
        Epoch of the equatorial frame (default J2000; use the observation date).
    pol
        Polarisation for named beams.
    horizon_width_deg
        Width of the soft horizon in degrees (:func:`horizon_weight`).
    method
        ``"fft"`` (fast engine) or ``"brute"`` (reference).
    cache
        Read and write the on-disk cache (:mod:`autocal.tsky_cache`).
    keep_components
        Also return per-component contributions (``fft`` only; never cached).
    progress
        Progress bar (``None``: only on a terminal).

    Returns
    -------
    TskyResult
        The table with its description in ``meta``.
    """
    from autocal import tsky_cache

    sky_model = get_sky(sky)
    beam_obj = get_beam(beam, pol)
    site_obj = get_site(site)
    freqs = beam_obj.check_freqs(check_grid(freqs, "frequency"))
    lsts = check_grid(lsts, "LST")
    tg = _tgnd_array(tgnd, freqs.size)
    if method not in {"fft", "brute"}:
        raise TskyError(f"unknown method {method!r}: use 'fft' or 'brute'")
    if not hp.isnsideok(nside, nest=True) or nside < 2:
        raise TskyError(f"nside {nside} must be a power of two >= 2")
    time_epoch = parse_epoch(epoch)
    meta = {
        "sky": sky_model.describe(),
        "beam": beam_obj.describe(),
        "site": site_obj.describe(),
        "tgnd_K": float(tg[0]) if np.all(tg == tg[0]) else "per-frequency",
        "nside": int(nside),
        "horizon_width_deg": float(horizon_width_deg),
        "epoch_jd": float(time_epoch.jd),
        "method": method,
        "engine_version": ENGINE_VERSION,
        "cmb": "included once (2.725 K)",
        "frame": "apparent equatorial of epoch (TETE); LST = apparent sidereal time",
        "azimuth_convention": "east of north",
    }
    key = tsky_cache.cache_key(meta, freqs, lsts, tg)
    if cache and not keep_components:
        hit = tsky_cache.load(key)
        if hit is not None:
            logger.info("Tsky cache hit %s", key)
            return hit
    t0 = time.perf_counter()
    comps = sky_model.components(freqs, nside=nside, epoch=time_epoch)
    if method == "fft":
        result = tsky_fft(
            comps,
            beam_obj,
            site_obj,
            lsts,
            tg,
            horizon_width_deg,
            keep_components=keep_components,
            progress=progress,
        )
    else:
        result = tsky_brute(
            comps, beam_obj, site_obj, lsts, tg, horizon_width_deg, progress=progress
        )
    elapsed = time.perf_counter() - t0
    meta["component_labels"] = list(comps.labels)
    meta["compute_seconds"] = round(elapsed, 3)
    result = TskyResult(
        tsky=result.tsky,
        freqs=result.freqs,
        lsts=result.lsts,
        f_above=result.f_above,
        f_below=result.f_below,
        meta=meta,
        components=result.components,
        spectra=comps.spectra if keep_components else None,
    )
    logger.info(
        "Tsky %s: %d LSTs x %d freqs at nside %d in %.2f s",
        method,
        lsts.size,
        freqs.size,
        nside,
        elapsed,
    )
    if cache and not keep_components:
        tsky_cache.store(key, result)
    return result
