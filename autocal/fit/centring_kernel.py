"""The sky-centred frame of :mod:`autocal.fit.centring`, compiled for one channel's system.

The same operations in the same order as the numpy functions there (columns, then the gain
rows, the upper triangle mirrored; rows, then columns back), on one ``(M, M)`` system into
scratch arrays, for the compiled solver (:mod:`autocal.fit.solve_kernel`) and the expected
jackknife (:mod:`autocal.fit.jackknife_kernel`). numba is imported with this module.
"""

from __future__ import annotations

import numba
import numpy as np

from autocal.fit.centring import minus_product as _minus_product_py

#: Compiled :func:`autocal.fit.centring.minus_product` (the same arithmetic).
minus_product = numba.njit(cache=True)(_minus_product_py)

#: The same as a ufunc over arrays (broadcasting as numpy's): the same arithmetic and bits
#: as the numpy function, without its dozen temporaries (0.45 s -> 0.02 s for the
#: jackknife's five refits of a HERA-size file's million channels).
minus_product_array = numba.vectorize(["float64(float64, float64, float64)"], cache=True)(
    _minus_product_py
)


@numba.njit(cache=True, nogil=True)
def _centre_many(a: np.ndarray, c: np.ndarray, out: np.ndarray) -> None:
    for i in range(a.shape[0]):
        centre_with_into(a[i], c[i], out[i])


def centre_many(ata: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Return :func:`autocal.fit.centring.centre` of ``(..., M, M)`` matrices, compiled.

    One system at a time into the output (the numpy function makes five copies of the
    matrices); the same operations, so the same bits (signed zeros included).
    """
    m = ata.shape[-1]
    lead = ata.shape[:-2]
    flat = np.ascontiguousarray(ata, dtype=np.float64).reshape(-1, m, m)
    cf = np.ascontiguousarray(np.broadcast_to(np.asarray(c, np.float64), lead)).reshape(-1)
    out = np.empty_like(flat)
    _centre_many(flat, cf, out)
    out += 0.0  # numpy's centre adds a zero to every element as it mirrors: -0.0 -> 0.0
    return out.reshape(ata.shape)


@numba.njit(cache=True)
def centre_into(a: np.ndarray, out: np.ndarray) -> float:
    """Fill ``out = S^T a S`` (:func:`autocal.fit.centring.centre`) and return ``c``.

    ``c = a[0, nb] / a[nb, nb]`` (0 where not finite: no change of frame).
    """
    nb = a.shape[0] // 2
    c = a[0, nb] / a[nb, nb] if a[nb, nb] != 0.0 else 0.0  # (numba raises on / 0)
    if not np.isfinite(c):
        c = 0.0
    centre_with_into(a, c, out)
    return c


@numba.njit(cache=True)
def centre_with_into(a: np.ndarray, c: float, out: np.ndarray) -> None:
    """Fill ``out = S^T a S`` for a given ``c`` (:func:`autocal.fit.centring.centre`)."""
    m = a.shape[0]
    nb = m // 2
    for r in range(m):
        for k in range(nb):
            out[r, k] = minus_product(a[r, k], c, a[r, nb + k])
        for k in range(nb, m):
            out[r, k] = a[r, k]
    for k in range(nb):
        for j in range(k, m):  # the gain rows' upper triangle (the offset rows are final)
            out[k, j] = minus_product(out[k, j], c, out[nb + k, j])
    for k in range(m):
        for j in range(k):
            out[k, j] = out[j, k]


@numba.njit(cache=True)
def centre_rhs_into(b: np.ndarray, c: float, rhs: np.ndarray) -> None:
    """Fill ``rhs = S^T b`` (:func:`autocal.fit.centring.centre_rhs`)."""
    nb = b.shape[0] // 2
    for k in range(nb):
        rhs[k] = minus_product(b[k], c, b[nb + k])
        rhs[nb + k] = b[nb + k]


@numba.njit(cache=True)
def uncentre_into(xc: np.ndarray, c: float, x: np.ndarray) -> None:
    """Fill ``x = S xc`` (:func:`autocal.fit.centring.uncentre`)."""
    nb = xc.shape[0] // 2
    for k in range(nb):
        x[k] = xc[k]
        x[nb + k] = minus_product(xc[nb + k], c, xc[k])


@numba.njit(cache=True)
def uncentre_cov_into(covc: np.ndarray, c: float, cov: np.ndarray) -> None:
    """Fill ``cov = S covc S^T`` (:func:`autocal.fit.centring.uncentre_cov`); may be ``covc``."""
    m = covc.shape[0]
    nb = m // 2
    for k in range(m):
        for j in range(m):
            cov[k, j] = covc[k, j]
    for k in range(nb):  # rows, then columns
        for j in range(m):
            cov[nb + k, j] = cov[nb + k, j] - c * cov[k, j]
    for j in range(m):
        for k in range(nb):
            cov[j, nb + k] = cov[j, nb + k] - c * cov[j, k]


@numba.njit(cache=True)
def _quadratic_forms_into(v: np.ndarray, a: np.ndarray, out: np.ndarray) -> None:
    n, m = v.shape
    nb = m // 2
    ac = np.empty((m, m))
    vc = np.empty(m)
    for i in range(n):
        c = a[i, 0, nb] / a[i, nb, nb] if a[i, nb, nb] != 0.0 else 0.0
        if not np.isfinite(c):
            c = 0.0
        centre_with_into(a[i], c, ac)
        for k in range(nb):
            vc[k] = v[i, k]
            vc[nb + k] = minus_product(v[i, nb + k], -c, v[i, k])
        total = 0.0
        for r in range(m):
            row = 0.0
            for j in range(m):
                row += ac[r, j] * vc[j]
            total += vc[r] * row
        out[i] = total


def quadratic_forms(v: np.ndarray, ata: np.ndarray) -> np.ndarray:
    """Return ``v^T A v`` of ``(..., M)`` vectors and ``(..., M, M)`` matrices, sky-centred.

    :func:`autocal.fit.centring.quadratic_form` one system at a time into scratch arrays
    (the numpy function forms every centred matrix at once: ~5 copies of ``ata``, 0.68 GB
    for the drift model of a whole HERA file); the same frame and products, the sums in
    another order, so equal to rounding.
    """
    m = v.shape[-1]
    flat_v = np.ascontiguousarray(v, dtype=np.float64).reshape(-1, m)
    flat_a = np.ascontiguousarray(ata, dtype=np.float64).reshape(-1, m, m)
    if flat_a.shape != (flat_v.shape[0], m, m):
        raise ValueError(f"{v.shape} vectors and {ata.shape} matrices do not match")
    out = np.empty(flat_v.shape[0])
    _quadratic_forms_into(flat_v, flat_a, out)
    return out.reshape(v.shape[:-1])
