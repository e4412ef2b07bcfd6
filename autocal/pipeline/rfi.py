"""Flagging before the fit: band edges and RFI found in the auto-correlations themselves.

The method follows hera_qm's ``xrfi`` (``detrend_medfilt``, ``watershed_flag``): a sample's
outlier significance is its difference from a robust local trend divided by a robust width
(``sqrt(median(residual^2) / 0.456)``); samples above :data:`NSIG` are flagged and the
flags grow into adjacent samples above :data:`NSIG_ADJACENT` (watershed). It is applied in
two separable steps, so that it gives the same flags whatever the read block size and
never needs a night in memory:

1. **RFI in frequency**, per spectrum: each spectrum is divided by the time-mean
   spectrum (the bandpass, stable in time, cancels and the ratio is smooth), detrended by
   the medians of :data:`BLOCK`-channel blocks interpolated between block centres (twice:
   the second time on what the first trend leaves), and
   divided by one robust width per spectrum (relative radiometer noise is the same in
   every channel), block by block as the data are read (:func:`frequency_flags`, a
   compiled kernel). Where hera_qm slides a 17-channel median filter, which cost ~190 s
   per pass over one 350-antenna HERA file (2 x 10^8 samples), the kernel takes ~3.8 s of
   CPU, ~1.9 s on two cores (a py-spy profile of ``autocal calibrate`` on the
   HERA-size file, one-off), and its width, from the whole spectrum rather than 16
   neighbours, is not itself noisy: on real HERA autos it finds 99 % of +1 % spikes where
   the sliding filter found 91 % (``python scripts/rfi_injection.py``);
2. **RFI in time**, per antenna-pol: each spectrum's level relative to the time-mean
   spectrum (the median of its block medians: one number per integration, kept for the
   whole observation) is median-filtered along time (:data:`KT` integrations each side)
   and outlying integrations are flagged whole; the robust width of
   :func:`robust_zscores` is floored at the series' own, or radiometer noise alone flags
   ~5e-4 of the integrations.

Then, once the whole observation has been seen (:class:`RfiScan`):

- **band edges**: channels outside the longest run of channels whose time-mean auto
  is at least :data:`EDGE_LEVEL` of the in-band median (the bandpass roll-off and the
  zeroed channels at the ends of a HERA band);
- channels that stand out of the time-mean spectrum (RFI that is always on), and channels
  flagged in frequency in more than :data:`CHANNEL_FRACTION` of their integrations, are
  flagged whole (persistent narrow-band RFI), and integrations with more than
  :data:`INTEGRATION_FRACTION` of their channels flagged are flagged whole (broad-band
  bursts), as xrfi's channel and integration thresholds do.

:class:`RfiMask` holds the result; :meth:`RfiMask.apply` ORs it into a block's flags before
the block enters the normal sums, so flagged samples never reach the fit.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.ndimage import find_objects, label, median_filter

if TYPE_CHECKING:
    from autocal.pipeline.rfi_kernel import BlockScan, ScanSums

logger = logging.getLogger(__name__)

#: Outlier significance (robust sigma) above which a sample is flagged (hera_qm's default
#: ``sig_init`` of ``simple_flag_waterfall``).
NSIG = 5.0
#: Significance above which a sample next to a flagged one is flagged too (watershed).
NSIG_ADJACENT = 2.0
#: Channels each side of a sample in the frequency median filter (hera_qm's ``Kf``).
KF = 8
#: Integrations each side in the time median filter (hera_qm's ``Kt``).
KT = 8
#: Channels per block of the frequency detrend (one median per block, interpolated).
BLOCK = 16
#: A band edge is where the time-mean auto is below this fraction of the in-band median.
EDGE_LEVEL = 0.1
#: A channel flagged in frequency in more than this fraction of its integrations is flagged.
CHANNEL_FRACTION = 0.25
#: An integration with more than this fraction of its channels flagged is flagged whole.
INTEGRATION_FRACTION = 0.5
#: Factor of hera_qm's ``detrend_medfilt``: ``median(z^2) = 0.456`` for a unit normal.
MEDIAN_CHI2_1 = 0.456

#: Frequency hits kept from the scan for the fit's reads (4 bytes each: 64 MB); blocks
#: beyond are flagged again when read (the same flags, the kernel is deterministic).
MAX_KEPT_HITS = 2**24

#: Reasons counted in the summary, in the order they are applied.
REASONS = ("band_edge", "rfi_frequency", "rfi_time")


def robust_zscores(
    values: np.ndarray,
    half_width: int,
    *,
    series_floor: bool = False,
    usable: np.ndarray | None = None,
) -> np.ndarray:
    """Return the outlier significance of each sample along the last axis.

    hera_qm's ``detrend_medfilt`` in one dimension: the residual from the median of the
    ``half_width`` neighbours each side (the sample itself excluded), divided by
    ``sqrt(median(residual^2) / 0.456)`` over the same neighbours, edges reflected.

    With ``series_floor``, the width is never less than the same statistic over the whole
    series (the last axis), for series whose noise is the same all along (the band level in
    time: :meth:`RfiScan._time_outliers`). The median of ``2 half_width`` squared residuals
    is itself noisy (for 16 it falls below half the true variance about one time in eight),
    and where it falls low by chance ordinary noise reaches 5 sigma: on white noise of 192
    samples with ``half_width`` 8 the local width alone flags 5.4e-4 of the samples after
    the :func:`watershed`, floored about 1e-6 (``python scripts/rfi_width_floor.py``). The
    cost: bursts just above the threshold are found less often (6 sigma: 0.48 against 0.55
    on white noise, 8 sigma 0.86 either way; the z-scores' spread is 0.89), and where part
    of the series is noisier the floor follows the noisier part once it is most of the
    series (8 sigma of the quiet part found in it at 0.11 against 0.86 when 60 % of the
    series has 3x the noise, 0.76 when 40 % has 2x), so it is not used where the
    residual's scatter varies along the series (the time-mean spectrum's fine structure:
    :func:`persistent_channels`).

    Parameters
    ----------
    values
        ``(..., N)`` finite values.
    half_width
        Neighbours each side (reduced to fit ``N``).
    series_floor
        Floor the local width at the whole series'.
    usable
        ``(..., N)`` the samples the series' width is taken over (default: all). Filled
        stand-ins for unusable samples (:func:`_filled`: the row's median) have residuals
        near zero and would lower it: with the first 60 of 192 samples of white noise
        filled, 3.6e-4 of the usable samples are flagged, 1.3e-6 with the floor over the
        usable ones (``python scripts/rfi_width_floor.py``).

    Returns
    -------
    numpy.ndarray
        ``(..., N)`` significances; ``inf`` where the robust width is zero and the
        residual is not, 0 where both are.
    """
    values = np.asarray(values, dtype=np.float64)
    n = values.shape[-1]
    k = max(1, min(int(half_width), (n - 1) // 2))
    if n < 3:
        return np.zeros_like(values)
    smooth = _neighbour_medians(values, k)
    resid = values - smooth
    squares = resid**2
    local = _neighbour_medians(squares, k)
    if series_floor:
        if usable is not None:
            with _quiet_nan():
                floor = np.nanmedian(np.where(usable, squares, np.nan), axis=-1, keepdims=True)
        else:
            floor = np.median(squares, axis=-1, keepdims=True)
        local = np.fmax(local, floor)  # a row without usable samples keeps its local width
    width = np.sqrt(local / MEDIAN_CHI2_1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = resid / width
    return np.where(width > 0, z, np.where(resid == 0, 0.0, np.inf))


def _neighbour_medians(values: np.ndarray, k: int) -> np.ndarray:
    """Return the median of the ``k`` neighbours each side along the last axis (reflected).

    scipy's median filter, the rows shared out over threads (it releases the GIL; each row
    is filtered on its own, so the result is the same).
    """
    from autocal.fit.threads import in_threads

    footprint = np.ones((1, 2 * k + 1), dtype=bool)
    footprint[0, k] = False
    rows = values.reshape(-1, values.shape[-1])
    out = np.empty_like(rows)

    def part(lo: int, hi: int) -> None:
        out[lo:hi] = median_filter(rows[lo:hi], footprint=footprint, mode="reflect")

    in_threads(part, rows.shape[0])
    return out.reshape(values.shape)


def watershed(z: np.ndarray, nsig: float, nsig_adjacent: float) -> np.ndarray:
    """Flag samples above ``nsig`` and every run above ``nsig_adjacent`` that touches one.

    Runs are contiguous along the last axis (hera_qm's ``watershed_flag`` in one
    dimension). Only excess power (``z > nsig``) starts a run, as RFI adds power: a
    channel whose mean is raised by intermittent RFI then does not get its clean samples,
    low against that mean, flagged; runs grow over ``|z| > nsig_adjacent``.
    """
    strong = z > nsig
    if not strong.any():
        return strong
    weak = np.abs(z) > nsig_adjacent
    structure = np.zeros((3,) * z.ndim, dtype=bool)
    structure[(1,) * (z.ndim - 1)] = True  # connect along the last axis only
    runs, _ = label(weak, structure=structure)
    hit = np.unique(runs[strong])
    return np.isin(runs, hit[hit > 0]) | strong


def _filled(data: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Return ``(rows, F)`` spectra with unusable samples replaced by the row's median."""
    rows = np.where(usable, data, np.nan)
    with np.errstate(all="ignore"), _quiet_nan():
        fill = np.nanmedian(rows, axis=-1, keepdims=True)
    return np.where(usable, data, np.where(np.isfinite(fill), fill, 0.0))


@contextmanager
def _quiet_nan() -> Iterator[None]:
    """Silence numpy's "All-NaN slice" warning (a fully flagged spectrum is expected)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def frequency_flags(
    data: np.ndarray,
    flags: np.ndarray,
    level: np.ndarray,
    sums: ScanSums | None = None,
    level_inverse: np.ndarray | None = None,
) -> tuple[np.ndarray, BlockScan]:
    """Flag RFI along frequency in each spectrum of a block.

    Each spectrum is divided by the time-mean spectrum ``level`` first, so the bandpass's
    fine structure (stable in time) cancels; the ratio's smooth trend is the median of each
    :data:`BLOCK` channels interpolated linearly between the blocks' centres and continued
    linearly beyond the first and last (:func:`trend_grid`), so a ratio that slopes across
    the band does not flag the band's ends; it is found twice, the second time from the
    block medians of what the first leaves (the median of a steep slope's block is as noisy
    as one sample; of a flat one, a quarter of that), and its width one robust number per spectrum,
    ``sqrt(median(residual^2) / 0.456)`` (hera_qm's ``detrend_medfilt`` factor; relative
    radiometer noise is the same in every channel). Runs above :data:`NSIG_ADJACENT` that
    hold a sample above :data:`NSIG` are flagged (:func:`watershed`). Computed by the
    compiled kernel :func:`autocal.pipeline.rfi_kernel.spectrum_hits`;
    :func:`frequency_flags_numpy` is the same as numpy array passes.

    Parameters
    ----------
    data, flags
        ``(Nant, Npol, Ntime, Nfreq)`` auto-correlations and their flags (flagged,
        non-finite and non-positive samples take no part and are not flagged again here).
    level
        ``(Nant, Npol, Nfreq)`` time-mean auto-correlations (:class:`LevelScan`).
    sums
        Per-channel sums over integrations to add the block to (the scan's), or ``None``.
    level_inverse
        ``1 / level`` where the level is positive and finite, NaN elsewhere, when the
        caller keeps it for its blocks (:class:`RfiScan` does), else ``None`` (made here).

    Returns
    -------
    hits : numpy.ndarray
        ``(..., Nfreq)`` the new RFI flags.
    scan : autocal.pipeline.rfi_kernel.BlockScan
        Each spectrum's level relative to ``level`` (``band``: the median of its block
        medians; NaN with fewer than three usable samples) and its usable and flagged
        sample counts.
    """
    from autocal.pipeline.rfi_kernel import spectrum_hits  # numba: only when flagging

    if level_inverse is None:
        level_inverse = _inverse(level)
    return spectrum_hits(
        data, flags, level_inverse, BLOCK, NSIG, NSIG_ADJACENT, MEDIAN_CHI2_1, sums
    )


def _inverse(level: np.ndarray) -> np.ndarray:
    """Return ``1 / level`` where the level is positive and finite, NaN elsewhere."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(level) & (level > 0), 1.0 / level, np.nan)


def frequency_flags_numpy(
    data: np.ndarray, flags: np.ndarray, level: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`frequency_flags` as numpy array passes (~10x slower): the kernel's reference."""
    nfreq = data.shape[-1]
    ratio = data * _inverse(level)[:, :, None, :]
    usable = ~flags & (ratio > 0) & np.isfinite(ratio)
    rows = np.where(usable, ratio, np.nan).reshape(-1, nfreq)
    block = max(1, min(BLOCK, nfreq))
    med = _block_medians(rows, block)
    enough = usable.reshape(-1, nfreq).sum(axis=1) >= 3
    with _quiet_nan():
        band = np.where(enough, np.nanmedian(med, axis=1), np.nan)
    resid = rows - _interpolate(_nearest_filled(med), nfreq, block)
    resid -= _interpolate(
        _nearest_filled(_block_medians(resid, block), np.isfinite(med)), nfreq, block
    )
    width = np.sqrt(_row_median(resid**2) / MEDIAN_CHI2_1)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(width > 0, resid / width, np.where(resid == 0, 0.0, np.inf))
    z[~usable.reshape(-1, nfreq) | ~enough[:, None]] = 0.0
    hits = watershed(z.reshape(data.shape), NSIG, NSIG_ADJACENT) & usable
    return hits, band.reshape(data.shape[:3])


def _block_medians(rows: np.ndarray, block: int) -> np.ndarray:
    """Return ``(R, Nblock)`` the median of each ``block`` channels of ``rows`` (NaN ignored)."""
    nrow, n = rows.shape
    nblock = -(-n // block)
    padded = np.full((nrow, nblock * block), np.nan)
    padded[:, :n] = rows
    return _row_median(padded.reshape(nrow * nblock, block)).reshape(nrow, nblock)


def _nearest_filled(med: np.ndarray, have: np.ndarray | None = None) -> np.ndarray:
    """Give each block without samples the nearest block's median, left first.

    A block has samples where ``have`` (default: where its median is finite).
    """
    nblock = med.shape[1]
    have = np.isfinite(med) if have is None else have
    index = np.arange(nblock)
    left = np.maximum.accumulate(np.where(have, index, -1), axis=1)
    right = np.minimum.accumulate(np.where(have, index, nblock)[:, ::-1], axis=1)[:, ::-1]
    nearest = np.where(left >= 0, left, np.minimum(right, nblock - 1))
    return np.take_along_axis(med, nearest, axis=1)


def trend_grid(nfreq: int, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Return how each channel's trend is read off the block medians.

    Channel ``j``'s trend is ``med[lo[j]] (1 - w[j]) + med[lo[j] + 1] w[j]``: linear
    between block centres and continued linearly beyond the first and last. A last block
    shorter than half a block (its median is one or a few samples) takes no part; its
    channels are extrapolated from the two before it.

    Returns
    -------
    lo, w : numpy.ndarray
        ``(nfreq,)`` the left block of each channel and its weight on the right one.
    """
    nblock = -(-nfreq // block)
    starts = np.arange(nblock) * block
    centres = (starts + np.minimum(starts + block, nfreq) - 1) / 2.0
    if nblock > 1 and nfreq - starts[-1] < block / 2:
        nblock -= 1  # a short last block
    channel = np.arange(nfreq, dtype=np.float64)
    if nblock < 2:
        return np.zeros(nfreq, np.int64), np.zeros(nfreq)
    lo = np.clip(np.searchsorted(centres[:nblock], channel, side="right") - 1, 0, nblock - 2)
    return lo.astype(np.int64), (channel - centres[lo]) / (centres[lo + 1] - centres[lo])


def _interpolate(med: np.ndarray, n: int, block: int) -> np.ndarray:
    """Return ``(R, n)`` block medians read off per channel (:func:`trend_grid`)."""
    lo, w = trend_grid(n, block)
    return med[:, lo] * (1.0 - w) + med[:, lo + 1 if med.shape[1] > 1 else lo] * w


def _row_median(rows: np.ndarray) -> np.ndarray:
    """Return the median of each row's finite values (NaN for a row without any)."""
    ordered = np.sort(rows, axis=-1)  # NaN sort last
    count = np.isfinite(rows).sum(axis=-1)
    lo = np.maximum(count - 1, 0) // 2
    hi = np.minimum(count // 2, rows.shape[-1] - 1)
    a = np.take_along_axis(ordered, lo[:, None], axis=-1)[:, 0]
    b = np.take_along_axis(ordered, hi[:, None], axis=-1)[:, 0]
    return np.where(count > 0, 0.5 * (a + b), np.nan)


def band_edges(level: np.ndarray, edge_level: float = EDGE_LEVEL) -> np.ndarray:
    """Return the band-edge channels of time-mean spectra.

    Parameters
    ----------
    level
        ``(..., Nfreq)`` time-mean auto-correlations (NaN: no data).
    edge_level
        Fraction of the in-band median below which a channel is out of band.

    Returns
    -------
    numpy.ndarray
        ``(..., Nfreq)`` True outside the longest run of channels at or above
        ``edge_level`` times the median of the positive channels, joined across gaps
        of up to ``2 KF`` channels to runs longer than that (:func:`_band_run`).
    """
    level = np.asarray(level, dtype=np.float64)
    out = np.ones(level.shape, dtype=bool)
    flat_level, flat_out = level.reshape(-1, level.shape[-1]), out.reshape(-1, level.shape[-1])
    for row, dest in zip(flat_level, flat_out, strict=True):
        positive = np.isfinite(row) & (row > 0)
        if not positive.any():
            continue
        # channels without data (NaN: flagged by the data) neither split nor extend the
        # band: the run is found among the channels that have data
        with_data = np.flatnonzero(np.isfinite(row))
        inband = positive[with_data] & (row[with_data] >= edge_level * np.median(row[positive]))
        lo, hi = _band_run(inband, 2 * KF)
        if hi > lo:
            dest[with_data[lo] : with_data[hi - 1] + 1] = False
    return out


def _band_run(inband: np.ndarray, max_gap: int) -> tuple[int, int]:
    """Return ``(start, stop)`` of the longest run of ``inband``, joined across short gaps.

    Gaps of at most ``max_gap`` channels are joined to runs at least ``max_gap + 1`` long,
    so a dead channel does not split the band, and an isolated spike beyond the roll-off
    does not extend it.
    """
    runs, nrun = label(inband)
    if nrun == 0:
        return 0, 0
    spans = [(int(sl[0].start), int(sl[0].stop)) for sl in find_objects(runs)]
    best = max(range(nrun), key=lambda i: spans[i][1] - spans[i][0])
    lo, hi = spans[best]
    for i in range(best - 1, -1, -1):  # join runs on the left
        start, stop = spans[i]
        if lo - stop > max_gap or stop - start <= max_gap:
            break
        lo = start
    for start, stop in spans[best + 1 :]:  # and on the right
        if start - hi > max_gap or stop - start <= max_gap:
            break
        hi = stop
    return lo, hi


def persistent_channels(level: np.ndarray) -> np.ndarray:
    """Return the channels of ``(Nant, Npol, Nfreq)`` time-mean spectra that stand out.

    RFI that is on all the time is part of the time-mean spectrum the frequency flags
    divide by, so it is looked for in that spectrum itself (the mean of the samples the
    frequency flags kept, so a few strong spikes do not cost their channel), with the same
    median filter along frequency.
    """
    usable = np.isfinite(level) & (level > 0)
    z = robust_zscores(_filled(level, usable), KF)
    return watershed(np.where(usable, z, 0.0), NSIG, NSIG_ADJACENT) & usable


def band_sky(tsky: np.ndarray, npol: int) -> np.ndarray:
    """Return the model sky's band level ``(npol, Ntime)``, as the data's is measured.

    The median over channels of ``Tsky(t, nu)`` over its time mean (as each spectrum's
    band level is the median over its channels of data over the time-mean spectrum). A
    model with one polarisation (or another number than ``npol``) is averaged and shared.
    """
    tsky = np.asarray(tsky, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"), _quiet_nan():
        rel = tsky / np.nanmean(tsky, axis=1, keepdims=True)
        level = np.nanmedian(rel, axis=-1)  # (P, T)
    if level.shape[0] != npol:
        level = np.broadcast_to(np.nanmean(level, axis=0), (npol, level.shape[1]))
    return level


def sky_trend(band: np.ndarray, ok: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """Return ``a + b sky(t)`` fitted to each antenna-pol's band level ``(Nant, Npol, Ntime)``.

    Least squares over the usable integrations, then again without those more than five
    robust sigma off (an RFI burst must not pull the line); zero where it cannot be fitted
    (fewer than three integrations or a constant sky) and at integrations whose model sky
    is not finite (:meth:`RfiScan._time_outliers` does not test those).
    """
    x = np.broadcast_to(np.asarray(sky, dtype=np.float64)[None], band.shape)
    finite = np.isfinite(x)
    w = (ok & finite).astype(np.float64)
    y = np.where(w > 0, band, 0.0)
    xs = np.where(finite, x, 0.0)
    fit = np.zeros(band.shape)
    for _ in range(2):
        sw, sx, sy = w.sum(-1), (w * xs).sum(-1), (w * y).sum(-1)
        sxx, sxy = (w * xs * xs).sum(-1), (w * xs * y).sum(-1)
        det = sw * sxx - sx * sx
        good = (sw >= 3) & (det > 1e-12 * np.maximum(sw * sxx, 1e-300))
        with np.errstate(invalid="ignore", divide="ignore"):
            b = np.where(good, (sw * sxy - sx * sy) / det, 0.0)
            a = np.where(good, (sy - b * sx) / np.where(sw > 0, sw, 1.0), 0.0)
        # zero (the level left as it is) where the model sky is not finite, not ``a``
        fit = np.where(good[..., None] & finite, a[..., None] + b[..., None] * xs, 0.0)
        resid = np.where(w > 0, y - fit, np.nan)
        with _quiet_nan():
            mad = 1.4826 * np.nanmedian(np.abs(resid), axis=-1, keepdims=True)
        w = np.where(np.abs(resid) <= 5 * np.maximum(mad, 1e-300), w, 0.0)
    return fit


@dataclass(frozen=True)
class RfiMask:
    """The flags of the whole observation that do not depend on one block alone.

    Attributes
    ----------
    band_edge
        ``(Nant, Npol, Nfreq)`` band-edge channels.
    channels
        ``(Nant, Npol, Nfreq)`` channels flagged whole for persistent RFI.
    integrations
        ``(Nant, Npol, Ntime)`` integrations flagged whole (RFI in time).
    level
        ``(Nant, Npol, Nfreq)`` the time-mean spectra the frequency flags divide by.
    counts
        The summary's ``rfi`` block (:meth:`RfiScan.finish`).
    hits
        The scan's frequency hits of each block, ``{(offset, shape): flat indices}``, so
        the fit's reads of the same blocks need not flag them again (:meth:`apply`; at
        most :data:`MAX_KEPT_HITS`; empty once :meth:`portable`).
    """

    band_edge: np.ndarray
    channels: np.ndarray
    integrations: np.ndarray
    level: np.ndarray
    counts: dict[str, Any] = field(default_factory=dict)
    hits: dict[tuple[int, tuple[int, ...]], np.ndarray] = field(default_factory=dict)

    def portable(self) -> RfiMask:
        """Return this mask without the kept hits (for Dask workers: they flag again)."""
        return replace(self, hits={})

    def hits_between(self, start: int, stop: int) -> dict[tuple[int, tuple[int, ...]], np.ndarray]:
        """Return the kept hits of the blocks starting at integrations ``start:stop`` (a file's).

        A worker given them with the :meth:`portable` mask needs not flag those blocks again.
        """
        return {key: where for key, where in self.hits.items() if start <= key[0] < stop}

    def apply(self, data: np.ndarray, flags: np.ndarray, offset: int) -> np.ndarray:
        """Return a block's flags with band edges and RFI added.

        Parameters
        ----------
        data, flags
            ``(Nant, Npol, Ntime, Nfreq)`` the block's autos and flags.
        offset
            Index of the block's first integration in the observation.
        """
        nt = data.shape[2]
        kept = self.hits.get((offset, data.shape))
        if kept is not None:  # the scan's flags of this very block
            out = np.zeros(data.shape, dtype=bool)
            out.reshape(-1)[kept] = True
        else:
            out, _ = frequency_flags(data, flags, self.level)  # the same flags again
        out |= flags | self.band_edge[:, :, None, :] | self.channels[:, :, None, :]
        out |= self.integrations[:, :, offset : offset + nt, None]
        return out


@dataclass
class LevelScan:
    """The first read: the time-mean spectrum of every antenna-pol, block by block."""

    total: np.ndarray | None = None
    count: np.ndarray | None = None

    def add(self, data: np.ndarray, flags: np.ndarray) -> None:
        """Add one block ``(Nant, Npol, Ntime, Nfreq)``: its finite, positive, unflagged samples."""
        from autocal.pipeline.rfi_kernel import level_sums  # numba: only when flagging

        self._start(data.shape[:2] + data.shape[3:])
        assert self.total is not None and self.count is not None
        level_sums(data, flags, self.total, self.count)

    def _start(self, shape: tuple[int, ...]) -> None:
        """Allocate the zero sums of ``(Nant, Npol, Nfreq)`` spectra (once)."""
        if self.total is None or self.count is None:
            self.total = np.zeros(shape)
            self.count = np.zeros(shape, np.int64)

    def add_scan(self, part: LevelScan) -> None:
        """Add the sums of a later stretch of integrations (a file) scanned on its own.

        The sums of a night are its files' sums added in file order, wherever each file
        was scanned (:mod:`autocal.pipeline.flag_partials`): the same level bit for bit.
        """
        if part.total is None or part.count is None:
            return
        self._start(part.total.shape)
        assert self.total is not None and self.count is not None
        self.total += part.total
        self.count += part.count

    def level(self) -> np.ndarray:
        """Return ``(Nant, Npol, Nfreq)`` the mean of the usable samples (NaN: none)."""
        if self.total is None or self.count is None:
            raise ValueError("no data were scanned for flagging")
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.count > 0, self.total / self.count, np.nan)


@dataclass
class RfiScan:
    """The second read: accumulates, block by block, what the flags are decided from.

    Attributes
    ----------
    ntime
        Integrations of the observation.
    level
        ``(Nant, Npol, Nfreq)`` time-mean spectra (:meth:`LevelScan.level`).
    sums
        Per-channel sums over integrations: samples flagged and usable, and the mean of
        the samples the frequency flags keep (:class:`~autocal.pipeline.rfi_kernel.ScanSums`).
    sky
        ``(Npol, Ntime)`` the model sky's band level (:func:`band_sky`), or ``None``.

    The inverse of ``level`` that the blocks' scans divide by is kept between blocks (made
    again if ``level`` is replaced) and left out when the scan is pickled (a file's scan
    travels back from reader processes and Dask workers).
    """

    ntime: int
    level: np.ndarray
    sky: np.ndarray | None = None
    sums: ScanSums | None = None
    band_median: np.ndarray | None = None
    hits_per_time: np.ndarray | None = None
    usable_per_time: np.ndarray | None = None
    prior_flagged: int = 0
    kept: dict[tuple[int, tuple[int, ...]], np.ndarray] = field(default_factory=dict)
    nkept: int = 0
    _inverse: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False)

    def __getstate__(self) -> dict[str, Any]:
        """Return the state to pickle: without the kept inverse level (derived from it)."""
        return {**self.__dict__, "_inverse": None}

    def add(self, data: np.ndarray, flags: np.ndarray, offset: int) -> None:
        """Add one block ``(Nant, Npol, Ntime, Nfreq)`` starting at integration ``offset``."""
        nant, npol, nt, nfreq = data.shape
        self._start((nant, npol, nfreq))
        assert self.band_median is not None
        assert self.hits_per_time is not None and self.usable_per_time is not None
        self.prior_flagged += int(np.count_nonzero(flags))
        if self._inverse is None or self._inverse[0] is not self.level:  # once for the blocks
            self._inverse = (self.level, _inverse(self.level))
        hits, scan = frequency_flags(data, flags, self.level, self.sums, self._inverse[1])
        self._keep(hits, offset)
        window = slice(offset, offset + nt)
        self.band_median[:, :, window] = scan.band
        self.hits_per_time[:, :, window] = scan.hit
        self.usable_per_time[:, :, window] = scan.usable

    def _start(self, shape: tuple[int, int, int]) -> None:
        """Allocate the zero sums of ``(Nant, Npol, Nfreq)`` spectra (once)."""
        from autocal.pipeline.rfi_kernel import ScanSums  # numba: only when flagging

        if self.sums is None:
            nant, npol, _ = shape
            self.sums = ScanSums.zeros(shape)
            self.band_median = np.full((nant, npol, self.ntime), np.nan)
            self.hits_per_time = np.zeros((nant, npol, self.ntime), np.int64)
            self.usable_per_time = np.zeros((nant, npol, self.ntime), np.int64)

    def add_scan(self, part: RfiScan, offset: int) -> None:
        """Add the scan of a later stretch of integrations (a file) scanned on its own.

        ``part`` covers integrations ``offset`` to ``offset + part.ntime`` (its own block
        offsets count from its start). The per-channel sums of a night are its files' sums
        added in file order, wherever each file was scanned
        (:mod:`autocal.pipeline.flag_partials`), so the mask is the same bit for bit; the
        per-integration results are copied into place and the kept hits moved to their
        offsets in the observation (while they fit :data:`MAX_KEPT_HITS`).
        """
        if part.sums is None:
            return
        assert part.band_median is not None
        assert part.hits_per_time is not None and part.usable_per_time is not None
        self._start(part.sums.hits.shape)
        assert self.sums is not None and self.band_median is not None
        assert self.hits_per_time is not None and self.usable_per_time is not None
        self.sums.add(part.sums)
        window = slice(offset, offset + part.ntime)
        self.band_median[:, :, window] = part.band_median
        self.hits_per_time[:, :, window] = part.hits_per_time
        self.usable_per_time[:, :, window] = part.usable_per_time
        self.prior_flagged += part.prior_flagged
        for (start, shape), where in part.kept.items():
            if self.nkept + where.size <= MAX_KEPT_HITS:
                self.kept[(offset + start, shape)] = where
                self.nkept += where.size

    def _keep(self, hits: np.ndarray, offset: int) -> None:
        """Keep a block's hits as flat indices while they fit :data:`MAX_KEPT_HITS`."""
        where = np.flatnonzero(hits)
        if self.nkept + where.size > MAX_KEPT_HITS:
            return
        dtype = np.int32 if hits.size < 2**31 else np.int64
        self.kept[(offset, hits.shape)] = where.astype(dtype)
        self.nkept += where.size

    def finish(self) -> RfiMask:
        """Return the observation's mask and the summary counts of every reason."""
        if self.sums is None:
            raise ValueError("no data were scanned for flagging")
        sums = self.sums
        assert self.hits_per_time is not None and self.usable_per_time is not None
        edge = band_edges(self.level)
        with np.errstate(divide="ignore", invalid="ignore"):
            channel = (sums.hits > CHANNEL_FRACTION * sums.usable) & ~edge
            clean = np.where(sums.clean_count > 0, sums.clean_total / sums.clean_count, np.nan)
        channel |= persistent_channels(clean) & ~edge
        nfreq = edge.shape[-1]
        bursts = self.hits_per_time > INTEGRATION_FRACTION * np.maximum(self.usable_per_time, 1)
        integrations = bursts | self._time_outliers()
        counts = self._counts(edge, channel, integrations, nfreq)
        return RfiMask(edge, channel, integrations, self.level, counts, self.kept)

    def _time_outliers(self) -> np.ndarray:
        """Integrations whose band level (of data / level) stands out from its neighbours.

        With the model sky's band level (:attr:`sky`), the band level is first divided by
        the part that follows the sky (``a + b sky(t)``, fitted per antenna-pol): at a
        coarse cadence the galaxy's transit through a narrow beam is sharper than the
        median filter, which would otherwise flag it (a day at 15-minute cadence through
        the HERA beam had three transit integrations flagged and the diagnosis named a
        sky-scale error that was not there).
        """
        assert self.band_median is not None
        med = self.band_median
        ok = np.isfinite(med)
        if self.sky is not None:  # relative to it: a gain drift times the transit stays smooth
            trend = sky_trend(med, ok, self.sky)
            with np.errstate(invalid="ignore", divide="ignore"):
                med = np.where(trend > 0, med / trend, med)
            # where a fitted row has no model sky (or no positive fit), it is not tested:
            # the level there, undivided, would stand out from its divided neighbours
            fitted = (trend > 0).any(axis=-1, keepdims=True)
            ok = ok & ((trend > 0) | ~fitted)
        filled = _filled(med, ok)
        if self.ntime >= 3:
            z = robust_zscores(filled, KT, series_floor=True, usable=ok)
        else:
            z = np.zeros_like(med)
        return watershed(np.where(ok, z, 0.0), NSIG, NSIG_ADJACENT) & ok

    def _counts(
        self, edge: np.ndarray, channel: np.ndarray, integrations: np.ndarray, nfreq: int
    ) -> dict[str, Any]:
        """Return the numbers of channels, integrations and samples flagged per reason.

        A channel without any usable sample (its time-mean spectrum not positive and
        finite) counts as ``no_data``, not as a band edge, though the mask flags it as one.
        """
        assert self.sums is not None and self.level is not None
        nant, npol, ntime = integrations.shape
        total = nant * npol * ntime * nfreq
        with np.errstate(invalid="ignore"):
            no_data = ~(np.isfinite(self.level) & (self.level > 0))
        edge = edge & ~no_data
        edge_samples = int(edge.sum()) * ntime
        channel_samples = int(channel.sum()) * ntime
        scattered = int(np.where(edge | channel | no_data, 0, self.sums.hits).sum())
        # integrations flagged whole x channels not flagged already, per antenna-pol
        kept_channels = np.count_nonzero(~(edge | channel | no_data), axis=-1)
        time_samples = int((np.count_nonzero(integrations, axis=-1) * kept_channels).sum())
        samples = {
            "band_edge": edge_samples,
            "rfi_frequency": channel_samples + scattered,
            "rfi_time": time_samples,
            "no_data": int(no_data.sum()) * ntime,
        }
        return {
            "applied": True,
            "samples_total": total,
            "samples": samples,
            "fractions": {k: round(v / total, 6) if total else 0.0 for k, v in samples.items()},
            "band_edge_channels": int(edge.any(axis=(0, 1)).sum()),
            "no_data_channels": int(no_data.any(axis=(0, 1)).sum()),
            "rfi_channels": int(channel.any(axis=(0, 1)).sum()),
            "rfi_integrations": int(integrations.any(axis=(0, 1)).sum()),
            "method": {
                "nsig": NSIG,
                "nsig_adjacent": NSIG_ADJACENT,
                "kf": KF,
                "kt": KT,
                "edge_level": EDGE_LEVEL,
                "channel_fraction": CHANNEL_FRACTION,
                "integration_fraction": INTEGRATION_FRACTION,
            },
        }
