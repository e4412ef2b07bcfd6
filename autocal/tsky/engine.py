"""Beam-weighted sky temperature Tsky(nu, LST) of a drift-scan antenna.

    Tsky(nu, t) = [ sum_above A Tmap + Tgnd sum_below A ] / sum_all A

The beam ``A`` is fixed in topocentric coordinates; ``Tmap`` includes the CMB exactly
once (see :mod:`autocal.sky.models`); the ground below the horizon radiates ``Tgnd`` (300 K by
default, scalar or per frequency).

Two implementations:

* :func:`tsky_fft` (the engine). For a drift scan the sky seen at LST ``L`` is the sky
  rotated about the celestial pole by ``L``. On HEALPix iso-latitude rings both the
  above-horizon beam (in equatorial coordinates at LST 0) and each sky component are
  Fourier-transformed along the ring once; the overlap at every LST is then
  ``Re sum_m D_m exp(-i m L)`` with ``D_m = sum_rings w_m B_m conj(T_m) / n_ring``: a
  ring-wise circular cross-correlation, exact up to pixelisation (band-limited
  interpolation in LST). The cost is independent of the number of LSTs; sky components
  are transformed once whatever the number of frequencies. Frequency chunks run in
  parallel threads; the beam integrals and the ``m = 0`` term are float64, the ring
  FFTs of the beam and the ``m >= 1`` terms float32 (relative error ~1e-7, i.e. < 1 mK).
* :func:`tsky_brute` (the reference). For each LST the beam is evaluated afresh at every
  pixel's (az, alt) and the sums above are taken directly.
* :class:`BruteForceTsky` (the benchmark baseline): beam precomputed once, sky rotated
  per LST, one matrix product per LST.

:func:`compute_tsky` is the public entry point: it resolves names, checks the grids,
chooses the method, and reads/writes the on-disk cache (:mod:`autocal.tsky.cache`) of
the engine's LST-free output (:class:`TskyHarmonics`: Tsky's Fourier series in LST), from
which a table for any LSTs is one inverse FFT.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from typing import Any

import healpy as hp
import numpy as np
import scipy.fft as sp_fft
from tqdm.auto import tqdm

from autocal.core.coords import hadec_to_altaz, healpix_ra_dec, parse_epoch
from autocal.core.sites import Site, get_site
from autocal.errors import AutocalError
from autocal.sky.beams import Beam, BeamEvaluator, get_beam
from autocal.sky.models import SkyComponents, SkyModel, get_sky

logger = logging.getLogger(__name__)

#: Default ground temperature in kelvin.
T_GROUND = 300.0
#: Bump when the numerical method changes, so cached tables are recomputed.
ENGINE_VERSION = "ringfft-2"


class TskyError(AutocalError):
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

    def __repr__(self) -> str:
        """Return one line: sky, beam, site, grid and Tsky's range (never the arrays)."""
        from autocal.core.reprs import median, span

        sky = (self.meta.get("sky") or {}).get("model", "?")
        beam_meta = self.meta.get("beam") or {}
        beam = f"{beam_meta.get('beam', '?')} {beam_meta.get('pol', '')}".rstrip()
        site = (self.meta.get("site") or {}).get("name", "?")
        tsky = np.asarray(self.tsky)
        finite = tsky[np.isfinite(tsky)]
        trange = f"{finite.min():.4g}-{finite.max():.4g} K" if finite.size else "-"
        comps = "" if self.components is None else f", {self.components.shape[-1]} components"
        return (
            f"TskyResult(sky {sky}, beam {beam}, site {site}: {self.lsts.size} LSTs "
            f"{span(self.lsts, 1, 'h')} x {self.freqs.size} channels "
            f"{span(self.freqs, 1e6, 'MHz')}; Tsky {trange}, median {median(tsky):.4g} K, "
            f"median f_below {median(self.f_below):.3g}{comps})"
        )


@dataclass(frozen=True)
class TskyHarmonics:
    """Tsky at every LST at once: its Fourier series in LST (the engine's LST-free output).

    For a drift scan the beam-weighted sky is periodic in LST, band-limited at
    ``m <= 2 nside``:

        Tsky(nu, L) = [Re sum_m coef[m, nu] exp(-i m L) + Tgnd(nu) sum_below(nu)] / sum_all(nu)

    (``L`` in radians). Nothing here depends on the LST grid or the ground temperature,
    so :func:`compute_tsky` caches it and turns it into a table for any LSTs
    (:meth:`table`) in milliseconds.

    Attributes
    ----------
    freqs
        ``(Nfreq,)`` Hz.
    coef
        ``(M, Nfreq)`` complex harmonics ``m = 0 .. M - 1`` of the above-horizon
        beam-sky overlap (kelvin times beam integral).
    sum_all, sum_below
        ``(Nfreq,)`` the beam integral over the sphere and below the horizon.
    meta
        Description of the sky, beam, site, resolution, epoch and method.
    """

    freqs: np.ndarray
    coef: np.ndarray
    sum_all: np.ndarray
    sum_below: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        """Return one line: the harmonics' shape and band (never the arrays)."""
        from autocal.core.reprs import span

        return (
            f"TskyHarmonics({self.coef.shape[0]} harmonics x {self.freqs.size} channels "
            f"{span(self.freqs, 1e6, 'MHz')})"
        )

    def __post_init__(self) -> None:
        nf = self.freqs.shape
        if self.coef.ndim != 2 or self.coef.shape[1:] != nf:
            raise TskyError(f"harmonics of shape {self.coef.shape} do not match {nf[0]} freqs")
        if self.sum_all.shape != nf or self.sum_below.shape != nf:
            raise TskyError("beam integrals must have one value per frequency")

    def table(
        self,
        lsts: np.ndarray | list[float],
        tgnd: float | np.ndarray = T_GROUND,
        meta: dict[str, Any] | None = None,
    ) -> TskyResult:
        """Return Tsky at ``lsts`` (hours) for ground temperature ``tgnd`` (K).

        Parameters
        ----------
        lsts
            LSTs in hours.
        tgnd
            Ground temperature in kelvin (scalar or per frequency).
        meta
            Description stored with the table (default: this object's).

        Returns
        -------
        TskyResult
            The table.
        """
        lsts = check_grid(lsts, "LST")
        tg = _tgnd_array(tgnd, self.freqs.size)
        tsky = _synthesise(self.coef, _lst_radians(lsts))  # (Nlst, Nf): the numerator
        tsky += tg * self.sum_below
        tsky /= self.sum_all
        f_below = self.sum_below / self.sum_all
        return TskyResult(
            tsky=tsky,
            freqs=self.freqs,
            lsts=lsts,
            f_above=1 - f_below,
            f_below=f_below,
            meta=dict(self.meta if meta is None else meta),
        )


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


#: Precision of the ring FFTs and of the per-m overlaps (``m >= 1``); the ``m = 0`` term,
#: the beam integrals and all accumulations are float64.
_FFT_DTYPE = np.float32
#: Target size of one frequency chunk of the beam (float64 ``Npix x Nf``) in bytes: large
#: enough for efficient batched FFTs and matrix products, small enough to stay in cache.
_CHUNK_BYTES = 16 << 20


@dataclass(frozen=True)
class _RingPlan:
    """Which HEALPix rings the engine transforms, and the sky side of the overlap.

    Rings are RING-ordered and contiguous in pixel index. Only rings where the horizon
    weight is somewhere positive are transformed (``[lo, hi)`` covers them); the
    ``2 nside + 1`` equatorial rings (``4 nside`` pixels each) form one contiguous block
    transformed in a single batched FFT, the polar-cap rings one by one.

    Attributes
    ----------
    lo, hi
        Pixel range covering every transformed ring.
    eq_start, eq_rings, eq_len
        First pixel, number of rings and ring length of the equatorial block (``eq_rings``
        is 0 when no equatorial ring is transformed).
    caps
        ``(first pixel, length)`` of each transformed polar-cap ring.
    moving
        The components that are not constant maps (only those have ``m >= 1`` terms),
        as a slice when they are consecutive.
    y_eq
        ``(M, Nmoving, eq_rings)`` complex: ``conj(S_m) w_m / n`` of those components on
        the equatorial rings, zero at ``m = 0`` (computed exactly in float64 instead).
    y_cap
        ``(M, Nmoving, Ncap)`` the same for the cap rings (zero beyond each ring's ``n/2``).
    mean_ring
        ``(Ncomp, Npix)``: each component's ring average at every pixel (the ``m = 0``
        term of the ring correlation).
    """

    lo: int
    hi: int
    eq_start: int
    eq_rings: int
    eq_len: int
    caps: tuple[tuple[int, int], ...]
    moving: slice | np.ndarray
    y_eq: np.ndarray
    y_cap: np.ndarray
    mean_ring: np.ndarray


def _ring_plan(maps: np.ndarray, w_above: np.ndarray, nside: int) -> _RingPlan:
    """Prepare the ring transforms of the sky components ``maps`` (``(Ncomp, Npix)``)."""
    nring = 4 * nside - 1
    start, length, _, _, _ = hp.ringinfo(nside, np.arange(1, nring + 1))
    start, length = start.astype(np.int64), length.astype(np.int64)
    ncomp, mmax = maps.shape[0], 2 * nside
    ctype = np.result_type(_FFT_DTYPE, np.complex64)
    ring_of_pixel = np.repeat(np.arange(nring), length)
    ring_mean = np.add.reduceat(maps, start, axis=1) / length  # (Ncomp, Nring)
    mean_ring = ring_mean[:, ring_of_pixel]
    needed = np.maximum.reduceat(w_above, start) > 0
    moving_idx = np.flatnonzero(np.ptp(maps, axis=1) > 0)
    moving: slice | np.ndarray = moving_idx
    if moving_idx.size and np.all(np.diff(moving_idx) == 1):
        moving = slice(int(moving_idx[0]), int(moving_idx[-1]) + 1)
    if not np.any(needed) or moving_idx.size == 0:  # nothing turns into view
        empty = np.zeros((mmax + 1, moving_idx.size, 0), dtype=ctype)
        return _RingPlan(0, 0, 0, 0, 4 * nside, (), moving, empty, empty, mean_ring)
    maps = maps[moving_idx]
    ncomp = maps.shape[0]
    rings = np.flatnonzero(needed)
    lo, hi = int(start[rings[0]]), int(start[rings[-1]] + length[rings[-1]])
    eq = np.arange(nside - 1, 3 * nside)
    eq_used = needed[eq].any()
    eq_rings = eq.size if eq_used else 0
    eq_start = int(start[eq[0]])
    n_eq = 4 * nside
    y_eq = np.zeros((mmax + 1, ncomp, eq_rings), dtype=ctype)
    if eq_used:
        block = maps[:, eq_start : eq_start + eq.size * n_eq].reshape(ncomp, eq.size, n_eq)
        s_hat = np.conj(np.fft.rfft(block, axis=-1)) * (_ring_weights(n_eq) / n_eq)
        y_eq[:] = s_hat.transpose(2, 0, 1)
        y_eq[0] = 0
        lo, hi = min(lo, eq_start), max(hi, eq_start + eq.size * n_eq)
    caps = [int(r) for r in rings if not (nside - 1 <= r < 3 * nside)]
    y_cap = np.zeros((mmax + 1, ncomp, len(caps)), dtype=ctype)
    for j, r in enumerate(caps):
        n = int(length[r])
        ring = maps[:, start[r] : start[r] + n]
        s_hat = np.conj(np.fft.rfft(ring, axis=-1)) * (_ring_weights(n) / n)
        y_cap[: n // 2 + 1, :, j] = s_hat.T
    y_cap[0] = 0
    cap_rings = tuple((int(start[r]), int(length[r])) for r in caps)
    return _RingPlan(lo, hi, eq_start, eq_rings, n_eq, cap_rings, moving, y_eq, y_cap, mean_ring)


class _Clock:
    """CPU time of the calling thread per stage (reported at DEBUG level).

    Thread CPU time rather than wall time: stage costs stay meaningful on a busy machine.
    """

    def __init__(self) -> None:
        self.times: dict[str, float] = {}
        self._last = time.thread_time()

    def lap(self, stage: str | None = None) -> None:
        """Charge the time since the previous lap to ``stage`` (``None``: discard)."""
        now = time.thread_time()
        if stage is not None:
            self.times[stage] = self.times.get(stage, 0.0) + now - self._last
        self._last = now

    def merge(self, times: dict[str, float]) -> None:
        """Add another clock's stage times (e.g. a worker thread's)."""
        for key, value in times.items():
            self.times[key] = self.times.get(key, 0.0) + value

    def report(self) -> str:
        """``stage=seconds`` pairs and their total."""
        parts = [f"{k}={v:.3f}s" for k, v in self.times.items()]
        return " ".join([*parts, f"sum={sum(self.times.values()):.3f}s"])


def _default_chunk(npix: int) -> int:
    """Frequencies per chunk: a power of two in [4, 64], the float32 beam within ~12 MB."""
    nf = 4
    while nf < 64 and 2 * nf * npix * 4 <= 12 << 20:
        nf *= 2
    return nf


def _default_workers() -> int:
    """Return the number of CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


@dataclass
class _FftJob:
    """Everything one frequency chunk of :func:`tsky_fft` needs (shared by the workers).

    ``weights`` rows: 1 (beam integral), ``1 - w`` (below-horizon part) and ``w`` times
    each component's ring average (the exact ``m = 0`` overlaps); ``sums`` and
    ``overlap`` receive the results, each chunk writing its own frequency columns.
    """

    plan: _RingPlan
    evaluator: BeamEvaluator
    beam_name: str
    freqs: np.ndarray
    chunk: int
    weights: np.ndarray
    w_above: np.ndarray
    sums: np.ndarray
    overlap: np.ndarray
    local: threading.local = field(default_factory=threading.local)

    def buffers(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the calling thread's work arrays (allocated once; ``cap_buf`` kept zero)."""
        if not hasattr(self.local, "b_sky"):
            plan, nf = self.plan, min(self.chunk, self.freqs.size)
            self.local.b_sky = np.empty((plan.hi - plan.lo, nf), dtype=_FFT_DTYPE)
            shape = (plan.y_cap.shape[0], len(plan.caps), nf)
            self.local.cap_buf = np.zeros(shape, dtype=plan.y_cap.dtype)
        return self.local.b_sky, self.local.cap_buf

    def run(self, start: int) -> dict[str, float]:
        """Process the frequencies ``start : start + chunk``; return the stage times."""
        clock = _Clock()
        sel = slice(start, min(start + self.chunk, self.freqs.size))
        freqs = self.freqs[sel]
        nf = freqs.size
        plan = self.plan
        b_sky, cap_buf = self.buffers()
        b_sky, cap_buf = b_sky[:, :nf], cap_buf[:, :, :nf]
        npix = self.w_above.size
        acc = np.zeros((self.weights.shape[0], nf))
        # Blocks of directions small enough to stay in cache, and for the products
        # below to run single-threaded in BLAS (parallelism comes from the chunks).
        step = max(256, 32768 // nf)
        for b0 in range(0, npix, step):
            b1 = min(b0 + step, npix)
            vals = self.evaluator.by_direction(freqs, slice(b0, b1))  # (rows, Nf) float64
            clock.lap("beam")
            if not (self.evaluator.nonnegative or vals.min() >= 0):  # also catches NaN
                raise TskyError(f"beam {self.beam_name} gave negative or non-finite values")
            acc += self.weights[:, b0:b1] @ vals
            o0, o1 = max(b0, plan.lo), min(b1, plan.hi)
            if o0 < o1:
                np.multiply(
                    vals[o0 - b0 : o1 - b0],
                    self.w_above[o0:o1, None],
                    out=b_sky[o0 - plan.lo : o1 - plan.lo],
                    casting="same_kind",
                )
            clock.lap("sums+horizon")
        self.sums[:, sel] = acc
        if plan.hi > plan.lo:
            _overlap_chunk(plan, b_sky, self.overlap[:, :, sel], cap_buf, clock)
        return clock.times


def _overlap_chunk(
    plan: _RingPlan, b_sky: np.ndarray, out: np.ndarray, cap_buf: np.ndarray, clock: _Clock
) -> None:
    """Set the ``m >= 1`` ring overlaps of one frequency chunk in ``out`` (``(M, Ncomp, Nf)``).

    ``b_sky`` is the ``(hi - lo, Nf)`` horizon-weighted beam over the transformed rings,
    ``cap_buf`` a zeroed ``(M, Ncap, Nf)`` complex work array (only the entries
    ``m <= n/2`` of each cap ring are ever written, so it stays zero elsewhere).
    """
    nf = b_sky.shape[1]
    total = np.zeros((out.shape[0], plan.y_eq.shape[1], nf), dtype=np.complex128)
    if plan.eq_rings:
        first = plan.eq_start - plan.lo
        block = b_sky[first : first + plan.eq_rings * plan.eq_len]
        x_eq = sp_fft.rfft(block.reshape(plan.eq_rings, plan.eq_len, nf), axis=1)
        clock.lap("fft")
        total += np.matmul(plan.y_eq, x_eq.transpose(1, 0, 2))
        clock.lap("ring_sum")
    if plan.caps:
        for j, (first, n) in enumerate(plan.caps):
            ring = b_sky[first - plan.lo : first - plan.lo + n]
            cap_buf[: n // 2 + 1, j] = sp_fft.rfft(ring, axis=0)
        clock.lap("fft")
        total += np.matmul(plan.y_cap, cap_buf)
        clock.lap("ring_sum")
    out[:, plan.moving] = total  # constant maps have no m >= 1 terms (out stays zero)


def _regular_grid(lst_rad: np.ndarray, mmax: int) -> tuple[int, np.ndarray] | None:
    """``(N, k)`` if every LST is ``lst[0] + k 2 pi / N`` (phase error < 1e-9 rad), else None."""
    if lst_rad.size < 2:
        return None
    diffs = np.diff(np.unique(lst_rad))
    if diffs.size == 0:
        return None
    n = round(float(2 * np.pi / diffs.min()))
    if n < 2 or n > (1 << 22):
        return None
    step = 2 * np.pi / n
    k = (lst_rad - lst_rad[0]) / step
    kr = np.round(k)
    if np.max(np.abs(k - kr)) * step * max(mmax, 1) > 1e-9:
        return None
    return n, np.mod(kr.astype(np.int64), n)


def _synthesise(coef: np.ndarray, lst_rad: np.ndarray) -> np.ndarray:
    """``Re sum_m coef[m] exp(-i m L)`` for every LST: ``(M, K)`` -> ``(Nlst, K)``.

    LSTs on a regular grid of ``N`` points per day use one inverse real FFT of length
    ``N`` (or, with fewer than ``2 M`` points per day, a complex FFT of the harmonics
    folded modulo ``N``); other LSTs a matrix product with ``cos``/``sin``.
    """
    nm = coef.shape[0]
    grid = _regular_grid(lst_rad, nm - 1)
    if grid is not None and grid[0] * max(np.log2(grid[0]), 1.0) <= 4 * lst_rad.size * nm:
        n, k = grid
        shifted = coef * np.exp(-1j * np.arange(nm) * lst_rad[0])[:, None]
        if 2 * (nm - 1) < n:
            # irfft(X)_k = [X_0 + 2 Re sum_m X_m e^{2 pi i m k / N}] / N with X_m = conj
            half = np.zeros((n // 2 + 1, coef.shape[1]), dtype=np.complex128)
            half[0] = n * shifted[0].real
            half[1:nm] = (n / 2) * np.conj(shifted[1:])
            full = sp_fft.irfft(half, n=n, axis=0, workers=-1)
        else:  # fewer LSTs per day than harmonics: alias m onto m mod N
            folded = np.zeros((n, coef.shape[1]), dtype=np.complex128)
            np.add.at(folded, np.arange(nm) % n, shifted)
            full = sp_fft.fft(folded, axis=0, workers=-1).real
        if k.size == n and np.array_equal(k, np.arange(n)):
            return full
        return full[k]
    phase = np.outer(lst_rad, np.arange(nm))
    return np.cos(phase) @ coef.real + np.sin(phase) @ coef.imag


def _fft_overlaps(
    sky: SkyComponents,
    beam: Beam,
    site: Site,
    horizon_width_deg: float,
    freq_chunk: int | None,
    progress: bool | None,
    workers: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the ring-FFT engine: ``(freqs, sums, overlap)``, nothing depending on the LSTs.

    ``sums`` is ``(2 + Ncomp, Nfreq)``: the beam integral, its below-horizon part and
    each component's ``m = 0`` overlap; ``overlap`` is ``(M, Ncomp, Nfreq)`` complex, the
    harmonics of every component's above-horizon overlap (its ``m = 0`` row set from
    ``sums``). See :func:`tsky_fft` for the method and the parameters.
    """
    freqs = beam.check_freqs(sky.freqs)
    nside = sky.nside
    npix = hp.nside2npix(nside)
    wall0 = time.perf_counter()
    clock = _Clock()
    az, za = topocentric_at_lst0(nside, site)
    w_above = horizon_weight(np.pi / 2 - za, horizon_width_deg)
    evaluator = beam.on(az, za)
    clock.lap("beam_bind")
    plan = _ring_plan(sky.maps, w_above, nside)
    ncomp, nfreq, mmax = sky.ncomp, freqs.size, 2 * nside
    chunk = int(freq_chunk) if freq_chunk is not None else _default_chunk(npix)
    if chunk < 1:
        raise TskyError("freq_chunk must be >= 1")
    job = _FftJob(
        plan=plan,
        evaluator=evaluator,
        beam_name=beam.name,
        freqs=freqs,
        chunk=chunk,
        weights=np.vstack([np.ones(npix), 1.0 - w_above, w_above * plan.mean_ring]),
        w_above=w_above,
        sums=np.empty((2 + ncomp, nfreq)),
        overlap=np.zeros((mmax + 1, ncomp, nfreq), dtype=np.complex128),
    )
    starts = list(range(0, nfreq, chunk))
    nworkers = max(1, min(int(workers) if workers is not None else _default_workers(), len(starts)))
    clock.lap("setup")
    bar = tqdm(total=len(starts), desc="Tsky (ring FFT)", unit="chunk", disable=_no_bar(progress))
    with bar:
        if nworkers == 1:
            for start in starts:
                clock.merge(job.run(start))
                bar.update()
        else:
            with ThreadPoolExecutor(max_workers=nworkers) as pool:
                futures = [pool.submit(job.run, start) for start in starts]
                try:
                    for future in as_completed(futures):
                        clock.merge(future.result())
                        bar.update()
                except BaseException:
                    for future in futures:
                        future.cancel()
                    raise
    clock.lap()
    sums, overlap = job.sums, job.overlap
    if not np.all(np.isfinite(sums)):
        raise TskyError(f"beam {beam.name} gave negative or non-finite values")
    if np.any(sums[0] <= 0):
        bad = freqs[sums[0] <= 0] / 1e6
        raise TskyError(f"beam {beam.name} integrates to zero at {bad[:5]} MHz")
    overlap[0] = sums[2:]
    logger.debug(
        "ring-FFT engine: %d freqs at nside %d in %.3f s wall; thread CPU per stage: %s",
        nfreq,
        nside,
        time.perf_counter() - wall0,
        clock.report(),
    )
    return freqs, sums, overlap


def tsky_harmonics(
    sky: SkyComponents,
    beam: Beam,
    site: Site,
    horizon_width_deg: float = HORIZON_WIDTH_DEG,
    freq_chunk: int | None = None,
    progress: bool | None = None,
    workers: int | None = None,
) -> TskyHarmonics:
    """Tsky's Fourier series in LST by the ring-FFT engine (see :func:`tsky_fft`).

    Parameters are as for :func:`tsky_fft`; the LSTs and the ground temperature come
    later, in :meth:`TskyHarmonics.table`.

    Returns
    -------
    TskyHarmonics
        Harmonics and beam integrals (``meta`` empty: :func:`compute_tsky` fills it).
    """
    freqs, sums, overlap = _fft_overlaps(
        sky, beam, site, horizon_width_deg, freq_chunk, progress, workers
    )
    return _harmonics(sky.spectra, freqs, sums, overlap)


def _harmonics(
    spectra: np.ndarray, freqs: np.ndarray, sums: np.ndarray, overlap: np.ndarray
) -> TskyHarmonics:
    """Combine the engine's per-component output with the component ``spectra``."""
    return TskyHarmonics(
        freqs=freqs,
        coef=np.einsum("fc,mcf->mf", spectra, overlap),
        sum_all=sums[0],
        sum_below=sums[1],
    )


def tsky_fft(
    sky: SkyComponents,
    beam: Beam,
    site: Site,
    lsts: np.ndarray,
    tgnd: float | np.ndarray = T_GROUND,
    horizon_width_deg: float = HORIZON_WIDTH_DEG,
    freq_chunk: int | None = None,
    keep_components: bool = False,
    progress: bool | None = None,
    workers: int | None = None,
) -> TskyResult:
    """Tsky at all LSTs by ring-wise FFT cross-correlation (see module docstring).

    Implementation: the beam is evaluated once per frequency chunk at the LST-0
    position of every pixel (direction-major, :meth:`BeamEvaluator.by_direction`); one
    float64 matrix product gives its integral, its below-horizon part and the exact
    ``m = 0`` overlap with every sky component (ring averages); the horizon-weighted beam
    is cast to float32 and Fourier-transformed along the rings that ever rise (one
    batched FFT for the equatorial block, one per polar-cap ring); the ``m >= 1``
    overlaps are summed over rings by batched complex matrix products with the
    precomputed sky transforms and accumulated in float64. Finally one inverse transform
    over ``m`` (an FFT for a regular LST grid, else a matrix product) gives every LST.

    Parameters
    ----------
    sky
        Low-rank equatorial sky (:meth:`autocal.sky.models.SkyModel.components`).
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
        Frequencies processed together (bounds memory to a few ``freq_chunk * Npix``
        floats); ``None`` chooses it from the map size (cache-sized chunks).
    keep_components
        Also return the per-component contributions (``TskyResult.components``).
    progress
        Show a progress bar (``None``: only on a terminal).
    workers
        Threads processing frequency chunks in parallel (``None``: one per available
        CPU). The beam evaluator is called from these threads.

    Returns
    -------
    TskyResult
        The table.
    """
    lsts = check_grid(lsts, "LST")
    tg = _tgnd_array(tgnd, sky.freqs.size)
    freqs, sums, overlap = _fft_overlaps(
        sky, beam, site, horizon_width_deg, freq_chunk, progress, workers
    )
    result = _harmonics(sky.spectra, freqs, sums, overlap).table(lsts, tg)
    if not keep_components:
        return result
    ncomp, nfreq, nm = sky.ncomp, freqs.size, overlap.shape[0]
    per_comp = _synthesise(overlap.reshape(nm, ncomp * nfreq), _lst_radians(lsts))
    comps = per_comp.reshape(lsts.size, ncomp, nfreq).transpose(0, 2, 1) / sums[0][:, None]
    return TskyResult(
        tsky=result.tsky,
        freqs=freqs,
        lsts=lsts,
        f_above=result.f_above,
        f_below=result.f_below,
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
    implies, so :func:`tsky_fft` and this class agree to rounding: the comparison checks
    the engine's implementation, :func:`tsky_brute` its physics.

    Parameters
    ----------
    sky, beam, site, tgnd, horizon_width_deg
        As for :func:`tsky_fft`.
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
        self.tgnd = _tgnd_array(tgnd, self.freqs.size)
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
            The table (``f_above``/``f_below`` as for :func:`tsky_fft`).
        """
        lsts = check_grid(lsts, "LST")
        lst_rad = _lst_radians(lsts)
        out = np.empty((lsts.size, self.freqs.size))
        batch = max(1, int(lsts_per_product))
        ncomp = self._ncomp
        starts = range(0, lsts.size, batch)
        for i0 in tqdm(starts, desc="Tsky (vectorised brute force)", disable=_no_bar(progress)):
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
        Sky model or its name (:func:`autocal.sky.models.get_sky`).
    beam
        Beam or its name/path (:func:`autocal.sky.beams.get_beam`).
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
        Width of the soft horizon in degrees (:func:`horizon_weight`).
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
    from autocal.tsky import cache as tsky_cache

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
    if method == "fft" and not keep_components:
        # the LST-free harmonics are what is cached: any LST grid (every observation of
        # a night) and any ground temperature then reuse them
        lst_free = {k: v for k, v in meta.items() if k != "tgnd_K"}
        key = tsky_cache.cache_key(lst_free, freqs)
        harmonics = tsky_cache.load(key) if cache else None
        lock = tsky_cache.computing(key) if cache and harmonics is None else nullcontext()
        with lock:
            if cache and harmonics is None:  # another process may have stored it meanwhile
                harmonics = tsky_cache.load(key)
            if harmonics is None:
                t0 = time.perf_counter()
                comps = sky_model.components(freqs, nside=nside, epoch=time_epoch)
                computed = tsky_harmonics(
                    comps, beam_obj, site_obj, horizon_width_deg, progress=progress
                )
                info = {
                    "component_labels": list(comps.labels),
                    "compute_seconds": round(time.perf_counter() - t0, 3),
                }
                harmonics = replace(computed, meta={**lst_free, **info})
                logger.info(
                    "Tsky harmonics for %d freqs at nside %d in %.2f s",
                    freqs.size,
                    nside,
                    info["compute_seconds"],
                )
                if cache:
                    tsky_cache.store(key, harmonics)
            else:
                logger.info("Tsky cache hit %s", key)
        extra = {
            k: harmonics.meta[k]
            for k in ("component_labels", "compute_seconds")
            if k in harmonics.meta
        }
        return harmonics.table(lsts, tg, meta={**meta, **extra})
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
    logger.info(
        "Tsky %s: %d LSTs x %d freqs at nside %d in %.2f s",
        method,
        lsts.size,
        freqs.size,
        nside,
        elapsed,
    )
    return replace(result, meta=meta, spectra=comps.spectra if keep_components else None)
