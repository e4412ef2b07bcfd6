"""The compiled solver of every channel's normal equations, one channel at a time.

:func:`solve_channels` does what :func:`autocal.fit.solve.solve_sums_numpy` does (the
sky-centred frame of :mod:`autocal.fit.centring`, column scaling, a 2-norm condition number
from the eigenvalues and the centring's cancellation, the inverse, coefficients, ``chi^2``,
covariance scaling, the flag reasons) in one loop per channel, chunks of channels
on threads (:func:`autocal.fit.threads.in_threads`), with no temporaries: numpy's batched
linear algebra spends most of its time in per-matrix overhead on a HERA file's million small
systems (LAPACK ``inv`` and ``eigvalsh`` for 4 x 4 ones ~4 us each). Eigenvalues are in
closed form for 2 x 2 systems and by cyclic Jacobi rotations otherwise; the inverse is
Gauss-Jordan on the scaled, centred, positive-definite matrix. The constant model's
two-parameter systems go through an unrolled copy of the loop (:func:`_kernel2`: the same
operations in the same order, bit-identical; 0.108 s -> 0.050 s for 1.07 M channels on two
threads: ``python benchmarks/solve_kernel.py``; the identity is tested in
``tests/fit/test_solve.py``). Larger systems bound the condition number by
``||A||_inf ||A^-1||_inf`` (the inverse is needed anyway) and run the Jacobi sweeps only
near the limit: the same flags and bits, 0.863 s -> 0.271 s for 1.07 M four-parameter
systems. numba is imported with this
module, which :mod:`autocal.fit.solve` imports when it solves.
"""

from __future__ import annotations

import numba
import numpy as np

from autocal.fit.centring_kernel import (
    centre_into,
    centre_rhs_into,
    minus_product,
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
    kernel = _kernel2 if m == 2 else _kernel  # the constant model: unrolled, 3-4x faster
    in_threads(lambda c0, c1: kernel(*args, c0, c1), -(-n // _CHUNK))
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
#: :func:`_kernel` takes the bound ``||A||_inf ||A^-1||_inf`` (at most ``M`` times the
#: 2-norm condition) for the condition when it is this many times below the limit, and
#: computes the eigenvalues otherwise: the flags are those of the exact condition.
BOUND_MARGIN = 16.0


@numba.njit(cache=True)
def _inf_norm(a: np.ndarray) -> float:
    """Return the largest absolute row sum of ``a`` (NaN propagates)."""
    best = 0.0
    for i in range(a.shape[0]):
        acc = 0.0
        for j in range(a.shape[1]):
            acc += abs(a[i, j])
        if np.isnan(acc):
            return acc
        best = max(best, acc)
    return best


@numba.njit(cache=True, nogil=True)
def _kernel(
    ata,
    aty,
    yty,
    count,
    min_samples,
    scale_mode,
    max_condition,
    positive,
    co,
    cv,
    ch,
    rs,
    c0,
    c1,
    bound=True,
):  # type: ignore[no-untyped-def]
    """Solve the channels of chunks ``c0`` to ``c1 - 1`` (see :func:`solve_channels`).

    With ``bound`` (systems of more than two parameters), the condition is first bounded by
    ``||A||_inf ||A^-1||_inf`` and the eigenvalues computed only when that bound is within
    :data:`BOUND_MARGIN` of the limit: the same flags and bit-identical outputs as without
    (``tests/fit/test_solve.py``), 3.2x faster for a Legendre-1 fit's 4 x 4 systems
    (``python benchmarks/solve_kernel.py``).
    """
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
            inverted = False
            if ok:
                # an upper bound first: cond_2 <= ||A||_inf ||A^-1||_inf for a symmetric A;
                # far below the limit it decides as the eigenvalues would, and the inverse
                # is needed anyway (the Jacobi sweeps cost ~3/4 of a 4 x 4 system's time)
                cond = -1.0
                for k in range(m):
                    for j in range(m):
                        work[k, j] = scaled[k, j]
                if bound and m > 2 and invert_in_place(work, True):
                    estimate = _inf_norm(scaled) * _inf_norm(work)
                    if estimate < max_condition / BOUND_MARGIN:
                        cond = estimate
                        inverted = True
                if cond < 0.0:  # near the limit or singular: the exact 2-norm condition
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
            if inverted:  # the same operations on a copy: the same inverse
                for k in range(m):
                    for j in range(m):
                        scaled[k, j] = work[k, j]
            else:
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


@numba.njit(cache=True, nogil=True)
def _kernel2(
    ata, aty, yty, count, min_samples, scale_mode, max_condition, positive, co, cv, ch, rs, c0, c1
):  # type: ignore[no-untyped-def]
    """:func:`_kernel` for two parameters ``(G, n)``, unrolled.

    The same floating-point operations in the same order as :func:`_kernel` with
    ``M = 2`` (the centring, the scaling, the closed-form eigenvalues, Gauss-Jordan and the
    uncentring written out), so the results are bit-identical
    (``tests/fit/test_solve.py``); without the loops over a run-time size and the scratch
    arrays, a HERA file's million channels solve 3-4x faster.
    """
    n = aty.shape[0]
    for c in range(c0, c1):
        for i in range(c * _CHUNK, min((c + 1) * _CHUNK, n)):
            reason = _TOO_FEW if count[i] < min_samples else 0
            a00, a01, a10, a11 = ata[i, 0, 0], ata[i, 0, 1], ata[i, 1, 0], ata[i, 1, 1]
            sky = a01 / a11 if a11 != 0.0 else 0.0  # centre_into
            if not np.isfinite(sky):
                sky = 0.0
            t00 = minus_product(a00, sky, a01)
            t10 = minus_product(a10, sky, a11)
            e00 = minus_product(t00, sky, t10)
            e01 = minus_product(a01, sky, a11)
            e10 = e01
            e11 = a11
            r0 = minus_product(aty[i, 0], sky, aty[i, 1])  # centre_rhs_into
            r1 = aty[i, 1]
            ok = reason == 0
            ok = ok and e00 > 0.0
            d0 = np.sqrt(e00) if e00 > 0.0 else 1.0
            ok = ok and e11 > 0.0
            d1 = np.sqrt(e11) if e11 > 0.0 else 1.0
            s00 = e00 / (d0 * d0)
            s01 = e01 / (d0 * d1)
            s10 = e10 / (d1 * d0)
            s11 = e11 / (d1 * d1)
            ok = ok and np.isfinite(s00) and np.isfinite(s01)
            ok = ok and np.isfinite(s10) and np.isfinite(s11)
            if reason == 0 and not ok:
                reason = _SINGULAR
            if ok:
                mean = (s00 + s11) / 2  # _eig_extremes, closed form
                radius = np.hypot((s00 - s11) / 2, s10)
                lo, hi = abs(mean - radius), abs(mean + radius)
                lo, hi = min(lo, hi), max(lo, hi)
                cond = hi / lo if lo > 0.0 else np.inf
                cond = max(cond, 4.0 * a00 / e00)  # the digits the centring cancelled
                if not (cond < max_condition):  # NaN or too large
                    reason = _SINGULAR
                    ok = False
            if not ok:
                _flagged(i, reason, co, cv, ch, rs)
                continue
            inv_p = 1.0 / s00  # invert_in_place, column 0
            s00 = 1.0
            s00 *= inv_p
            s01 *= inv_p
            f = s10
            s10 = 0.0
            s10 -= f * s00
            s11 -= f * s01
            inv_p = 1.0 / s11  # column 1
            s11 = 1.0
            s10 *= inv_p
            s11 *= inv_p
            f = s01
            s01 = 0.0
            s00 -= f * s10
            s01 -= f * s11
            s00 = s00 / (d0 * d0)  # the centred covariance, and x row by row
            s01 = s01 / (d0 * d1)
            acc = 0.0
            acc += s00 * r0
            acc += s01 * r1
            x0 = acc
            s10 = s10 / (d1 * d0)
            s11 = s11 / (d1 * d1)
            acc = 0.0
            acc += s10 * r0
            acc += s11 * r1
            x1 = acc
            fit = 0.0  # x^T (b + r), r = b - A x
            acc = 0.0
            acc += e00 * x0
            acc += e01 * x1
            fit += x0 * (r0 + (r0 - acc))
            acc = 0.0
            acc += e10 * x0
            acc += e11 * x1
            fit += x1 * (r1 + (r1 - acc))
            co[i, 0] = x0  # uncentre_into
            co[i, 1] = minus_product(x1, sky, x0)
            c10 = s10 - sky * s00  # uncentre_cov_into: rows, then columns
            c11 = s11 - sky * s01
            c01 = s01 - sky * s00
            c11 = c11 - sky * c10
            cv[i, 0, 0] = s00
            cv[i, 0, 1] = c01
            cv[i, 1, 0] = c10
            cv[i, 1, 1] = c11
            chi2 = max(yty[i] - fit, 0.0)
            if scale_mode != 0:
                dof = count[i] - 2
                factor = chi2 / dof if dof > 0 else np.nan
                if scale_mode == 2:
                    factor = 1.0 if not np.isfinite(factor) else max(factor, 1.0)
                cv[i, 0, 0] *= factor
                cv[i, 0, 1] *= factor
                cv[i, 1, 0] *= factor
                cv[i, 1, 1] *= factor
            if positive and not (co[i, 0] > 0.0):
                _flagged(i, _NON_POSITIVE, co, cv, ch, rs)
                continue
            ch[i] = chi2
            rs[i] = 0
