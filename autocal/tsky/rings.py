"""HEALPix iso-latitude rings and the sky side of the ring-FFT engine.

On HEALPix RING ordering every iso-latitude ring is a contiguous run of pixels equally
spaced in right ascension, so turning the sky about the celestial pole by an LST is a
circular shift along each ring: a phase factor on the ring's Fourier transform. The
ring-FFT engine (:mod:`autocal.tsky.ringfft`) transforms the sky components along the
rings once (:func:`ring_plan`) and the beam per frequency chunk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from autocal.core.lazy import healpy as hp


@dataclass(frozen=True)
class RingGroup:
    """Rings of one length: ``pix`` is ``(Nring, n)`` RING indices."""

    pix: np.ndarray

    @property
    def n(self) -> int:
        """Number of pixels of each ring."""
        return self.pix.shape[1]


def ring_groups(nside: int) -> list[RingGroup]:
    """Group the HEALPix rings of ``nside`` by length (north and south caps paired)."""
    nring = 4 * nside - 1
    start, npix_ring, _, _, _ = hp.ringinfo(nside, np.arange(1, nring + 1))
    groups = []
    for i in range(1, nside):
        north, south = i - 1, nring - i
        rows = [np.arange(start[r], start[r] + npix_ring[r]) for r in (north, south)]
        groups.append(RingGroup(np.array(rows)))
    eq = np.arange(nside - 1, 3 * nside)  # 2 nside + 1 equatorial rings of 4 nside pixels
    groups.append(RingGroup(np.array([np.arange(start[r], start[r] + npix_ring[r]) for r in eq])))
    return groups


def _ring_weights(n: int) -> np.ndarray:
    """Weights turning one-sided rfft products into the two-sided sum (even ``n``)."""
    w = np.full(n // 2 + 1, 2.0)
    w[0] = 1.0
    if n % 2 == 0:
        w[-1] = 1.0
    return w


#: Precision of the ring FFTs and of the per-m overlaps (``m >= 1``); the ``m = 0`` term,
#: the beam integrals and all accumulations are float64.
FFT_DTYPE = np.float32


@dataclass(frozen=True)
class RingPlan:
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


def ring_plan(maps: np.ndarray, w_above: np.ndarray, nside: int) -> RingPlan:
    """Prepare the ring transforms of the sky components ``maps`` (``(Ncomp, Npix)``)."""
    nring = 4 * nside - 1
    start, length, _, _, _ = hp.ringinfo(nside, np.arange(1, nring + 1))
    start, length = start.astype(np.int64), length.astype(np.int64)
    ncomp, mmax = maps.shape[0], 2 * nside
    ctype = np.result_type(FFT_DTYPE, np.complex64)
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
        return RingPlan(0, 0, 0, 0, 4 * nside, (), moving, empty, empty, mean_ring)
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
    return RingPlan(lo, hi, eq_start, eq_rings, n_eq, cap_rings, moving, y_eq, y_cap, mean_ring)
