"""Is a per-integration gain series jitter? The test of ``gain_jitter`` and its kin.

A ``gain_jitter`` fit absorbs any achromatic time structure; :func:`jitter_is_significant`
names it only when what a smooth function of time or of the sky (:func:`sky_time_shapes`)
leaves of the series pays for its parameters, against the bulk's scatter
(:func:`~autocal.diagnosis.dispersion.robust_overdispersion`). :func:`feed_departures_rough`
applies the same test to every antenna-pol's departure from the common series
(``antenna_gain_jitter``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.effects import DIURNAL_MIN_SPAN_H, SkyTemplates, diurnal_basis, time_basis
from autocal.diagnosis.extended_fit import ExtendedFit
from autocal.diagnosis.feeds import FeedGainFit
from autocal.diagnosis.trials import BIC_THRESHOLD
from autocal.fit.model import unwrap_lsts

#: Legendre order of the smooth part removed from a ``gain_jitter`` series before its
#: remainder is tested (:func:`jitter_is_significant`).
JITTER_SMOOTH_ORDER = 3
#: Sidereal-day harmonics also removed from a ``gain_jitter`` series spanning at least
#: :data:`autocal.diagnosis.effects.DIURNAL_MIN_SPAN_H` (:func:`jitter_is_significant`).
JITTER_DIURNAL_HARMONICS = 2


@dataclass(frozen=True)
class JitterTest:
    """The verdict of :func:`jitter_is_significant` and the numbers behind it.

    Attributes
    ----------
    significant
        Whether the series is jitter (:attr:`rough_delta_bic` above the threshold).
    rough_reduced_chi2
        The remainder's chi^2 per degree of freedom once the smooth part is removed.
    smooth_fraction
        For information: the share of the series' weighted power the smooth part holds.
    lag1
        For information: the remainder's lag-1 autocorrelation.
    rough_delta_bic
        Delta BIC of the remainder (its chi^2 over the overdispersion, less ``ln N`` per
        parameter beyond the smooth part).
    """

    significant: bool
    rough_reduced_chi2: float
    smooth_fraction: float
    lag1: float
    rough_delta_bic: float

    def to_dict(self) -> dict[str, float]:
        """Return the numbers (a diagnosis's ``jitter_tests`` entry)."""
        return {
            "rough_reduced_chi2": self.rough_reduced_chi2,
            "smooth_fraction": self.smooth_fraction,
            "lag1": self.lag1,
            "rough_delta_bic": self.rough_delta_bic,
        }


def jitter_is_significant(
    eps: np.ndarray,
    sigma: np.ndarray,
    lsts: np.ndarray,
    sky_shapes: np.ndarray | None = None,
    *,
    ndata: int = 1,
    overdispersion: float = 1.0,
) -> JitterTest:
    """Test whether a per-integration gain series is jitter rather than a smooth change.

    A ``gain_jitter`` fit absorbs any achromatic time structure, including a smooth one
    (a drift) and the time shape of a sky model that is slightly wrong (the series then
    follows the sky's own variation). The series counts as jitter only if, after removing
    a Legendre polynomial of order :data:`JITTER_SMOOTH_ORDER` in LST and the sky's time
    shapes (``sky_shapes``: e.g. the band-averaged model Tsky, its square and its time
    derivative), and over 6 h or more :data:`JITTER_DIURNAL_HARMONICS` sidereal-day
    harmonics, the remainder pays for its extra parameters as any candidate must: its
    chi-square over the overdispersion, less ``ln N`` per parameter beyond the smooth part,
    exceeds :data:`~autocal.diagnosis.trials.BIC_THRESHOLD`. Fluctuations correlated from
    one integration to the next (red gain noise) pass when they are large; what a smooth
    function of time or of the sky explains does not, and goes to a smooth effect or stays
    unexplained.

    Parameters
    ----------
    eps
        ``(Ntime,)`` fractional gain factors (0 for the reference integration).
    sigma
        ``(Ntime,)`` their 1-sigma (0 for the reference: it gets the median).
    lsts
        ``(Ntime,)`` hours.
    sky_shapes
        ``(K, Ntime)`` further smooth templates, or ``None``.
    ndata, overdispersion
        The data count ``N`` of the BIC penalty and the fit's ``max(1, chi^2/dof)``.

    Returns
    -------
    JitterTest
        The verdict and the numbers behind it (``rough_reduced_chi2``, ``rough_delta_bic``,
        and for information ``smooth_fraction``, the share of the series' weighted power the
        smooth part holds, and ``lag1``, the remainder's lag-1 autocorrelation).
    """
    eps = np.asarray(eps, float)
    sig = np.asarray(sigma, float)
    good = np.isfinite(eps) & np.isfinite(sig)
    positive = good & (sig > 0)
    sig = np.where(positive, sig, np.median(sig[positive]) if positive.any() else 1.0)
    eps = np.where(good, eps, 0.0)
    basis = _smooth_basis(eps.size, good, lsts, sky_shapes)
    w = good / sig**2
    coef = np.linalg.lstsq((basis * np.sqrt(w)).T, eps * np.sqrt(w), rcond=None)[0]
    rough = np.where(good, eps - coef @ basis, 0.0)
    dof = max(int(good.sum()) - basis.shape[0], 1)
    chi2 = float(np.sum(w * rough**2))
    z = rough[good] / sig[good]
    lag1 = float(np.sum(z[1:] * z[:-1]) / np.sum(z * z)) if z.size > 2 and np.any(z) else 0.0
    centred = np.where(good, eps - np.sum(w * eps) / np.sum(w), 0.0)
    total_power = float(np.sum(w * centred**2))
    # the per-integration freedom beyond the smooth part must pay for itself as any
    # candidate does: Delta BIC of the rough part (its chi2 over the overdispersion, less
    # ln N per extra parameter) above the threshold
    rough_delta_bic = chi2 / max(overdispersion, 1.0) - dof * math.log(max(ndata, 2))
    return JitterTest(
        significant=bool(rough_delta_bic > BIC_THRESHOLD),
        rough_reduced_chi2=chi2 / dof,
        smooth_fraction=1.0 - chi2 / total_power if total_power > 0 else 0.0,
        lag1=lag1,
        rough_delta_bic=rough_delta_bic,
    )


def _smooth_basis(
    ntime: int, good: np.ndarray, lsts: np.ndarray, sky_shapes: np.ndarray | None
) -> np.ndarray:
    """Return the rows of the smooth part of a series: Legendre, diurnal and sky shapes."""
    rows = [np.ones(ntime)]
    order = min(JITTER_SMOOTH_ORDER, max(int(good.sum()) - 3, 0))
    if order:
        rows += list(time_basis(lsts, order))
    if np.ptp(unwrap_lsts(np.asarray(lsts, float))) >= DIURNAL_MIN_SPAN_H:
        # the catalogue's diurnal drifts are smooth too (a sidereal-day sine is not a
        # low-order polynomial over a day)
        rows += list(diurnal_basis(lsts, JITTER_DIURNAL_HARMONICS))
    if sky_shapes is not None:
        for shape in np.atleast_2d(sky_shapes):
            if np.all(np.isfinite(shape)) and np.ptp(shape) > 0:
                rows.append((shape - shape.mean()) / np.ptp(shape))
    basis = np.vstack(rows)
    return basis[: max(1, min(basis.shape[0], int(good.sum()) - 2))]


def sky_time_shapes(tpl: SkyTemplates) -> np.ndarray:
    """Return ``(3, Ntime)`` time shapes of the model sky.

    The band-averaged relative Tsky, its square and its time derivative: the templates a
    slightly wrong sky model leaves in a per-integration gain series.
    """
    rel = tpl.total / np.mean(tpl.total, axis=1, keepdims=True)  # (P, T, F)
    mean = rel.mean(axis=(0, 2))
    deriv = np.gradient(mean)
    return np.vstack([mean, mean**2, deriv])


def feed_departures_rough(
    feed: FeedGainFit, current: ExtendedFit, obs: Observation, tpl: SkyTemplates
) -> float:
    """Delta BIC of the rough part of each antenna-pol's departure from the common series.

    The test :func:`jitter_is_significant` applies to ``gain_jitter``, applied to every
    antenna-pol's series divided by the common one and summed over antenna-pols: what a
    smooth function of time explains (one antenna's gain drifting against the others) is
    not jitter. The remainders are judged against the scatter of the bulk of the
    antenna-pols' residuals (:attr:`.FeedGainFit.bulk_overdispersion`, a median), not their
    ``chi^2 / dof``, which a few outliers inflate.
    """
    shared = current.gain_factor / np.mean(current.gain_factor)
    shapes = sky_time_shapes(tpl)
    total = 0.0
    for ia in range(obs.nant):
        for ip in range(len(obs.pols)):
            test = jitter_is_significant(
                feed.factors[ia, ip] / shared - 1.0,
                feed.sigmas[ia, ip],
                obs.lsts,
                shapes,
                ndata=current.ndata,
                overdispersion=feed.bulk_overdispersion,
            )
            total += test.rough_delta_bic
    return float(total)
