"""Flagging narrow-band and impulsive outliers (RFI) in the residuals of a fit.

:func:`find_outliers` high-passes a fit's normalised residuals in time and in frequency by
running medians (:func:`running_median`) and flags what deviates by many sigma of their
clean-data tails (:func:`tail_scale`); the search
(:func:`autocal.diagnosis.stepwise.diagnose`) flags on its final model's residuals and
searches again.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter
from scipy.stats import norm, poisson

from autocal.core.observation import Observation
from autocal.diagnosis.chunks import antenna_chunks, weights_dtype
from autocal.diagnosis.extended_fit import ExtendedFit, residual_pieces

#: Compare-exchange pairs of a median-of-9 sorting network (19 exchanges; Paeth, Devillard):
#: afterwards element 4 holds the median.
_MEDIAN9 = (
    (1, 2),
    (4, 5),
    (7, 8),
    (0, 1),
    (3, 4),
    (6, 7),
    (1, 2),
    (4, 5),
    (7, 8),
    (0, 3),
    (5, 8),
    (4, 7),
    (3, 6),
    (1, 4),
    (2, 5),
    (4, 7),
    (4, 2),
    (6, 4),
    (4, 2),
)


def running_median(x: np.ndarray, window: int, axis: int) -> np.ndarray:
    """Return the running median of ``x`` over ``window`` samples along ``axis``.

    That of ``scipy.ndimage.median_filter`` (mode ``"mirror"``, a footprint along ``axis``
    only). A window of 9 over an axis longer than 9 uses a sorting network on whole arrays (the
    same values as ``median_filter``, ~4x faster on a HERA antenna); other windows call
    ``median_filter``.
    """
    n = x.shape[axis]
    if window != 9 or n <= window:
        size = [1] * x.ndim
        size[axis] = window
        return median_filter(x, size=tuple(size), mode="mirror")
    half = window // 2
    pad = [(0, 0)] * x.ndim
    pad[axis] = (half, half)
    xp = np.pad(x, pad, mode="reflect")  # scipy's "mirror"
    lead = (slice(None),) * (axis % x.ndim)
    p = [np.array(xp[(*lead, slice(i, i + n))]) for i in range(window)]
    for a, b in _MEDIAN9:
        low = np.minimum(p[a], p[b])
        np.maximum(p[a], p[b], out=p[b])
        p[a] = low
    return p[4]


#: Integrations and channels of the running medians of :func:`find_outliers`.
OUTLIER_WINDOW = 9
#: White Gaussian samples (time x frequency) from which :func:`tail_scale` reads the null
#: distribution of the high-passed residuals, and the two-sided tail probability at which
#: it reads their width.
NULL_SHAPE = (1024, 4096)
NULL_TAIL_PROBABILITY = 1e-4


def high_pass(res: np.ndarray, window: int) -> np.ndarray:
    """Subtract from ``res`` its running median over ``window`` integrations, then channels.

    ``res`` is ``(..., Ntime, Nfreq)`` with no NaN (flagged samples filled with zero).
    """
    hp = res - running_median(res, window, axis=-2)
    return hp - running_median(hp, window, axis=-1)


@functools.cache
def tail_scale(window: int) -> float:
    """Width of the high-passed residuals' tails in units of their robust sigma (white noise).

    Subtracting running medians narrows the core of the distribution (a sample's own value
    pulls the median it is compared with) but hardly its tails (an extreme sample keeps
    nearly all of its deviation): on white Gaussian noise the robust sigma
    (1.4826 x MAD) of the high-passed values is 0.71 of their tails' width, so "6 robust
    sigma" flagged 3e-5 of clean samples, 15 000 times the Gaussian 6-sigma rate (~6000
    samples of a clean 350-antenna HERA file, and two extra rounds of the search). The tails
    are close to those of a Gaussian (an extreme value minus medians of its neighbours),
    whose width is read here at the two-sided tail probability
    :data:`NULL_TAIL_PROBABILITY` of :data:`NULL_SHAPE` samples of white noise (fixed seed;
    computed once per window). They are somewhat heavier farther out: white noise exceeds
    ``k`` sigma at 1.1-1.5 x the Gaussian rate for ``k`` = 3.5-4.5
    (``tests/diagnosis/test_outliers.py``) and at 2.0x for ``k`` = 5 (80 of 71 M white
    samples, 41 expected), and the excess keeps growing with ``k`` (an extreme sample minus
    its neighbours' medians: estimated ~3x at 6 sigma; see :data:`TAIL_EXCESS`).

    Parameters
    ----------
    window
        Integrations and channels of the running medians.

    Returns
    -------
    float
        Tail width / robust sigma: a threshold of ``k`` sigma is ``k * tail_scale`` robust
        sigma of the high-passed residuals, flagging clean samples at about the Gaussian
        rate ``2 Phi(-k)`` (see above).
    """
    if window < 3:
        raise ValueError(f"the running medians need a window of at least 3 samples, not {window}")
    noise = np.random.default_rng(20261128).standard_normal(NULL_SHAPE)
    dev = np.abs(high_pass(noise, window))
    robust = 1.4826 * np.median(dev)
    width = np.quantile(dev, 1 - NULL_TAIL_PROBABILITY) / norm.isf(NULL_TAIL_PROBABILITY / 2)
    return float(width / robust)


#: Clean residuals exceed a threshold of the filtered values at up to this many times the
#: Gaussian rate at the default 6 sigma (~1.1x at 4 sigma and 2x at 5, measured; ~3x at 6,
#: estimated: the tails are somewhat heavier than the Gaussian of :func:`tail_scale`'s
#: width) ...
TAIL_EXCESS = 3.0
#: ... and a round's new outliers count as noise up to this Poisson quantile of that
#: expectation (:func:`noise_outlier_limit`), if none deviates by more than
#: :data:`NOISE_MAX_SIGMA` (white noise exceeds 8 sigma of the filtered residuals at
#: ~1e-14 per sample).
NOISE_QUANTILE = 0.999
NOISE_MAX_SIGMA = 8.0


def noise_outlier_limit(samples: int, threshold: float) -> int:
    """Most outliers ``samples`` clean residuals give at ``threshold`` sigma (one round).

    The :data:`NOISE_QUANTILE` Poisson quantile of :data:`TAIL_EXCESS` times the Gaussian
    expectation ``2 Phi(-threshold) samples``; at 6 sigma: 6 for a 350-antenna HERA file
    (206 M samples, 0.4 expected at the Gaussian rate), 1 for 1 M, 0 below ~1.7e5. A round that
    flags no more than this found nothing the fits need to be repeated without
    (:func:`autocal.diagnosis.stepwise.diagnose`).
    """
    samples = max(int(samples), 0)
    expected = min(TAIL_EXCESS * 2.0 * norm.sf(threshold), 1.0) * samples
    return min(int(poisson.ppf(NOISE_QUANTILE, expected)), samples) if expected > 0 else 0


def model_residual_pieces(
    fit: ExtendedFit, flags: np.ndarray
) -> Iterator[tuple[slice, np.ndarray]]:
    """Yield ``(antenna slice, normalised residuals)`` of a fit wherever ``flags`` is false.

    ``(R - model) sqrt(dnu dt N) / model``: the radiometer normalisation of the fit's own
    model, so that samples the fit did not use (flagged by an earlier round of
    :func:`find_outliers`) get residuals too. NaN where ``flags`` is set, the data are not
    finite or the channel has no ``(G, n)`` solution.
    """
    src = fit.source
    if src is None:
        raise ValueError("the fit is detached from its data: no residuals")
    obs = src.obs
    width = obs.channel_width[None, None, None, :]
    tint = obs.integration_time[None, None, :, None]
    for sl, model in fit.model_chunks():
        bt = width * (tint * obs.nsamples[sl])
        usable = ~flags[sl] & np.isfinite(obs.data[sl]) & src.chan_ok[sl][:, :, None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            res = (obs.data[sl] - model) * np.sqrt(bt) / np.abs(model)
        yield sl, np.where(usable & np.isfinite(res), res, np.nan)


@dataclass(frozen=True)
class OutlierRound:
    """One round of :func:`find_outliers`.

    Attributes
    ----------
    flags
        ``(Nant, Npol, Ntime, Nfreq)`` flags (the observation's own included).
    peak_sigma
        The largest deviation of a sample beyond the threshold, in sigma (0 if none).
    """

    flags: np.ndarray
    peak_sigma: float


def find_outliers(
    obs: Observation,
    fit: ExtendedFit,
    *,
    threshold: float = 6.0,
    window: int = OUTLIER_WINDOW,
    max_fraction: float = 0.5,
    base_flags: np.ndarray | None = None,
) -> OutlierRound:
    """Flag narrow-band or impulsive outliers (RFI) in the residuals of a fit.

    The normalised residuals are high-passed by subtracting their running median over
    ``window`` integrations and then over ``window`` channels, so structure smooth in
    time or in frequency (the signatures of every catalogue effect, and the bending of
    a channel's fit by an outlier) is left alone and only features a few samples wide
    are flagged: samples deviating by more than ``threshold`` sigma, the sigma being the
    width of the high-passed values' tails on clean data (1.4826 x their median absolute
    deviation over all samples x :func:`tail_scale`), so that white Gaussian residuals
    are flagged at the Gaussian rate ``2 Phi(-threshold)``. A channel (integration)
    that loses more than ``max_fraction`` of its samples is flagged entirely. The
    residuals are filtered a chunk of antennas at a time; the high-passed values of a
    large observation (:func:`~autocal.diagnosis.chunks.is_large`) are kept in float32 for
    the median over all.

    Parameters
    ----------
    obs
        The observation the fit was made to.
    fit
        A fit of it (:func:`~autocal.diagnosis.extended_fit.fit_extended`).
    threshold
        Sigmas (of the tails' width, see above) beyond which a sample is an outlier.
    window
        Integrations and channels of the running medians.
    max_fraction
        Fraction of flagged samples above which a whole channel or integration is flagged.
    base_flags
        The flags the outliers are added to, ``(Nant, Npol, Ntime, Nfreq)``. Given (the
        observation's own flags, before any outlier round), every sample they leave is
        judged afresh on the fit's model (:func:`model_residual_pieces`), those flagged by
        an earlier round included: the flags are recomputed, not accumulated, so a bad
        first model does not leave its flags behind. ``None``: ``obs.flags``, and only the
        samples the fit used are judged.

    Returns
    -------
    OutlierRound
        The flags (the observation's own included) and the largest deviation flagged.
    """
    if not threshold > 0:
        raise ValueError(
            f"the outlier threshold must be a positive number of sigma, not {threshold}"
        )
    scale = tail_scale(window)  # before the large arrays below are allocated
    base = obs.flags if base_flags is None else np.asarray(base_flags, bool)
    pieces = residual_pieces(fit) if base_flags is None else model_residual_pieces(fit, base)
    dev = np.empty(obs.shape, weights_dtype(obs.shape))
    usable = np.zeros(obs.shape, bool)
    for sl, res in pieces:
        ok = np.isfinite(res)
        usable[sl] = ok
        # high-pass in time, then in frequency: what a fit bent by an outlier spreads over
        # its channel is smooth in time and goes; the outlier itself stays
        hp = high_pass(np.where(ok, res, 0.0), window)
        dev[sl] = np.where(ok, hp, np.nan)
    if not usable.any():
        return OutlierRound(base.copy(), 0.0)
    centre = np.nanmedian(dev)
    np.subtract(dev, centre, out=dev)
    np.abs(dev, out=dev)  # in place: |deviation from the centre|
    # the tails' width on clean data: ``threshold`` sigma flag clean samples at the
    # Gaussian rate (tail_scale)
    sigma = 1.4826 * np.nanmedian(dev) * scale
    if not np.isfinite(sigma) or sigma <= 0:
        return OutlierRound(base.copy(), 0.0)
    flags = base.copy()
    peak = 0.0
    for sl in antenna_chunks(obs.shape):
        ok = usable[sl]
        new = ok & (dev[sl] > threshold * sigma)
        if new.any():
            peak = max(peak, float(dev[sl][new].max() / sigma))
        count = np.maximum(ok.sum(axis=2, keepdims=True), 1)
        new |= (new.sum(axis=2, keepdims=True) / count > max_fraction) & ok
        count = np.maximum(ok.sum(axis=3, keepdims=True), 1)
        new |= (new.sum(axis=3, keepdims=True) / count > max_fraction) & ok
        flags[sl] |= new
    return OutlierRound(flags, peak)
