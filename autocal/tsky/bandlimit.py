"""The sky as the Tsky engine needs it: band-limited to what its HEALPix grid resolves.

The engine (:mod:`autocal.tsky.ringfft`) sums beam x sky over the pixel centres of one
HEALPix grid. A sky sampled at those centres from a map with structure at the pixel
scale (GSM2008's native nside 64, interpolated bilinearly) aliases that structure into
the beam-weighted sum; averaging the sky over each pixel instead (a box window)
attenuates the degree-scale modes a ~10 degree beam sees by a per cent. Both give errors
of 0.2-1 K at nside 64 against a converged quadrature
(:func:`autocal.tsky.quadrature.tsky_quadrature`; ``benchmarks/tsky_accuracy.py``).

:func:`band_limited_components` gives the grid a sky whose spherical harmonics are those
of the continuous sky up to ``lmax`` (default ``2 nside``) and zero above: the components
are sampled on a grid ``oversample`` times finer, transformed
(:func:`healpy.map2alm`) and synthesised at the engine's resolution
(:func:`healpy.alm2map`). Modes the grid resolves are kept unattenuated and nothing is
aliased; the beam (smooth, evaluated at the pixel centres) needs nothing more. Constant
maps (the CMB) are kept as they are.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import replace
from typing import Any

import numpy as np

from autocal.core.lazy import healpy as hp
from autocal.core.stopping import checkpoint
from autocal.sky.models import SkyComponents, SkyModel

logger = logging.getLogger(__name__)

#: The components are sampled this many times finer (in nside) before the transform, at
#: least at nside :data:`MIN_FINE_NSIDE`.
OVERSAMPLE = 4
MIN_FINE_NSIDE = 256
#: Jacobi iterations of :func:`healpy.map2alm`: a constant map comes back within 5e-3
#: with none, 4e-5 with one, 2e-9 with three (healpy's default; lmax 128 from nside 256).
MAP2ALM_ITER = 3
#: Band-limited skies kept for reuse (a diagnosis asks for the same sky ~10 times).
MEMO_SIZE = 4
_MEMO: dict[tuple[int, int], tuple[SkyComponents, SkyComponents]] = {}
_MEMO_LOCK = threading.Lock()


def fine_nside(nside: int) -> int:
    """Resolution at which the components are sampled before the transform."""
    return max(OVERSAMPLE * nside, MIN_FINE_NSIDE)


def band_limit_maps(maps: np.ndarray, nside: int, lmax: int | None = None) -> np.ndarray:
    """Band-limit RING maps ``(Ncomp, Npix_fine)`` to ``lmax`` and synthesise them at ``nside``.

    Constant maps are returned as constants (their only mode is the monopole).

    Parameters
    ----------
    maps
        Maps on a grid finer than (or equal to) ``nside``.
    nside
        Output resolution.
    lmax
        Band limit (default ``2 nside``).

    Returns
    -------
    numpy.ndarray
        ``(Ncomp, 12 nside^2)`` maps.
    """
    maps = np.atleast_2d(np.asarray(maps, dtype=np.float64))
    lmax = 2 * nside if lmax is None else int(lmax)
    out = np.empty((maps.shape[0], hp.nside2npix(nside)))
    for i, m in enumerate(maps):
        checkpoint("band-limiting a sky map")
        if np.ptp(m) <= 1e-12 * np.abs(m).max():  # constant up to rounding
            out[i] = m[0]
            continue
        alm = hp.map2alm(m, lmax=lmax, iter=MAP2ALM_ITER)
        out[i] = hp.alm2map(alm, nside, lmax=lmax)
    return out


def band_limited_components(
    sky: SkyModel, freqs: np.ndarray, nside: int, epoch: Any = None
) -> SkyComponents:
    """Return ``sky``'s components at ``nside``, band-limited to ``lmax = 2 nside``.

    Parameters
    ----------
    sky
        Sky model.
    freqs
        Frequencies in Hz.
    nside
        Resolution of the Tsky computation.
    epoch
        Epoch of the equatorial frame (as for :meth:`SkyModel.components`).

    Returns
    -------
    SkyComponents
        The components (read-only arrays; the last :data:`MEMO_SIZE` are memoised).
    """
    fine = sky.components(freqs, nside=fine_nside(nside), epoch=epoch)
    # the fine components are memoised by the sky model (equal models, channels, nside
    # and epoch give the same object); the memo keeps them alive, so their id is unique
    key = (id(fine), nside)
    with _MEMO_LOCK:
        hit = _MEMO.get(key)
    if hit is not None and hit[0] is fine:
        return hit[1]
    t0 = time.perf_counter()
    maps = band_limit_maps(fine.maps, nside)
    maps.flags.writeable = False
    comps = replace(fine, maps=maps, nside=nside)
    logger.debug(
        "sky %s band-limited to lmax %d at nside %d (from nside %d) in %.2f s",
        sky.name,
        2 * nside,
        nside,
        fine.nside,
        time.perf_counter() - t0,
    )
    with _MEMO_LOCK:
        _MEMO[key] = (fine, comps)
        while len(_MEMO) > MEMO_SIZE:
            _MEMO.pop(next(iter(_MEMO)))
    return comps
