"""The compiled frequency flagger: one pass over each spectrum, antenna-pols on threads.

:func:`spectrum_hits` does what :func:`autocal.pipeline.rfi.frequency_flags` describes
(ratio to the time-mean spectrum, block-median trend, one robust width per spectrum,
watershed) in one loop per spectrum, so a 350-antenna HERA file (2 x 10^8 samples) is
flagged in a few seconds instead of the ~14 s the same steps take as numpy array passes (and
the ~190 s of a sliding median filter); antenna-pols run on threads
(:func:`autocal.fit.threads.in_threads`). This module imports numba:
:mod:`autocal.pipeline.rfi` imports it only when it flags (the command line never loads it).
The machine code is cached on disk (numba's ``cache=True``: beside this module, or numba's
per-user cache directory when that is not writable).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from autocal.fit.threads import in_threads
from autocal.pipeline.rfi import trend_grid


@dataclass(frozen=True, eq=False)
class BlockScan:
    """What one block's flagging found, besides the hits (:func:`spectrum_hits`).

    Attributes
    ----------
    band
        ``(Nant, Npol, Ntime)`` the median of each spectrum's block medians (its level
        relative to the time-mean spectrum; NaN for a spectrum with fewer than three
        usable samples), which the flags in time are found from.
    usable, hit
        ``(Nant, Npol, Ntime)`` usable and flagged samples of each spectrum.
    """

    band: np.ndarray
    usable: np.ndarray
    hit: np.ndarray


@dataclass(frozen=True, eq=False)
class ScanSums:
    """Per-channel sums over integrations that a scan adds block after block.

    Attributes
    ----------
    hits, usable
        ``(Nant, Npol, Nfreq)`` flagged and usable samples of each channel.
    clean_total, clean_count
        ``(Nant, Npol, Nfreq)`` the sum and number of the usable samples left unflagged
        (their mean is the time-mean spectrum of clean data).
    """

    hits: np.ndarray
    usable: np.ndarray
    clean_total: np.ndarray
    clean_count: np.ndarray

    def add(self, other: ScanSums) -> None:
        """Add ``other``'s sums into these, in place."""
        for mine, theirs in (
            (self.hits, other.hits),
            (self.usable, other.usable),
            (self.clean_total, other.clean_total),
            (self.clean_count, other.clean_count),
        ):
            np.add(mine, theirs, out=mine)

    @classmethod
    def zeros(cls, shape: tuple[int, int, int]) -> ScanSums:
        """Return empty sums of ``(Nant, Npol, Nfreq)``."""
        return cls(
            np.zeros(shape, np.int64),
            np.zeros(shape, np.int64),
            np.zeros(shape),
            np.zeros(shape, np.int64),
        )


def spectrum_hits(
    data: np.ndarray,
    flags: np.ndarray,
    inverse_level: np.ndarray,
    block: int,
    nsig: float,
    nsig_adjacent: float,
    median_chi2: float,
    sums: ScanSums | None = None,
) -> tuple[np.ndarray, BlockScan]:
    """Return the RFI hits of every spectrum of a block and what else the scan needs.

    Parameters
    ----------
    data, flags
        ``(Nant, Npol, Ntime, Nfreq)`` autos and their flags.
    inverse_level
        ``(Nant, Npol, Nfreq)`` one over the time-mean spectrum (NaN where it is not
        positive and finite: those channels take no part).
    block
        Channels per median block of the trend.
    nsig, nsig_adjacent
        Significance that starts a flagged run, and that a run grows over.
    median_chi2
        ``median(z^2)`` of a unit normal (0.456): the width is
        ``sqrt(median(residual^2) / median_chi2)``.
    sums
        Per-channel sums to add this block to (in place), or ``None``.

    Returns
    -------
    hits : numpy.ndarray
        ``(Nant, Npol, Ntime, Nfreq)`` bool, True where a usable sample is flagged.
    scan : BlockScan
        Each spectrum's band level and its usable and flagged sample counts.
    """
    nant, npol, ntime, nfreq = data.shape
    block = max(1, min(int(block), nfreq))
    lo, weight = trend_grid(nfreq, block)
    out = np.zeros(data.shape, dtype=np.bool_)
    scan = BlockScan(
        np.full((nant, npol, ntime), np.nan),
        np.zeros((nant, npol, ntime), np.int64),
        np.zeros((nant, npol, ntime), np.int64),
    )
    acc = ScanSums.zeros((nant, npol, nfreq)) if sums is None else sums
    args = (
        np.ascontiguousarray(data, dtype=np.float64),
        np.ascontiguousarray(flags, dtype=np.bool_),
        np.ascontiguousarray(inverse_level, dtype=np.float64),
        block,
        _network(block),
        lo,
        weight,
        (float(nsig), float(nsig_adjacent), float(median_chi2)),
        out,
        (scan.band, scan.usable, scan.hit),
        (acc.hits, acc.usable, acc.clean_total, acc.clean_count),
    )
    in_threads(lambda ap0, ap1: _kernel(*args, ap0, ap1), nant * npol)
    return out, scan


def level_sums(data: np.ndarray, flags: np.ndarray, total: np.ndarray, count: np.ndarray) -> None:
    """Add each channel's usable samples (finite, positive, unflagged) and their number.

    ``data``, ``flags`` ``(Nant, Npol, Ntime, Nfreq)``; ``total``, ``count`` ``(Nant, Npol,
    Nfreq)``, in place; antenna-pols on threads (:func:`autocal.fit.threads.in_threads`).
    """
    data = np.ascontiguousarray(data, dtype=np.float64)
    flags = np.ascontiguousarray(flags, dtype=np.bool_)
    in_threads(
        lambda lo, hi: _level_sums(data, flags, total, count, lo, hi),
        data.shape[0] * data.shape[1],
    )


@numba.njit(cache=True, nogil=True)
def _level_sums(data, flags, total, count, ap0, ap1):  # type: ignore[no-untyped-def]
    """:func:`level_sums` for antenna-pols ``ap0`` to ``ap1 - 1``."""
    _, npol, ntime, nfreq = data.shape
    for ap in range(ap0, ap1):
        a = ap // npol
        p = ap % npol
        for t in range(ntime):
            for j in range(nfreq):
                x = data[a, p, t, j]
                if (not flags[a, p, t, j]) and x > 0.0 and x < np.inf:
                    total[a, p, j] += x
                    count[a, p, j] += 1


def _network(block: int) -> np.ndarray:
    """Return the sorting network for blocks of ``block`` channels (padded to a power of 2)."""
    size = 1
    while size < block:
        size *= 2
    return sorting_network(size)


def sorting_network(n: int) -> np.ndarray:
    """Return Batcher's odd-even merge sort for ``n`` inputs as ``(Ncomparator, 2)`` pairs.

    ``n`` must be a power of two (16: 63 comparators). Applying ``a[i], a[j] = min, max``
    for every pair in order sorts any ``n`` values; with a fixed sequence and no branches,
    the kernel runs it on all blocks of a spectrum at once in SIMD registers.
    """
    if n < 1 or n & (n - 1):
        raise ValueError(f"a sorting network needs a power of two inputs, not {n}")
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


@numba.njit(cache=True)
def _beyond(d: float, width: float, nsig: float, absolute: bool) -> bool:
    """Return whether the residual ``d`` is more than ``nsig`` widths (``|z|`` if absolute)."""
    if width > 0.0:
        z = d / width
    elif d == 0.0:
        z = 0.0
    else:
        z = np.inf if d > 0.0 else -np.inf
    return (abs(z) if absolute else z) > nsig


@numba.njit(cache=True)
def _block_medians(ratio, usable, block, network):  # type: ignore[no-untyped-def]
    """Return the median of each ``block`` channels' usable samples, and which had any.

    The blocks are laid side by side (``(block, Nblock)``, unusable samples +inf) and
    sorted together by the comparator ``network``; the inner loop over blocks vectorises.
    """
    nfreq = ratio.size
    nblock = (nfreq + block - 1) // block
    size = 1
    while size < block:
        size *= 2
    buf = np.full((size, nblock), np.inf)
    count = np.zeros(nblock, dtype=np.int64)
    for j in range(nfreq):
        if usable[j]:
            b = j // block
            buf[j - b * block, b] = ratio[j]
            count[b] += 1
    for c in range(network.shape[0]):
        i0 = network[c, 0]
        i1 = network[c, 1]
        for b in range(nblock):
            x = buf[i0, b]
            y = buf[i1, b]
            buf[i0, b] = x if x < y else y
            buf[i1, b] = y if x < y else x
    med = np.empty(nblock)
    for b in range(nblock):
        m = count[b]
        med[b] = 0.5 * (buf[(m - 1) // 2, b] + buf[m // 2, b]) if m > 0 else np.nan
    return med, count > 0


@numba.njit(cache=True)
def _kth_nonnegative(values, k, hist, scratch):  # type: ignore[no-untyped-def]
    """Return the ``k``-th smallest (0-based) of finite non-negative ``values``.

    A radix select on the IEEE bits (which order non-negative doubles as integers): the
    exponent, then the next 11 mantissa bits, then a sort of the few values left; three
    linear passes instead of quickselect's data-dependent branches.
    """
    bits = values.view(np.int64)  # sign bit 0: non-negative doubles order as integers
    n = values.size
    hist[:] = 0
    for i in range(n):
        hist[bits[i] >> 52] += 1
    acc = 0
    top = 0
    while acc + hist[top] <= k:
        acc += hist[top]
        top += 1
    k -= acc
    hist[:] = 0
    for i in range(n):  # without a branch: values of other exponents count in a spare slot
        hist[((bits[i] >> 41) & 2047) if (bits[i] >> 52) == top else 2048] += 1
    acc = 0
    mid = 0
    while acc + hist[mid] <= k:
        acc += hist[mid]
        mid += 1
    k -= acc
    key = (top << 11) | mid
    m = 0
    for i in range(n):
        if (bits[i] >> 41) == key:
            scratch[m] = values[i]
            m += 1
    return np.sort(scratch[:m])[k]


@numba.njit(cache=True)
def _median_nonnegative(values, hist, scratch):  # type: ignore[no-untyped-def]
    """Return the median of finite non-negative ``values`` (the mean of the middle two)."""
    n = values.size
    lo = _kth_nonnegative(values, (n - 1) // 2, hist, scratch)
    if n % 2 == 1:
        return lo
    below = 0  # values <= lo: if more than n // 2, the upper middle equals lo too
    above = np.inf
    for i in range(n):  # branch-free: the comparisons are coin flips
        v = values[i]
        below += v <= lo
        above = min(above, v if v > lo else np.inf)
    return lo if below > n // 2 else 0.5 * (lo + above)


@numba.njit(cache=True)
def _filled(med, have):  # type: ignore[no-untyped-def]
    """Give each block without samples the nearest block's median (left first), in place."""
    first = 0
    while not have[first]:
        first += 1
    last = first
    for b in range(med.size):
        if have[b]:
            last = b
        else:
            med[b] = med[last] if b > first else med[first]
    return med


@numba.njit(cache=True)
def _trend(med, lo, weight):  # type: ignore[no-untyped-def]
    """Return the block medians interpolated (and extrapolated) linearly per channel."""
    out = np.empty(lo.size)
    for j in range(lo.size):
        i = lo[j]
        out[j] = med[i] * (1.0 - weight[j]) + med[min(i + 1, med.size - 1)] * weight[j]
    return out


@numba.njit(cache=True, nogil=True)
def _kernel(
    data, flags, inv, block, network, lo, weight, sig, out, per_time, per_channel, ap0, ap1
):  # type: ignore[no-untyped-def]
    """Flag every spectrum of ``data`` into ``out`` (see :func:`spectrum_hits`).

    Antenna-pols ``ap0`` to ``ap1 - 1``: threads take whole antenna-pols, so each one's
    per-channel sums have one writer.
    """
    nsig, nadj, chi2 = sig
    band, n_usable, n_hit = per_time
    f_hits, f_usable, c_total, c_count = per_channel
    _, npol, ntime, nfreq = data.shape
    for ap in range(ap0, ap1):
        a = ap // npol
        p = ap % npol
        ratio = np.empty(nfreq)
        usable = np.zeros(nfreq, dtype=np.bool_)
        squares = np.empty(nfreq)
        scratch = np.empty(nfreq)
        hist = np.empty(2049, dtype=np.int32)
        for t in range(ntime):
            count = 0
            for j in range(nfreq):
                r = data[a, p, t, j] * inv[a, p, j]
                ok = (not flags[a, p, t, j]) and r > 0.0 and r < np.inf
                usable[j] = ok
                if ok:
                    ratio[j] = r
                    count += 1
                    f_usable[a, p, j] += 1
            n_usable[a, p, t] = count
            if count >= 3:
                band[a, p, t] = _flag_spectrum(
                    ratio,
                    usable,
                    count,
                    block,
                    network,
                    lo,
                    weight,
                    nsig,
                    nadj,
                    chi2,
                    out[a, p, t],
                    squares,
                    scratch,
                    hist,
                )
            hits = 0
            for j in range(nfreq):
                if out[a, p, t, j]:
                    hits += 1
                    f_hits[a, p, j] += 1
                elif usable[j]:
                    c_total[a, p, j] += data[a, p, t, j]
                    c_count[a, p, j] += 1
            n_hit[a, p, t] = hits


@numba.njit(cache=True)
def _flag_spectrum(
    ratio, usable, count, block, network, lo, weight, nsig, nadj, chi2, out, squares, scratch, hist
):  # type: ignore[no-untyped-def]
    """Flag one spectrum's ``ratio`` (to the time-mean spectrum) into ``out``.

    Returns the spectrum's band level: the median of its block medians.
    """
    nfreq = ratio.size
    med, have = _block_medians(ratio, usable, block, network)
    level = np.median(med[have])
    # the trend, twice: block medians of a steep slope are as noisy as one sample, so
    # the medians of what the first trend leaves (flat within blocks) correct it
    resid = ratio - _trend(_filled(med, have), lo, weight)
    med2, _ = _block_medians(resid, usable, block, network)
    resid -= _trend(_filled(med2, have), lo, weight)
    m = 0
    for j in range(nfreq):
        if usable[j]:
            squares[m] = resid[j] * resid[j]
            m += 1
    width = np.sqrt(_median_nonnegative(squares[:count], hist, scratch) / chi2)
    # watershed: runs of |z| > nadj that hold a sample with z > nsig
    j = 0
    while j < nfreq:
        if not (usable[j] and _beyond(resid[j], width, nadj, True)):
            j += 1
            continue
        start = j
        strong = False
        while j < nfreq and usable[j] and _beyond(resid[j], width, nadj, True):
            strong = strong or _beyond(resid[j], width, nsig, False)
            j += 1
        if strong:
            for k in range(start, j):
                out[k] = True
    return level
