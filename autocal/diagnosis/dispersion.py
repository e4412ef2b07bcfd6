"""The overdispersion of a fit from the bulk of its residuals (robust to a few outliers).

:func:`robust_overdispersion` is the ``chi^2 / dof`` that the bulk of the data shows: the
median squared normalised residual over that of a chi-square variable with one degree of
freedom. The tests of per-integration gain series (:mod:`autocal.diagnosis.jitter`) and of
the antenna-pols' own fits (:mod:`autocal.diagnosis.feeds`) divide by it, so that a few
strong outliers (RFI not yet flagged, on the first search) do not decide their verdicts.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
from scipy import stats

from autocal.diagnosis.extended_fit import ExtendedFit, residual_pieces

#: Median of a chi-square variable with one degree of freedom.
CHI2_1_MEDIAN = float(stats.chi2.ppf(0.5, 1))

#: Residuals :func:`robust_overdispersion` takes the median of, at most (about).
ROBUST_SAMPLES = 1 << 22


def fit_nchunks(fit: Any) -> int:
    """Return the number of antenna chunks a fit streams its residuals in (1 for arrays)."""
    source = getattr(fit, "source", None)
    return len(source.chunks) if source is not None else 1


def squared_residual_sample(
    fit: ExtendedFit | Any, max_samples: int = ROBUST_SAMPLES
) -> np.ndarray:
    """Return a regular subsample (about ``max_samples``) of a fit's squared residuals.

    A whole HERA file has 2e8 residuals; the stride is chosen prime to the channel count, so
    that the subsample is not a comb of the same channels.
    """
    squares = []
    for _, res in residual_pieces(fit):
        flat = np.asarray(res).ravel()
        stride = max(1, flat.size * max(1, fit_nchunks(fit)) // max(1, max_samples))
        while stride > 1 and math.gcd(stride, np.shape(res)[-1]) != 1:
            stride += 1
        sub = flat[::stride]
        squares.append(sub[np.isfinite(sub)] ** 2)
    return np.concatenate(squares) if squares else np.zeros(0)


def robust_overdispersion(fit: ExtendedFit | Any) -> float:
    """Return the fit's overdispersion from the median squared normalised residual.

    ``median(r^2) / 0.455`` (the median of chi-square with one degree of freedom): the
    scatter of the bulk of the data, which a few strong outliers (RFI not yet flagged, on
    the first search) do not inflate as they inflate ``chi^2 / dof``. ``chi^2 / dof`` when
    the fit has no finite residual.
    """
    values = squared_residual_sample(fit)
    if not values.size:
        return float(fit.reduced_chi2)
    return float(np.median(values) / CHI2_1_MEDIAN)


def pooled_overdispersion(samples: Iterable[np.ndarray], fallback: float) -> float:
    """Return the robust overdispersion of several fits' squared residuals pooled.

    ``samples``: :func:`squared_residual_sample` of each fit. ``fallback`` when there is no
    finite residual at all.
    """
    values = [np.asarray(s, float) for s in samples]
    pooled = np.concatenate(values) if values else np.zeros(0)
    if not pooled.size:
        return float(fallback)
    return float(np.median(pooled) / CHI2_1_MEDIAN)
