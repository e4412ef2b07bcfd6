"""The compiled expectation of the delete-a-block jackknife covariance, channel by channel.

:func:`expected_jackknife` computes what
:func:`autocal.fit.total_uncertainty.expected_jackknife_numpy` does (see its notes for the
algebra) in one loop per channel, chunks of channels on threads
(:func:`autocal.fit.threads.in_threads`): the refit's normal matrix of
each left-out block is inverted in place (Gauss-Jordan: the matrices are positive definite)
and the products are sums over ``M`` terms, all in the sky-centred frame of
:mod:`autocal.fit.centring` with one ``c`` per channel (on a short span the normal matrices
are too ill-conditioned to invert to more than a few digits, and the covariance of ``(G,
n)`` to invert at all; that of ``(G, n + c G)`` is well conditioned). numpy's batched
``inv``, ``det`` and ``@`` on a million 2 x 2 systems (one 350-antenna HERA file) spend ~10
s in per-matrix overhead; this takes a fraction of a second. numba is imported with this
module, which :mod:`autocal.fit.total_uncertainty` imports only when it computes a total
uncertainty.
"""

from __future__ import annotations

import numba
import numpy as np

from autocal.fit.centring_kernel import centre_with_into
from autocal.fit.threads import in_threads


def expected_jackknife(
    a: np.ndarray, parts: list[np.ndarray], p: np.ndarray | None, proj: np.ndarray, c: np.ndarray
) -> np.ndarray:
    """Return the jackknife covariance of the projected parameters the statistics predict.

    Every matrix is taken to the sky-centred frame of the one ``c`` per channel (for the
    refits too, whatever block they leave out), so the result is the covariance of
    ``(G, n + c G)``: on a short span that of ``(G, n)`` has a condition number ~1e15 and
    its inverse (:func:`autocal.fit.total_uncertainty._jackknife_factor`) would keep no
    digit.

    Parameters
    ----------
    a
        ``(..., M, M)`` the normal matrices of the fit.
    parts
        The ``(..., M, M)`` normal matrices of each block (they sum to ``a``).
    p
        ``(..., M, M)`` the prior's rows (noiseless), or ``None``.
    proj
        ``(2, M)`` the projection onto the time-averaged ``(G, n)`` (``vg``, ``vn`` of
        :func:`autocal.fit.model.mean_vectors`: in the centred frame it gives ``(G, n + c
        G)``).
    c
        ``(...)`` the frame's sky mean per channel
        (:func:`autocal.fit.centring.sky_mean` of ``a``).

    Returns
    -------
    numpy.ndarray
        ``(..., 2, 2)`` the covariance of ``(G, n + c G)``; NaN where a refit's matrix is
        singular or not finite.
    """
    lead = a.shape[:-2]
    m = a.shape[-1]
    flat = np.ascontiguousarray(a, dtype=np.float64).reshape(-1, m, m)
    blocks = np.stack([np.asarray(b, dtype=np.float64).reshape(-1, m, m) for b in parts])
    prior = (
        np.zeros((1, m, m))
        if p is None
        else np.ascontiguousarray(np.broadcast_to(p, a.shape), dtype=np.float64).reshape(-1, m, m)
    )
    out = np.empty((flat.shape[0], 2, 2))
    proj = np.ascontiguousarray(proj, dtype=np.float64)
    sky = np.ascontiguousarray(np.broadcast_to(c, lead), dtype=np.float64).reshape(-1)
    nchunk = -(-flat.shape[0] // _CHUNK)
    in_threads(lambda c0, c1: _kernel(flat, blocks, prior, proj, sky, out, c0, c1), nchunk)
    return out.reshape(*lead, 2, 2)


@numba.njit(cache=True)
def invert_in_place(mat: np.ndarray, check: bool) -> bool:
    """Invert the small symmetric positive-definite matrix ``mat`` in place.

    Gauss-Jordan without pivoting (stable for positive-definite normal matrices; also the
    solver's, :mod:`autocal.fit.solve_kernel`, which checks the condition first and passes
    ``check=False``). With ``check``, returns ``False`` (``mat`` then undefined) at a pivot
    that is not positive and finite: a singular matrix.
    """
    m = mat.shape[0]
    for col in range(m):
        piv = mat[col, col]
        if check and not (piv > 0.0 and piv < np.inf):
            return False
        inv_p = 1.0 / piv
        mat[col, col] = 1.0
        for j in range(m):
            mat[col, j] *= inv_p
        for r in range(m):
            if r != col:
                f = mat[r, col]
                mat[r, col] = 0.0
                for j in range(m):
                    mat[r, j] -= f * mat[col, j]
    return True


@numba.njit(cache=True)
def _matmul(x: np.ndarray, y: np.ndarray, out: np.ndarray) -> None:
    """``out = x @ y`` for small matrices (explicit loops: no BLAS call per product)."""
    for i in range(x.shape[0]):
        for j in range(y.shape[1]):
            acc = 0.0
            for q in range(x.shape[1]):
                acc += x[i, q] * y[q, j]
            out[i, j] = acc


#: Channels per chunk of the loop (its scratch arrays are allocated once per chunk).
_CHUNK = 4096


@numba.njit(cache=True, nogil=True)
def _kernel(a, blocks, prior, proj, sky, out, c0, c1):  # type: ignore[no-untyped-def]
    """Fill ``out[n]`` for the channels of chunks ``c0`` to ``c1 - 1``.

    See :func:`expected_jackknife`.
    """
    nblk, nchan, m, _ = blocks.shape
    frac = (nblk - 1) / nblk
    for c in range(c0, c1):
        ysum = np.empty((2, m))
        cross = np.empty((2, m))  # sum_b Y_b A_b
        own = np.empty((2, 2))  # sum_b Y_b (A - A_b) Y_b^T
        same = np.empty((2, 2))  # sum_b Y_b A_b Y_b^T
        rest = np.empty((m, m))
        k = np.empty((m, m))
        ac = np.empty((m, m))  # a, sky-centred
        bc = np.empty((m, m))  # a block's matrix, sky-centred
        y = np.empty((2, m))
        ya = np.empty((2, m))
        yr = np.empty((2, m))
        for n in range(c * _CHUNK, min((c + 1) * _CHUNK, nchan)):
            pn = prior[0] if prior.shape[0] == 1 else prior[n]
            ysum[:] = 0.0
            cross[:] = 0.0
            own[:] = 0.0
            same[:] = 0.0
            ok = True
            cn = sky[n]
            centre_with_into(a[n], cn, ac)
            for b in range(nblk):
                for i in range(m):
                    for j in range(m):
                        rest[i, j] = a[n, i, j] - blocks[b, n, i, j] + pn[i, j]
                centre_with_into(rest, cn, k)  # inverted in the sky-centred frame
                if not invert_in_place(k, True):
                    ok = False
                    break
                centre_with_into(blocks[b, n], cn, bc)
                _matmul(proj, k, y)  # Y_b
                _matmul(y, bc, ya)  # Y_b A_b
                _matmul(y, ac, yr)
                for i in range(2):
                    for q in range(m):
                        yr[i, q] -= ya[i, q]  # Y_b (A - A_b)
                        ysum[i, q] += y[i, q]
                        cross[i, q] += ya[i, q]
                for i in range(2):
                    for j in range(2):
                        for q in range(m):
                            own[i, j] += yr[i, q] * y[j, q]
                            same[i, j] += ya[i, q] * y[j, q]
            if not ok:
                out[n] = np.nan
                continue
            _matmul(ysum, ac, yr)  # Ysum A
            for i in range(2):
                for j in range(2):
                    every = same[i, j]
                    for q in range(m):
                        every += (yr[i, q] - cross[i, q]) * ysum[j, q] - ysum[i, q] * cross[j, q]
                    out[n, i, j] = frac * (own[i, j] - every / nblk)
