"""The sky-centred parametrisation in which the solvers work: a congruence of the normal sums.

Per channel the design has gain columns ``Tsky P_k`` and offset columns ``P_k`` (gain
coefficients first, then as many offset coefficients: :class:`autocal.fit.model.FitModel`'s
layout). Over a short span the sky changes by ~1 % of its mean, so ``Tsky P_k`` is nearly
``c P_k`` and the column-scaled normal matrix of the model with one more time order has a
condition number ~1e11 on a 10-minute HERA file: a solve loses ~11 of 16 digits. With ``c``
the weighted time mean of ``Tsky`` (``A[0, nb] / A[nb, nb]``, from the sums themselves) the
columns ``(Tsky - c) P_k`` and ``P_k`` are nearly orthogonal. That is the substitution
``x = S x'``, ``S`` the identity with ``-c`` at ``(nb + k, k)`` (the offsets ``n_k = n'_k -
c g_k``, the gains unchanged), i.e. the congruence ``A' = S^T A S``, ``b' = S^T b``; then
``x = S x'``, ``cov = S cov' S^T`` and ``chi^2`` is unchanged.

Forming ``A'`` from ``A`` cancels: its gain block is ``sum w (Tsky - c)^2 ...``, ~1e-4 of
``sum w Tsky^2`` at 1 % sky variation. Each product ``c * a`` is therefore formed exactly
(Dekker's two-product, :func:`minus_product`), so that only the subtraction rounds: ``A'`` is
then as exact, relative to its own entries, as ``A`` is to its entries (with an ordinary
product the rounding of ``c * a``, ``eps |A|``, would cost the digits the congruence
saves; compilers do not fuse it into a multiply-add for us, and numpy's products may or may
not). The scalar functions here are plain arithmetic: numpy applies them to arrays (the
reference solver, :mod:`autocal.fit.solve`) and the compiled kernels
(:mod:`autocal.fit.centring_kernel`, used by :mod:`autocal.fit.solve_kernel` and
:mod:`autocal.fit.jackknife_kernel`) compile them.

The sums are stored, added and passed (Dask partials, block sums) in the original
parametrisation; only the solvers change frames.
"""

from __future__ import annotations

import numpy as np

#: Veltkamp's splitting constant ``2^27 + 1`` for float64 (53-bit significands).
_SPLIT = 134217729.0


def minus_product(x, c, y):  # type: ignore[no-untyped-def]
    """Return ``x - c * y`` with the product exact, so that only the subtraction rounds.

    Dekker's two-product (``c * y = p + e`` exactly, by Veltkamp's splitting) for
    float64 scalars or arrays, barring overflow (``|c|, |y| < ~1e300``). Non-finite inputs
    give non-finite results.
    """
    p = c * y
    t = _SPLIT * c
    ch = t - (t - c)
    cl = c - ch
    t = _SPLIT * y
    yh = t - (t - y)
    yl = y - yh
    e = ((ch * yh - p) + ch * yl + cl * yh) + cl * yl
    return (x - p) - e


def sky_mean(ata: np.ndarray) -> np.ndarray:
    """Return ``c = A[0, nb] / A[nb, nb]`` (the weighted time mean of ``Tsky``) per system.

    ``ata`` is ``(..., M, M)``; ``c`` is 0 (no change of frame) where it is not finite.
    """
    nb = ata.shape[-1] // 2
    with np.errstate(divide="ignore", invalid="ignore"):
        c = ata[..., 0, nb] / ata[..., nb, nb]
    return np.where(np.isfinite(c), c, 0.0)


def centre(ata: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Return the symmetric ``A' = S^T A S`` of ``(..., M, M)`` normal matrices.

    Columns first (``B = A S``), then the gain rows (``S^T B``); the upper triangle is kept
    and mirrored, as :mod:`autocal.fit.centring_kernel` does it, so both give the same bits.
    """
    nb = ata.shape[-1] // 2
    cc = np.asarray(c, dtype=np.float64)[..., None, None]
    cols = ata.copy()
    cols[..., :, :nb] = minus_product(ata[..., :, :nb], cc, ata[..., :, nb:])
    rows = cols.copy()
    rows[..., :nb, :] = minus_product(cols[..., :nb, :], cc, cols[..., nb:, :])
    return np.triu(rows) + np.swapaxes(np.triu(rows, 1), -1, -2)


def centre_rhs(aty: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Return ``b' = S^T b`` of ``(..., M)`` right-hand sides."""
    nb = aty.shape[-1] // 2
    rhs = aty.copy()
    rhs[..., :nb] = minus_product(
        aty[..., :nb], np.asarray(c, np.float64)[..., None], aty[..., nb:]
    )
    return rhs


def uncentre(coeffs: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Return ``x = S x'`` of ``(..., M)`` solutions: the offsets ``n_k = n'_k - c g_k``."""
    nb = coeffs.shape[-1] // 2
    x = coeffs.copy()
    x[..., nb:] = minus_product(
        coeffs[..., nb:], np.asarray(c, np.float64)[..., None], coeffs[..., :nb]
    )
    return x


def uncentre_cov(cov: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Return ``S C' S^T`` of ``(..., M, M)`` covariances (or inverses): rows, then columns."""
    nb = cov.shape[-1] // 2
    cc = np.asarray(c, dtype=np.float64)[..., None, None]
    rows = cov.copy()
    rows[..., nb:, :] = cov[..., nb:, :] - cc * cov[..., :nb, :]
    out = rows.copy()
    out[..., :, nb:] = rows[..., :, nb:] - cc * rows[..., :, :nb]
    return out


def cancellation_bound(ata: np.ndarray, centred: np.ndarray) -> np.ndarray:
    """Return ``max_k 4 A[k, k] / A'[k, k]`` over the gain columns (inf if one is not positive).

    How much of each gain column's weight was the sky's mean: forming ``A'[k, k]`` cancels
    all but ``4 / factor`` of ``A[k, k]``, so its rounding, ``eps A[k, k]``, is this factor
    over 4 times ``eps A'[k, k]``. For ``k = 0`` (``A'[0, 0] / A[0, 0] = 1 - r^2``, ``r``
    the correlation of the columns ``Tsky`` and ``1``) it is also an upper bound of the
    condition number ``(1 + |r|) / (1 - |r|)`` of that scaled pair of columns, equal to it
    as they near collinearity: for the constant model (where ``A'`` is diagonal) the solvers
    flag the same channels as from the original matrix's condition number.
    """
    nb = ata.shape[-1] // 2
    orig = np.diagonal(ata, axis1=-2, axis2=-1)[..., :nb]
    kept = np.diagonal(centred, axis1=-2, axis2=-1)[..., :nb]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(kept > 0, 4.0 * orig / np.where(kept > 0, kept, 1.0), np.inf)
    return ratio.max(axis=-1)


def quadratic_form(v: np.ndarray, ata: np.ndarray) -> np.ndarray:
    """Return ``v^T A v`` of ``(..., M)`` vectors and ``(..., M, M)`` matrices, sky-centred.

    Evaluated as ``v'^T A' v'`` with ``v' = S^-1 v`` (the offsets ``n'_k = n_k + c g_k``,
    the product exact): for ``v`` near the null direction of an ill-conditioned ``A`` the
    plain form is a sum of terms far larger than itself.
    """
    nb = v.shape[-1] // 2
    c = sky_mean(ata)
    vc = v.copy()
    vc[..., nb:] = minus_product(v[..., nb:], -c[..., None], v[..., :nb])
    return np.einsum("...i,...ij,...j->...", vc, centre(ata, c), vc)
