"""Tsky(nu, LST) for a sky, a beam and a site: :func:`compute_tsky`, the public entry point.

:func:`compute_tsky` resolves names (sky models, beams, sites), checks the grids, chooses
the method (the ring-FFT engine, :mod:`autocal.tsky.ringfft`, or the brute-force
reference, :mod:`autocal.tsky.brute`), gives both the sky band-limited to what the
HEALPix grid resolves (:mod:`autocal.tsky.bandlimit`) and reads/writes the on-disk cache
(:mod:`autocal.tsky.cache`) of the engine's LST-free output
(:class:`~autocal.tsky.result.TskyHarmonics`: Tsky's Fourier series in LST), from which a
table for any LSTs is one inverse FFT.
"""

from __future__ import annotations

import logging
import time
from contextlib import nullcontext
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from astropy.time import Time

from autocal.core.coords import parse_epoch
from autocal.core.sites import Site, get_site
from autocal.sky.beam_base import Beam
from autocal.sky.beam_names import get_beam
from autocal.sky.models import SkyModel, get_sky
from autocal.tsky import cache as tsky_cache
from autocal.tsky.bandlimit import band_limited_components
from autocal.tsky.brute import tsky_brute
from autocal.tsky.horizon import HORIZON_WIDTH_DEG
from autocal.tsky.result import (
    T_GROUND,
    TskyError,
    TskyHarmonics,
    TskyResult,
    check_grid,
    tgnd_array,
)
from autocal.tsky.ringfft import ENGINE_VERSION, tsky_fft, tsky_harmonics

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Request:
    """The resolved and checked inputs of one :func:`compute_tsky` call (LSTs and ground aside)."""

    sky: SkyModel
    beam: Beam
    site: Site
    freqs: np.ndarray
    nside: int
    epoch: Time
    horizon_width_deg: float
    method: str
    progress: bool | None


def _nside_ok(nside: Any) -> bool:
    """Whether ``nside`` is a HEALPix nside of the nested scheme >= 2 (as healpy checks it).

    A power of two from 2 to 2**29, given as an integer or an integral float.
    """
    if isinstance(nside, bool):
        return False
    if isinstance(nside, (float, np.floating)):
        if not float(nside).is_integer():
            return False
        nside = int(nside)
    if not isinstance(nside, (int, np.integer)):
        return False
    n = int(nside)
    return 2 <= n <= 2**29 and not (n & (n - 1))


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
        Sky model or its name (:func:`autocal.sky.models.get_sky`).
    beam
        Beam or its name/path (:func:`autocal.sky.beam_names.get_beam`).
    site
        Site or its name (:func:`autocal.core.sites.get_site`).
    freqs
        Frequencies in Hz.
    lsts
        LSTs in hours.
    tgnd
        Ground temperature in kelvin (scalar or per frequency).
    nside
        HEALPix resolution of the computation.
    epoch
        Epoch of the equatorial frame (default J2000; for data, their night's:
        :func:`autocal.core.coords.night_epoch`).
    pol
        Polarisation for named beams.
    horizon_width_deg
        Width of the soft horizon in degrees (:func:`~autocal.tsky.horizon.horizon_weight`).
    method
        ``"fft"`` (fast engine) or ``"brute"`` (reference, never cached).
    cache
        Read and write the on-disk cache (:mod:`autocal.tsky.cache`). It holds the
        LST-free harmonics (:class:`TskyHarmonics`), so one entry serves every LST grid
        and ground temperature: every observation of a night, once the first has run.
    keep_components
        Also return per-component contributions (``fft`` only; never cached).
    progress
        Progress bar (``None``: only on a terminal).

    Returns
    -------
    TskyResult
        The table with its description in ``meta``.
    """
    sky_model = get_sky(sky)
    beam_obj = get_beam(beam, pol)
    site_obj = get_site(site)
    cached_harmonics = method == "fft" and not keep_components
    # the beam's range is checked before anything is computed, not for a cache hit (the
    # entry's key holds the beam file's checksum and these frequencies: it passed then)
    freqs = beam_obj.check_freqs(check_grid(freqs, "frequency"), in_range=not cached_harmonics)
    lsts = check_grid(lsts, "LST")
    tg = tgnd_array(tgnd, freqs.size)
    if method not in {"fft", "brute"}:
        raise TskyError(f"unknown method {method!r}: use 'fft' or 'brute'")
    if not _nside_ok(nside):
        raise TskyError(f"nside {nside} must be a power of two >= 2")
    req = _Request(
        sky_model,
        beam_obj,
        site_obj,
        freqs,
        nside,
        parse_epoch(epoch),
        horizon_width_deg,
        method,
        progress,
    )
    meta = _describe(req, tg)
    if cached_harmonics:
        # the LST-free harmonics are what is cached: any LST grid (every observation of
        # a night) and any ground temperature then reuse them
        lst_free = {k: v for k, v in meta.items() if k != "tgnd_K"}
        harmonics = _harmonics(req, lst_free, cache)
        extra = {
            k: harmonics.meta[k]
            for k in ("component_labels", "compute_seconds")
            if k in harmonics.meta
        }
        return harmonics.table(lsts, tg, meta={**meta, **extra})
    return _table(req, lsts, tg, meta, keep_components)


def _describe(req: _Request, tg: np.ndarray) -> dict[str, Any]:
    """Return the description of a Tsky table stored in its ``meta`` (and cache key)."""
    return {
        "sky": req.sky.describe(),
        "beam": req.beam.describe(),
        "site": req.site.describe(),
        "tgnd_K": float(tg[0]) if np.all(tg == tg[0]) else "per-frequency",
        "nside": int(req.nside),
        "horizon_width_deg": float(req.horizon_width_deg),
        "epoch_jd": float(req.epoch.jd),
        "method": req.method,
        "engine_version": ENGINE_VERSION,
        "cmb": "included once (2.725 K)",
        "sky_band_limit": f"lmax {2 * req.nside} (autocal.tsky.bandlimit)",
        "frame": "apparent equatorial of epoch (TETE); LST = apparent sidereal time",
        "azimuth_convention": "east of north",
    }


def _harmonics(req: _Request, lst_free: dict[str, Any], cache: bool) -> TskyHarmonics:
    """Return the harmonics described by ``lst_free`` from the cache, or compute them.

    With ``cache``, one process computes a missing entry and stores it while the others
    computing the same entry wait for it (:func:`autocal.tsky.cache.computing`).
    """
    key = tsky_cache.cache_key(lst_free, req.freqs)
    harmonics = tsky_cache.load(key) if cache else None
    lock = tsky_cache.computing(key) if cache and harmonics is None else nullcontext()
    with lock:
        if cache and harmonics is None:  # another process may have stored it meanwhile
            harmonics = tsky_cache.load(key)
        if harmonics is None:
            req.beam.check_freqs(req.freqs)
            harmonics = _compute_harmonics(req, lst_free)
            if cache:
                tsky_cache.store(key, harmonics)
        else:
            logger.info("Tsky cache hit %s", key)
    return harmonics


def _compute_harmonics(req: _Request, lst_free: dict[str, Any]) -> TskyHarmonics:
    """Compute the harmonics by the ring-FFT engine, described by ``lst_free``."""
    t0 = time.perf_counter()
    comps = band_limited_components(req.sky, req.freqs, req.nside, req.epoch)
    computed = tsky_harmonics(
        comps, req.beam, req.site, req.horizon_width_deg, progress=req.progress
    )
    info = {
        "component_labels": list(comps.labels),
        "compute_seconds": round(time.perf_counter() - t0, 3),
    }
    harmonics = replace(computed, meta={**lst_free, **info})
    logger.info(
        "Tsky harmonics for %d freqs at nside %d in %.2f s",
        req.freqs.size,
        req.nside,
        info["compute_seconds"],
    )
    return harmonics


def _table(
    req: _Request, lsts: np.ndarray, tg: np.ndarray, meta: dict[str, Any], keep_components: bool
) -> TskyResult:
    """Compute the table directly (never cached): brute force, or the engine with components."""
    t0 = time.perf_counter()
    comps = band_limited_components(req.sky, req.freqs, req.nside, req.epoch)
    if req.method == "fft":
        result = tsky_fft(
            comps,
            req.beam,
            req.site,
            lsts,
            tg,
            req.horizon_width_deg,
            keep_components=keep_components,
            progress=req.progress,
        )
    else:
        result = tsky_brute(
            comps, req.beam, req.site, lsts, tg, req.horizon_width_deg, progress=req.progress
        )
    elapsed = time.perf_counter() - t0
    meta["component_labels"] = list(comps.labels)
    meta["compute_seconds"] = round(elapsed, 3)
    logger.info(
        "Tsky %s: %d LSTs x %d freqs at nside %d in %.2f s",
        req.method,
        lsts.size,
        req.freqs.size,
        req.nside,
        elapsed,
    )
    return replace(result, meta=meta, spectra=comps.spectra if keep_components else None)
