"""The compiled solver of every channel's normal equations, one channel at a time.

:func:`solve_channels` does what :func:`autocal.fit.solve.solve_sums_numpy` does (the
sky-centred frame of :mod:`autocal.fit.centring`, column scaling, a 2-norm condition number
from the eigenvalues and the centring's cancellation, the inverse, coefficients, ``chi^2``,
covariance scaling, the flag reasons) in one loop per channel, chunks of channels
on threads (:func:`autocal.fit.threads.in_threads`), with no temporaries: numpy's batched
linear algebra spends most of its time in per-matrix overhead on a HERA file's million small
systems (LAPACK ``inv`` and ``eigvalsh`` for 4 x 4 ones ~4 us each). Eigenvalues are in
closed form for 2 x 2 systems and by cyclic Jacobi rotations otherwise; the inverse is
Gauss-Jordan on the scaled, centred, positive-definite matrix. numba is imported with this module,
which :mod:`autocal.fit.solve` imports when it solves.
"""

from __future__ import annotations

import numba
import numpy as np

from autocal.fit.centring_kernel import (
    centre_into,
    centre_rhs_into,
    uncentre_cov_into,
    uncentre_into,
)
from autocal.fit.jackknife_kernel import invert_in_place
from autocal.fit.threads import in_threads

#: Flag reason codes (as :data:`autocal.fit.solve.FLAG_REASONS`).
_TOO_FEW, _SINGULAR, _NON_POSITIVE = 1, 2, 3


def solve_channels(
    ata: np.ndarray,
    aty: np.ndarray,
    yty: np.ndarray,
    count: np.ndarray,
    min_samples: int,
    scale_mode: int,
    max_condition: float,
    positive_gain: bool,
) -> dict[str, np.ndarray]:
    """Solve ``(N, M, M)`` normal systems.

    ``scale_mode``: 0 no covariance scaling, 1 times ``chi^2 / dof``, 2 times
    ``max(1, chi^2 / dof)``. Returns ``coeffs``, ``cov``, ``chi2``, ``flag_reason`` as
    :func:`autocal.fit.solve.solve_sums` documents (``dof`` is the caller's).
    """
    n, m = aty.shape
    out = {
        "coeffs": np.empty((n, m)),
        "cov": np.empty((n, m, m)),
        "chi2": np.empty(n),
        "flag_reason": np.zeros(n, np.int8),
    }
    args = (
        np.ascontiguousarray(ata, dtype=np.float64),
        np.ascontiguousarray(aty, dtype=np.float64),
        np.ascontiguousarray(yty, dtype=np.float64),
        np.ascontiguousarray(count),
        int(min_samples),
        int(scale_mode),
        float(max_condition),
        bool(positive_gain),
        out["coeffs"],
        out["cov"],
        out["chi2"],
        out["flag_reason"],
    )
    in_threads(lambda c0, c1: _kernel(*args, c0, c1), -(-n // _CHUNK))
    return out


@numba.njit(cache=True)
def _eig_extremes(a: np.ndarray, work: np.ndarray) -> tuple[float, float]:
    """Return the smallest and largest ``|eigenvalue|`` of the symmetric matrix ``a``."""
    m = a.shape[0]
    if m == 1:
        return abs(a[0, 0]), abs(a[0, 0])
    if m == 2:  # closed form, as autocal.fit.solve.sym_eigvalsh
        mean = (a[0, 0] + a[1, 1]) / 2
        radius = np.hypot((a[0, 0] - a[1, 1]) / 2, a[1, 0])
        lo, hi = abs(mean - radius), abs(mean + radius)
        return min(lo, hi), max(lo, hi)
    for i in range(m):
        for j in range(m):
            work[i, j] = a[i, j]
    for _ in range(64):  # cyclic Jacobi sweeps
        off = 0.0
        diag = 0.0
        for i in range(m):
            diag += work[i, i] * work[i, i]
            for j in range(i + 1, m):
                off += work[i, j] * work[i, j]
        if off <= 1e-32 * diag:
            break
        for p in range(m - 1):
            for q in range(p + 1, m):
                apq = work[p, q]
                if apq == 0.0:
                    continue
                theta = (work[q, q] - work[p, p]) / (2.0 * apq)
                t = np.sign(theta) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                if theta == 0.0:
                    t = 1.0
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(m):  # columns p, q
                    akp, akq = work[k, p], work[k, q]
                    work[k, p] = c * akp - s * akq
                    work[k, q] = s * akp + c * akq
                for k in range(m):  # rows p, q
                    apk, aqk = work[p, k], work[q, k]
                    work[p, k] = c * apk - s * aqk
                    work[q, k] = s * apk + c * aqk
    lo = np.inf
    hi = 0.0
    for i in range(m):
        v = abs(work[i, i])
        lo = min(lo, v)
        hi = max(hi, v)
    return lo, hi


#: Channels per chunk of the loop (its scratch arrays are allocated once per chunk).
_CHUNK = 4096


@numba.njit(cache=True, nogil=True)
def _kernel(
    ata, aty, yty, count, min_samples, scale_mode, max_condition, positive, co, cv, ch, rs, c0, c1
):  # type: ignore[no-untyped-def]
    """Solve the channels of chunks ``c0`` to ``c1 - 1`` (see :func:`solve_channels`)."""
    n, m = aty.shape
    nb = m // 2
    for c in range(c0, c1):
        centred = np.empty((m, m))
        scaled = np.empty((m, m))
        work = np.empty((m, m))
        rhs = np.empty(m)
        x = np.empty(m)
        d = np.empty(m)
        for i in range(c * _CHUNK, min((c + 1) * _CHUNK, n)):
            reason = _TOO_FEW if count[i] < min_samples else 0
            sky = centre_into(ata[i], centred)
            centre_rhs_into(aty[i], sky, rhs)
            ok = reason == 0
            for k in range(m):
                dk = centred[k, k]
                ok = ok and dk > 0.0
                d[k] = np.sqrt(dk) if dk > 0.0 else 1.0
            for k in range(m):
                for j in range(m):
                    scaled[k, j] = centred[k, j] / (d[k] * d[j])
                    ok = ok and np.isfinite(scaled[k, j])
            if reason == 0 and not ok:
                reason = _SINGULAR
            if ok:
                lo, hi = _eig_extremes(scaled, work)
                cond = hi / lo if lo > 0.0 else np.inf
                for k in range(nb):  # the digits the centring cancelled
                    cond = max(cond, 4.0 * ata[i, k, k] / centred[k, k])
                if not (cond < max_condition):  # NaN or too large
                    reason = _SINGULAR
                    ok = False
            if not ok:
                _flagged(i, reason, co, cv, ch, rs)
                continue
            invert_in_place(scaled, False)  # the condition number was checked above
            for k in range(m):
                acc = 0.0
                for j in range(m):
                    scaled[k, j] = scaled[k, j] / (d[k] * d[j])  # the centred covariance
                for j in range(m):
                    acc += scaled[k, j] * rhs[j]
                x[k] = acc
            fit = 0.0  # x^T (b + r), r = b - A x: chi2 stationary in x (solve._chi2)
            for k in range(m):
                acc = 0.0
                for j in range(m):
                    acc += centred[k, j] * x[j]
                fit += x[k] * (rhs[k] + (rhs[k] - acc))
            uncentre_into(x, sky, co[i])
            uncentre_cov_into(scaled, sky, cv[i])
            chi2 = max(yty[i] - fit, 0.0)
            if scale_mode != 0:
                dof = count[i] - m
                factor = chi2 / dof if dof > 0 else np.nan
                if scale_mode == 2:
                    factor = 1.0 if not np.isfinite(factor) else max(factor, 1.0)
                for k in range(m):
                    for j in range(m):
                        cv[i, k, j] *= factor
            if positive and not (co[i, 0] > 0.0):
                _flagged(i, _NON_POSITIVE, co, cv, ch, rs)
                continue
            ch[i] = chi2
            rs[i] = 0


@numba.njit(cache=True)
def _flagged(i, reason, co, cv, ch, rs):  # type: ignore[no-untyped-def]
    """Mark channel ``i`` flagged for ``reason``: NaN coefficients, covariance and chi2."""
    co[i, :] = np.nan
    cv[i, :, :] = np.nan
    ch[i] = np.nan
    rs[i] = reason
