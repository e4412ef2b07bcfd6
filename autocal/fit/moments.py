"""Normal-equation sums as weighted time moments, and the numpy engine that computes them.

With the design row ``a_t = (T_t b_0(t) .. T_t b_p(t), b_0(t) .. b_p(t))`` (``b_k = P_k(s)``,
or 1 for the constant model) every normal-equation sum is a weighted time moment::

    ata[j, k] = sum_t w T^2 b_j b_k,   ata[j, K + k] = sum_t w T b_j b_k,
    ata[K + j, K + k] = sum_t w b_j b_k,   aty[k] = sum_t w y T b_k,   aty[K + k] = sum_t w y b_k

and ``b_j b_k = sum_r L[j, k, r] P_r`` (Legendre linearisation, ``r <= 2p``). So per sample
only the ``3 (2p + 1)`` moments ``sum_t w T^e P_r`` (``e = 0, 1, 2``), the ``2 (p + 1)``
moments ``sum_t w y T^e P_k`` (``e = 0, 1``), ``sum_t w y^2`` and the count are needed, and
the full design ``(Nant, Npol, Ntime, Nfreq, 2 (p + 1))`` array never exists. Two engines
compute them: a fused numba kernel (:mod:`autocal.fit.kernels`: one pass over the data,
compiled per model order and weight kind) and the numpy fallback here
(:func:`moments_numpy`: antenna blocks, matrix products over time). Both read a
:class:`Chunk`, which :func:`autocal.fit.sums.accumulate` builds: weights laid out by
:func:`num_array`, rows placed off each other's cache sets by :func:`offset_copy`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.polynomial import legendre

from autocal.fit.model import FitError, FitModel


def time_functions(model: FitModel, lsts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the moment functions ``(R, Ntime)`` and the linearisation ``(K, K, R)``.

    ``coef[r] = P_r(s(t))`` for ``r = 0 .. 2p`` (ones for the constant model) and
    ``basis_j basis_k = sum_r lin[j, k, r] coef[r]``; the first ``K = p + 1`` rows of
    ``coef`` are the model's basis.
    """
    nb = model.nbasis
    nr = 2 * model.order + 1
    if model.kind == "constant":
        coef = np.ones((1, np.size(lsts)))
    else:
        coef = legendre.legvander(model.s(lsts), nr - 1).T
    lin = np.zeros((nb, nb, nr))
    for j in range(nb):
        for k in range(nb):
            prod = legendre.legmul(np.eye(nb)[j], np.eye(nb)[k])
            lin[j, k, : prod.size] = prod
    return np.ascontiguousarray(coef), lin


def _assemble(lin: np.ndarray, mom: np.ndarray, ymom: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Build the normal matrix and right-hand side from the moments.

    Parameters
    ----------
    lin
        ``(K, K, R)`` linearisation from :func:`time_functions`.
    mom
        ``(..., 3, R)``: ``sum_t w T^e P_r``.
    ymom
        ``(..., 2, K)``: ``sum_t w y T^e P_k``.
    """
    nb = lin.shape[0]
    blocks = np.einsum("jkr,...er->...ejk", lin, mom)  # (..., 3, K, K)
    ata = np.empty((*mom.shape[:-2], 2 * nb, 2 * nb))
    ata[..., :nb, :nb] = blocks[..., 2, :, :]
    ata[..., :nb, nb:] = blocks[..., 1, :, :]
    ata[..., nb:, :nb] = blocks[..., 1, :, :]
    ata[..., nb:, nb:] = blocks[..., 0, :, :]
    aty = np.concatenate([ymom[..., 1, :], ymom[..., 0, :]], axis=-1)
    return ata, aty


@dataclass
class Chunk:
    """Validated inputs of :func:`autocal.fit.sums.accumulate` in the layout the engines read."""

    data: np.ndarray  # (A, P, T, F) float64, C order
    flags: np.ndarray  # (A, P, T, F) uint8, C order (0 = usable)
    mode: str  # identity | radiometer | user
    num: np.ndarray | float  # radiometer dnu dt N, or user 1/sigma^2 (array or scalar)
    power: np.ndarray | None  # radiometer reference power (None: the data)
    tsky: np.ndarray  # (P, T, F) float64
    coef: np.ndarray  # (R, T)
    lin: np.ndarray  # (K, K, R)


def num_array(values: Any, data: np.ndarray) -> np.ndarray | float:
    """Return per-sample ``dnu dt N`` or user weights in the layout the engines read.

    A scalar stays a float; values that vary only with frequency (uniform ``nsamples`` and
    integration time: what the pipeline passes for raw files) become one ``(Nfreq,)`` row,
    which stays in the L1 cache while the kernel streams the data; values that vary only
    with time and frequency one ``(Ntime, Nfreq)`` array shared by all antennas and
    polarisations, so the kernel reads 8 bytes per sample less; anything else a C-ordered
    float64 array of the data's shape.
    """
    arr = np.asarray(values, dtype=np.float64)
    if arr.size == 1:
        return float(arr.reshape(-1)[0])
    try:
        ok = np.broadcast_shapes(arr.shape, data.shape) == data.shape
    except ValueError:
        ok = False
    if not ok:
        raise FitError(f"weights of shape {arr.shape} do not broadcast to the data's {data.shape}")
    if all(n == 1 for n in arr.shape[:-2]):
        shared = np.broadcast_to(
            arr.reshape(arr.shape[-2:]) if arr.ndim >= 2 else arr, data.shape[2:]
        )
        if (shared == shared[:1]).all():  # the same for every integration (NaN never is)
            return offset_copy(shared[0], data, 3072)
        return offset_copy(shared, data, 3072)
    return np.ascontiguousarray(np.broadcast_to(arr, data.shape))


def offset_copy(arr: np.ndarray, other: np.ndarray, shift: int = 2048) -> np.ndarray:
    """Copy ``arr`` (C order, float64) to an address ``shift`` bytes after ``other``'s mod 4 kB.

    Rows of the two arrays at equal indices then fall in different L1 cache sets.
    """
    buf = np.empty(arr.size + 512)
    target = (other.ctypes.data + shift) % 4096
    start = ((target - buf.ctypes.data) % 4096) // 8
    out = buf[start : start + arr.size].reshape(arr.shape)
    out[...] = arr
    return out


def moments_numpy(c: Chunk, a0: int, a1: int, out: dict[str, np.ndarray]) -> int:
    """Fill ``out[...][a0:a1]`` with numpy; return the number of invalid user weights.

    One antenna at a time with preallocated ``(Npol, Ntime, Nfreq)`` buffers (no page
    faults, cache-sized operands); the time moments are matrix products with ``coef``.
    """
    shape = c.data.shape[1:]
    w, y, tmp = np.empty(shape), np.empty(shape), np.empty(shape)
    used, mask, valid = np.empty(shape, bool), np.empty(shape, bool), np.empty(shape, bool)
    nb = c.lin.shape[0]
    cw, cwk, tt = c.coef, c.coef[:nb], c.tsky
    per_sample = np.ndim(c.num) == 4
    nbad = 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for a in range(a0, a1):
            d = c.data[a]
            num = c.num[a] if per_sample else c.num  # type: ignore[index]
            np.isfinite(d, out=used)
            np.equal(c.flags[a], 0, out=mask)
            used &= mask
            if c.mode == "identity":
                np.copyto(w, used)
            elif c.mode == "radiometer":
                power = d if c.power is None else c.power[a]
                np.multiply(power, power, out=tmp)
                np.divide(num, tmp, out=w)
                used &= np.greater(w, 0.0, out=mask)
                used &= np.less(w, np.inf, out=mask)
                np.copyto(w, 0.0, where=np.logical_not(used, out=mask))
            else:
                np.copyto(w, num)
                np.greater_equal(w, 0.0, out=mask)
                mask &= np.less(w, np.inf, out=valid)
                nbad += int(np.count_nonzero(used & ~mask))
                np.copyto(w, 0.0, where=np.logical_not(used, out=mask))
                np.greater(w, 0.0, out=used)
            np.copyto(y, d)
            np.copyto(y, 0.0, where=np.logical_not(used, out=mask))
            mom = np.empty((*shape[::2], 3, cw.shape[0]))  # (P, F, 3, R)
            ymom = np.empty((*shape[::2], 2, nb))
            mom[..., 0, :] = np.swapaxes(cw @ w, -1, -2)
            np.multiply(w, tt, out=tmp)
            mom[..., 1, :] = np.swapaxes(cw @ tmp, -1, -2)
            tmp *= tt
            mom[..., 2, :] = np.swapaxes(cw @ tmp, -1, -2)
            w *= y  # w y
            ymom[..., 0, :] = np.swapaxes(cwk @ w, -1, -2)
            out["yty"][a] += np.einsum("ptf,ptf->pf", w, y)
            np.multiply(w, tt, out=tmp)
            ymom[..., 1, :] = np.swapaxes(cwk @ tmp, -1, -2)
            ata, aty = _assemble(c.lin, mom, ymom)
            out["ata"][a] += ata
            out["aty"][a] += aty
            count = np.count_nonzero(used, axis=1)
            out["count"][a] += count
            out["nflagged"][a] += shape[1] - count
    return nbad
