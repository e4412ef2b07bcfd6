"""Fit receiver gain and noise to auto-correlations against a Tsky model.

Per antenna, polarisation and channel the data are ``R(t) = G(t) Tsky(t) + n(t)`` with

- the *constant* model: ``G(t) = G``, ``n(t) = n`` (parameters ``x = (G, n)``);
- the *Legendre* model of order ``p``: ``G(t) = sum_k g_k P_k(s)``, ``n(t) = sum_k n_k
  P_k(s)``, ``s`` the LST mapped linearly onto ``[-1, 1]`` over the model's LST range
  (``x = (g_0..g_p, n_0..n_p)``; order 1 is the paper's ``G0 + G1 t``).

The generalised least-squares solution ``x = (A^T W A)^-1 A^T W y`` with ``C_x = (A^T W
A)^-1`` is computed from *normal-equation sums* (:class:`NormalSums`) accumulated chunk by
chunk, so a night never sits in memory and sums from several workers simply add. All
channels, antennas and polarisations are solved at once with batched numpy linear algebra.

Weights ``W``:

- ``"radiometer"``: ``sigma = R / sqrt(dnu dt N)`` (radiometer equation; ``dnu`` channel
  width, ``dt`` integration time, ``N`` the sample count). The first pass uses the data
  for ``R``; later passes (``iterations``) use the fitted model, which removes the small
  bias that data-derived weights carry (``-2 sigma_R^2 / R^2`` relative, see the tests).
- ``"identity"``: unit weights (what the paper used on real data). The covariance is then
  scaled by ``chi^2 / dof`` (the residual variance), the usual OLS estimate.
- an array of inverse variances ``1 / sigma^2`` broadcastable to the data.

Flagged and non-finite samples get zero weight and are counted. A channel with too few
samples, a singular normal matrix or a non-positive gain is flagged with its reason and
its values set to NaN, never filled.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.polynomial import legendre

from autocal.core.observation import Observation
from autocal.core.user_cache import user_cache_dir
from autocal.errors import AutocalError

if TYPE_CHECKING:
    from autocal.fit.uncertainty import TotalUncertainty

logger = logging.getLogger(__name__)

#: Reasons a channel is flagged by the fit (``Solution.flag_reason`` codes).
FLAG_REASONS: dict[int, str] = {
    0: "ok",
    1: "too few unflagged samples",
    2: "singular normal matrix",
    3: "non-positive gain",
}
#: Largest condition number of the (column-scaled) normal matrix accepted as solvable.
MAX_CONDITION = 1e12


class FitError(AutocalError):
    """Invalid fit input."""


# the time model -------------------------------------------------------------------------


def unwrap_lsts(lsts: np.ndarray) -> np.ndarray:
    """Return LSTs (hours, in time order) made continuous across the 24 h wrap."""
    lsts = np.asarray(lsts, dtype=np.float64)
    return np.unwrap(lsts * (2 * np.pi / 24.0)) * (24.0 / (2 * np.pi))


@dataclass(frozen=True)
class FitModel:
    """Which model to fit.

    Parameters
    ----------
    kind
        ``"constant"`` or ``"legendre"``.
    order
        Legendre order ``p`` (0 for the constant model).
    lst_start, lst_span
        The LST (hours) mapped to ``s = -1`` and the span (hours) mapped to ``s = 2``;
        set from the data by :meth:`for_lsts`. Unused by the constant model.
    """

    kind: Literal["constant", "legendre"] = "constant"
    order: int = 0
    lst_start: float = 0.0
    lst_span: float = 24.0

    def __post_init__(self) -> None:
        if self.kind not in ("constant", "legendre"):
            raise FitError(f"unknown model {self.kind!r}: use 'constant' or 'legendre'")
        if self.kind == "constant" and self.order != 0:
            raise FitError("the constant model has order 0; use kind='legendre' for order > 0")
        if not 0 <= self.order <= 20:
            raise FitError(f"Legendre order must be in 0..20, got {self.order}")
        if not (np.isfinite(self.lst_span) and self.lst_span > 0):
            raise FitError("the model's LST span must be positive")

    @classmethod
    def for_lsts(cls, lsts: np.ndarray, kind: str = "constant", order: int = 0) -> FitModel:
        """Build a model whose time axis spans the given LSTs (hours, time order)."""
        un = unwrap_lsts(lsts)
        span = float(un.max() - un.min())
        if kind == "legendre" and order > 0 and span <= 0:
            raise FitError("a time-dependent model needs data at more than one LST")
        return cls(kind, order, float(un.min() % 24.0), span if span > 0 else 24.0)  # type: ignore[arg-type]

    @property
    def nbasis(self) -> int:
        """Number of time basis functions ``p + 1``."""
        return self.order + 1

    @property
    def nparam(self) -> int:
        """Number of parameters per channel ``2 (p + 1)``."""
        return 2 * self.nbasis

    @property
    def param_names(self) -> tuple[str, ...]:
        """``("G", "n")`` or ``("g_0", .., "g_p", "n_0", .., "n_p")``."""
        if self.kind == "constant":
            return ("G", "n")
        k = range(self.nbasis)
        return tuple(f"g_{i}" for i in k) + tuple(f"n_{i}" for i in k)

    def s(self, lsts: np.ndarray) -> np.ndarray:
        """Map LSTs (hours) onto the model's ``[-1, 1]`` coordinate."""
        offset = (np.asarray(lsts, dtype=np.float64) - self.lst_start) % 24.0
        # An LST outside a span shorter than a day is put on the nearer side of it
        # (before the start: s < -1; after the end: s > 1).
        if self.lst_span < 24.0:
            offset = np.where(
                offset > self.lst_span + (24.0 - self.lst_span) / 2, offset - 24, offset
            )
        return 2.0 * offset / self.lst_span - 1.0

    def basis(self, lsts: np.ndarray) -> np.ndarray:
        """Return ``(nbasis, Ntime)`` Legendre polynomials ``P_k(s(t))``."""
        if self.kind == "constant":
            return np.ones((1, np.size(lsts)))
        return legendre.legvander(self.s(lsts), self.order).T

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description."""
        return {
            "kind": self.kind,
            "order": self.order,
            "lst_start_h": self.lst_start,
            "lst_span_h": self.lst_span,
            "parameters": list(self.param_names),
        }


def design(model: FitModel, tsky: np.ndarray, lsts: np.ndarray) -> np.ndarray:
    """Return the design features ``(Npol, Nfreq, Ntime, nparam)``.

    Parameters
    ----------
    model
        The fit model.
    tsky
        ``(Npol, Ntime, Nfreq)`` (or ``(Ntime, Nfreq)``) model sky temperature in kelvin.
    lsts
        ``(Ntime,)`` hours.
    """
    tsky = np.asarray(tsky, dtype=np.float64)
    if tsky.ndim == 2:
        tsky = tsky[None]
    basis = model.basis(lsts)  # (K, T)
    tt = np.swapaxes(tsky, 1, 2)  # (P, F, T)
    gain_part = tt[..., None] * basis.T[None, None]  # (P, F, T, K)
    noise_part = np.broadcast_to(basis.T[None, None], gain_part.shape)
    return np.concatenate([gain_part, noise_part], axis=-1)


# normal-equation sums -------------------------------------------------------------------


@dataclass
class NormalSums:
    """Sufficient statistics of the weighted least-squares problem per channel.

    Arrays have leading axes ``(Nant, Npol, Nfreq)``; sums over time of ``w a a^T``
    (``ata``), ``w a y`` (``aty``), ``w y^2`` (``yty``), the number of used samples
    (``count``) and of excluded (flagged or non-finite) samples (``nflagged``). Two sums
    over disjoint sets of integrations add with ``+``.
    """

    model: FitModel
    ata: np.ndarray
    aty: np.ndarray
    yty: np.ndarray
    count: np.ndarray
    nflagged: np.ndarray
    lst_min: float = np.inf
    lst_max: float = -np.inf
    info: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        from autocal.core.reprs import compact_repr

        return compact_repr(self)

    @classmethod
    def zeros(cls, model: FitModel, nant: int, npol: int, nfreq: int) -> NormalSums:
        """Empty sums."""
        m = model.nparam
        lead = (nant, npol, nfreq)
        return cls(
            model,
            np.zeros((*lead, m, m)),
            np.zeros((*lead, m)),
            np.zeros(lead),
            np.zeros(lead, np.int64),
            np.zeros(lead, np.int64),
        )

    def __iadd__(self, other: NormalSums) -> NormalSums:
        """Add ``other`` into these sums in place (the same values as ``self + other``)."""
        if self.model != other.model or self.ata.shape != other.ata.shape:
            return self + other  # raises the FitError that explains the mismatch
        self.ata += other.ata
        self.aty += other.aty
        self.yty += other.yty
        self.count += other.count
        self.nflagged += other.nflagged
        self.lst_min = min(self.lst_min, other.lst_min)
        self.lst_max = max(self.lst_max, other.lst_max)
        self.info.update(other.info)
        return self

    def __add__(self, other: NormalSums) -> NormalSums:
        if self.model != other.model:
            raise FitError("cannot add normal sums of different models")
        if self.ata.shape != other.ata.shape:
            raise FitError(f"cannot add normal sums of shapes {self.ata.shape}, {other.ata.shape}")
        return NormalSums(
            self.model,
            self.ata + other.ata,
            self.aty + other.aty,
            self.yty + other.yty,
            self.count + other.count,
            self.nflagged + other.nflagged,
            min(self.lst_min, other.lst_min),
            max(self.lst_max, other.lst_max),
            {**self.info, **other.info},
        )


def _check_tsky(tsky: np.ndarray, npol: int, ntime: int, nfreq: int) -> np.ndarray:
    tsky = np.asarray(tsky, dtype=np.float64)
    if tsky.ndim == 2:
        tsky = np.broadcast_to(tsky[None], (npol, *tsky.shape))
    if tsky.shape != (npol, ntime, nfreq):
        raise FitError(
            f"Tsky has shape {tsky.shape}; expected (Npol, Ntime, Nfreq) = "
            f"{(npol, ntime, nfreq)} or (Ntime, Nfreq)"
        )
    if not np.all(np.isfinite(tsky)):
        raise FitError("the Tsky model has non-finite values")
    return tsky


def weights_for(
    weights: str | np.ndarray,
    data: np.ndarray,
    usable: np.ndarray,
    bandwidth_time: np.ndarray | float | None,
    reference: np.ndarray | None = None,
) -> np.ndarray:
    """Return inverse-variance weights (zero where not usable).

    Parameters
    ----------
    weights
        ``"radiometer"``, ``"identity"`` or an array of ``1 / sigma^2``.
    data
        ``(Nant, Npol, Ntime, Nfreq)`` auto-correlations.
    usable
        Boolean mask of samples to use.
    bandwidth_time
        ``dnu dt N`` per sample (radiometer weights only).
    reference
        Power used in the radiometer equation instead of the data (e.g. a model).
    """
    if isinstance(weights, str):
        if weights == "identity":
            return usable.astype(np.float64)
        if weights == "radiometer":
            if bandwidth_time is None:
                raise FitError("radiometer weights need the channel width and integration time")
            power = data if reference is None else reference
            bt = np.broadcast_to(np.asarray(bandwidth_time, np.float64), data.shape)
            with np.errstate(divide="ignore", invalid="ignore"):
                w = bt / power**2
            ok = usable & np.isfinite(w) & (w > 0)
            return np.where(ok, w, 0.0)
        raise FitError(
            f"unknown weights {weights!r}: use 'radiometer', 'identity' or an array of 1/sigma^2"
        )
    w = np.broadcast_to(np.asarray(weights, np.float64), data.shape)
    if np.any(w[usable] < 0) or not np.all(np.isfinite(w[usable])):
        raise FitError("user weights (1/sigma^2) must be finite and >= 0")
    return np.where(usable, w, 0.0)


# moment-based accumulation ----------------------------------------------------------------
#
# With the design row a_t = (T_t b_0(t) .. T_t b_p(t), b_0(t) .. b_p(t)) (b_k = P_k(s), or 1
# for the constant model) every normal-equation sum is a weighted time moment:
#
#   ata[j, k] = sum_t w T^2 b_j b_k,   ata[j, K + k] = sum_t w T b_j b_k,
#   ata[K + j, K + k] = sum_t w b_j b_k,   aty[k] = sum_t w y T b_k,   aty[K + k] = sum_t w y b_k
#
# and b_j b_k = sum_r L[j, k, r] P_r (Legendre linearisation, r <= 2p). So per sample only
# the 3 (2p + 1) moments sum_t w T^e P_r (e = 0, 1, 2), the 2 (p + 1) moments
# sum_t w y T^e P_k (e = 0, 1), sum_t w y^2 and the count are needed, and the full design
# (Nant, Npol, Ntime, Nfreq, 2 (p + 1)) array never exists. Two engines compute them: a
# fused numba kernel (one pass over the data, compiled per model order and weight kind) and
# a numpy fallback (antenna blocks, matrix products over time).

#: Antenna-block engines: ``"numba"`` (fused compiled kernel), ``"numpy"`` or ``"auto"``.
Engine = Literal["auto", "numba", "numpy"]
#: Smallest chunk (samples) for which ``engine="auto"`` compiles a numba kernel; smaller
#: chunks use numpy unless a matching kernel is already compiled.
NUMBA_MIN_SAMPLES = 1 << 22


def _time_functions(model: FitModel, lsts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
        ``(K, K, R)`` linearisation from :func:`_time_functions`.
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
class _Chunk:
    """Validated inputs of :func:`accumulate` in the layout the engines read."""

    data: np.ndarray  # (A, P, T, F) float64, C order
    flags: np.ndarray  # (A, P, T, F) uint8, C order (0 = usable)
    mode: str  # identity | radiometer | user
    num: np.ndarray | float  # radiometer dnu dt N, or user 1/sigma^2 (array or scalar)
    power: np.ndarray | None  # radiometer reference power (None: the data)
    tsky: np.ndarray  # (P, T, F) float64
    coef: np.ndarray  # (R, T)
    lin: np.ndarray  # (K, K, R)


def _num_array(values: Any, data: np.ndarray) -> np.ndarray | float:
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
            return _offset_copy(shared[0], data, 3072)
        return _offset_copy(shared, data, 3072)
    return np.ascontiguousarray(np.broadcast_to(arr, data.shape))


def _offset_copy(arr: np.ndarray, other: np.ndarray, shift: int = 2048) -> np.ndarray:
    """Copy ``arr`` (C order, float64) to an address ``shift`` bytes after ``other``'s mod 4 kB.

    Rows of the two arrays at equal indices then fall in different L1 cache sets.
    """
    buf = np.empty(arr.size + 512)
    target = (other.ctypes.data + shift) % 4096
    start = ((target - buf.ctypes.data) % 4096) // 8
    out = buf[start : start + arr.size].reshape(arr.shape)
    out[...] = arr
    return out


def _moments_numpy(c: _Chunk, a0: int, a1: int, out: dict[str, np.ndarray]) -> int:
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


#: Integrations handled per pass of the compiled kernel's channel loop, by the number of
#: chunk-sized arrays it reads per sample (data, dnu dt N or user weights, reference power):
#: with Nfreq a multiple of 512 (HERA: 1536) every row of these starts at the same offset
#: modulo 4 kB (large arrays are page-aligned alike), so the rows read together compete for
#: one 8-way L1 set; at most 8 of them may be in flight. Tsky is copied to another offset
#: (:func:`_offset_copy`) and the kernel places its accumulators off that set too.
_TUNROLL = {1: 4, 2: 4, 3: 2}
#: Bytes of accumulators per channel block: a block has as many channels (a multiple of 256,
#: 256 to 1536) as keep its ``3 (2p + 1) + 2 (p + 1) + 2`` accumulator rows within this, so
#: they stay in the L2 cache; a longer block reads a longer stretch of each data row per pass,
#: which the hardware prefetcher streams faster (constant model: 1536 channels, Legendre 1:
#: 768, Legendre 2: 512; ``benchmarks/fit.py``).
_BLOCK_BYTES = 96 * 1024
_KERNELS: dict[tuple[Any, ...], Any] = {}
_KERNEL_LOCK = threading.Lock()


def _numba_available() -> bool:
    try:
        import numba  # noqa: F401
    except ImportError:  # pragma: no cover - numba is optional
        return False
    return True


def _kernel_key(c: _Chunk) -> tuple[Any, ...]:
    nb, _, nr = c.lin.shape
    num_dims = np.ndim(c.num)  # 0 scalar, 1 (Nfreq,) / 2 (Ntime, Nfreq) shared, 4 per sample
    nbig = 1 + (num_dims == 4) + (c.power is not None)
    nacc = 3 * nr + 2 * nb + 2 + (c.mode == "user")
    fb = int(np.clip(_BLOCK_BYTES // (8 * nacc) // 256 * 256, 256, 1536))
    return (nr, nb, c.mode, num_dims, c.power is None, c.lin.tobytes(), _TUNROLL[nbig], fb)


def _kernel_source(key: tuple[Any, ...], lin: np.ndarray) -> str:
    """Python source of the fused moment kernel for one model order and weight kind.

    The channel loop is straight-line code over scalar accumulators (one per moment, kept in
    a flat block with a constant row stride so LLVM vectorises it over channels without
    aliasing checks between rows), unrolled over ``_TUNROLL`` integrations.
    """
    nr, nb, mode, num_dims, own_power, _, tu, fb = key
    fbp = fb + 8  # pad rows so they do not share cache sets
    names = [f"m{e}_{r}" for e in range(3) for r in range(nr)]
    names += [f"q{e}_{k}" for e in range(2) for k in range(nb)]
    names += ["yy", "cn"] + (["bd"] if mode == "user" else [])
    src = [
        "def kernel(data, flags, num, power, tsky, coef, a_start, a_stop, ata, aty, yty, "
        "count, nflagged, bad):",
        "    npol, ntime, nfreq = data.shape[1], data.shape[2], data.shape[3]",
        # the accumulator rows start one cache line after the data rows modulo 4 kB, so
        # they never share an L1 set with the data (see _TUNROLL)
        f"    buf = np.empty({len(names) * fbp + 512})",
        "    off = ((np.int64(data.ctypes.data) + 64 - np.int64(buf.ctypes.data)) % 4096) // 8",
        f"    acc = buf[off : off + {len(names) * fbp}]",
        "    for ia in range(a_start, a_stop):",
        "        nbad = 0.0",
        "        for p in range(npol):",
        f"            for f0 in range(0, nfreq, {fb}):",
        f"                nf = min({fb}, nfreq - f0)",
        "                acc[:] = 0.0",
        f"                for tb in range(0, ntime, {tu}):",
    ]
    ind = " " * 20
    for u in range(tu):
        src += [
            f"{ind}t{u} = min(tb + {u}, ntime - 1)",
            f"{ind}v{u} = tb + {u} < ntime",
            f"{ind}d{u} = data[ia, p, t{u}, f0:f0 + nf]",
            f"{ind}g{u} = flags[ia, p, t{u}, f0:f0 + nf]",
            f"{ind}s{u} = tsky[p, t{u}, f0:f0 + nf]",
        ]
        if mode != "identity" and num_dims:
            lead = {1: "", 2: f"t{u}, ", 4: f"ia, p, t{u}, "}[num_dims]
            src.append(f"{ind}n{u} = num[{lead}f0:f0 + nf]")
        if mode == "radiometer" and not own_power:
            src.append(f"{ind}w{u} = power[ia, p, t{u}, f0:f0 + nf]")
        src += [f"{ind}c{u}_{r} = coef[{r}, t{u}]" for r in range(1, nr)]
    src.append(f"{ind}for j in range(nf):")
    ind = " " * 24
    src += [f"{ind}{n} = acc[{i * fbp} + j]" for i, n in enumerate(names)]
    for u in range(tu):
        src += [f"{ind}x = d{u}[j]", f"{ind}ok = (x - x == 0.0) & (g{u}[j] == 0) & v{u}"]
        numer = f"n{u}[j]" if num_dims else "num"
        if mode == "identity":
            src.append(f"{ind}w = 1.0")
        elif mode == "radiometer":
            pw = "x" if own_power else f"w{u}[j]"
            src += [
                f"{ind}pw = {pw}",
                f"{ind}w = {numer} / (pw * pw)",
                f"{ind}ok = ok & (w > 0.0) & (w < np.inf)",
            ]
        else:
            src += [
                f"{ind}w = {numer}",
                f"{ind}bd += 0.0 if (w >= 0.0) & (w < np.inf) else (1.0 if ok else 0.0)",
                f"{ind}ok = ok & (w > 0.0)",
            ]
        src += [
            f"{ind}w = w if ok else 0.0",
            f"{ind}y = x if ok else 0.0",
            f"{ind}cn += 1.0 if ok else 0.0",
            f"{ind}ts = s{u}[j]",
            f"{ind}x1 = w * ts",
            f"{ind}x2 = x1 * ts",
            f"{ind}x3 = w * y",
            f"{ind}x4 = x3 * ts",
            f"{ind}yy += x3 * y",
        ]
        # P_0 = 1: the r = 0 moments are plain sums (adds, off the FMA pipes)
        feats = ("w", "x1", "x2")
        src += [f"{ind}m{e}_0 += {feats[e]}" for e in range(3)]
        src += [f"{ind}m{e}_{r} += c{u}_{r} * {feats[e]}" for e in range(3) for r in range(1, nr)]
        yfeats = ("x3", "x4")
        src += [f"{ind}q{e}_0 += {yfeats[e]}" for e in range(2)]
        src += [f"{ind}q{e}_{k} += c{u}_{k} * {yfeats[e]}" for e in range(2) for k in range(1, nb)]
    src += [f"{ind}acc[{i * fbp} + j] = {n}" for i, n in enumerate(names)]
    # write the normal matrix of each channel of the block
    ind = " " * 16
    src.append(f"{ind}for j in range(nf):")
    ind = " " * 20
    src.append(f"{ind}f = f0 + j")
    src += [f"{ind}{n} = acc[{i * fbp} + j]" for i, n in enumerate(names)]

    def comb(e: int, j: int, k: int) -> str:
        terms = [
            f"m{e}_{r}" if lin[j, k, r] == 1.0 else f"{lin[j, k, r]!r} * m{e}_{r}"
            for r in range(nr)
            if lin[j, k, r] != 0.0
        ]
        return " + ".join(terms) if terms else "0.0"

    for j in range(nb):
        for k in range(nb):
            src += [
                f"{ind}ata[ia, p, f, {j}, {k}] += {comb(2, j, k)}",
                f"{ind}ata[ia, p, f, {j}, {nb + k}] += {comb(1, j, k)}",
                f"{ind}ata[ia, p, f, {nb + j}, {k}] += {comb(1, j, k)}",
                f"{ind}ata[ia, p, f, {nb + j}, {nb + k}] += {comb(0, j, k)}",
            ]
    for k in range(nb):
        src += [f"{ind}aty[ia, p, f, {k}] += q1_{k}", f"{ind}aty[ia, p, f, {nb + k}] += q0_{k}"]
    src += [
        f"{ind}yty[ia, p, f] += yy",
        f"{ind}count[ia, p, f] += np.int64(cn)",
        f"{ind}nflagged[ia, p, f] += ntime - np.int64(cn)",
    ]
    if mode == "user":
        src.append(f"{ind}nbad += bd")
    src.append("        bad[ia] = nbad")
    return "\n".join(src) + "\n"


_KERNEL_HEADER = (
    '"""Generated by autocal.fit.lsq._kernel_source; safe to delete."""\n\n'
    "import numba\nimport numpy as np\n\n\n"
    "@numba.njit(cache=True, nogil=True, fastmath={'contract'}, boundscheck=False, "
    "error_model='numpy')\n"
)


def kernel_cache_dir() -> Path | None:
    """Return the folder of the compiled fit kernels, or ``None`` when caching is off.

    ``AUTOCAL_KERNEL_CACHE`` (``off`` disables), else ``$XDG_CACHE_HOME/autocal/fit_kernels``
    (default ``~/.cache/autocal/fit_kernels``). Each kernel is a generated module there
    whose machine code numba caches next to it, so a process does not recompile it.
    """
    return user_cache_dir("AUTOCAL_KERNEL_CACHE", "fit_kernels")


def _load_kernel(source: str) -> Any:
    """Compile a kernel's source, through the on-disk cache when it is usable."""
    import numba

    text = _KERNEL_HEADER + source
    name = "autocal_fit_kernel_" + hashlib.sha256(text.encode()).hexdigest()[:20]
    folder = kernel_cache_dir()
    if folder is not None:
        path = folder / f"{name}.py"
        try:
            if not path.is_file() or path.read_text() != text:
                folder.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix(f".{os.getpid()}.tmp")
                tmp.write_text(text)
                os.replace(tmp, path)
            spec = importlib.util.spec_from_file_location(name, path)
            if spec is not None and spec.loader is not None:
                module = importlib.util.module_from_spec(spec)
                sys.modules[name] = module  # numba's cache re-imports it by name
                spec.loader.exec_module(module)
                return module.kernel
        except OSError as err:
            logger.info("not caching the fit kernel in %s: %s", folder, err)
    namespace: dict[str, Any] = {"np": np}
    exec(compile(source, f"<{name}>", "exec"), namespace)
    return numba.njit(nogil=True, fastmath={"contract"}, boundscheck=False, error_model="numpy")(
        namespace["kernel"]
    )


def _kernel(c: _Chunk) -> Any:
    """Return the compiled kernel for this chunk's order and weight kind (built on first use)."""
    key = _kernel_key(c)
    with _KERNEL_LOCK:
        if key not in _KERNELS:
            logger.debug("loading the fit kernel for %s", key[:5])
            _KERNELS[key] = _load_kernel(_kernel_source(key, c.lin))
        return _KERNELS[key]


def _moments_numba(c: _Chunk, a0: int, a1: int, out: dict[str, np.ndarray]) -> int:
    """Fill ``out[...][a0:a1]`` with the compiled kernel; return the invalid user weights."""
    power = c.data if c.power is None else c.power
    _kernel(c)(
        c.data,
        c.flags,
        c.num,
        power,
        c.tsky,
        c.coef,
        a0,
        a1,
        out["ata"],
        out["aty"],
        out["yty"],
        out["count"],
        out["nflagged"],
        out["bad"],
    )
    return int(out["bad"][a0:a1].sum())


def _default_threads() -> int:
    """Return the default thread count of :func:`accumulate`.

    ``AUTOCAL_FIT_THREADS``, else ``OMP_NUM_THREADS`` (Dask workers set it to 1), else the
    usable CPUs (at most 8).
    """
    for var in ("AUTOCAL_FIT_THREADS", "OMP_NUM_THREADS"):
        value = os.environ.get(var, "").strip()
        if value.isdigit() and int(value) > 0:
            return int(value)
    try:
        ncpu = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        ncpu = os.cpu_count() or 1
    return max(1, min(ncpu, 8))


def _choose_engine(engine: str | None, c: _Chunk) -> str:
    engine = engine or os.environ.get("AUTOCAL_FIT_ENGINE", "auto")
    if engine not in ("auto", "numba", "numpy"):
        raise FitError(f"unknown fit engine {engine!r}: use 'auto', 'numba' or 'numpy'")
    if engine == "numpy":
        return "numpy"
    if not _numba_available():
        if engine == "numba":
            raise FitError("the numba fit engine needs the numba package")
        return "numpy"
    if engine == "numba" or c.data.size >= NUMBA_MIN_SAMPLES or _kernel_key(c) in _KERNELS:
        return "numba"
    return "numpy"


def _antenna_blocks(nant: int, size: int) -> list[tuple[int, int]]:
    size = max(1, size)
    return [(a, min(a + size, nant)) for a in range(0, nant, size)]


def accumulate(
    model: FitModel,
    data: np.ndarray,
    tsky: np.ndarray,
    lsts: np.ndarray,
    *,
    flags: np.ndarray | None = None,
    weights: str | np.ndarray = "radiometer",
    bandwidth_time: np.ndarray | float | None = None,
    reference: np.ndarray | None = None,
    engine: Engine | None = None,
    threads: int | None = None,
    into: NormalSums | None = None,
) -> NormalSums:
    """Accumulate the normal-equation sums of one chunk of integrations.

    Only weighted time moments of the data are computed (see the comment above
    :func:`_time_functions`), in one pass over the chunk; the design matrix is never built.

    Parameters
    ----------
    model
        The fit model (its LST range must cover the whole fit, not just this chunk).
    data
        ``(Nant, Npol, Ntime, Nfreq)`` auto-correlations.
    tsky
        ``(Npol, Ntime, Nfreq)`` or ``(Ntime, Nfreq)`` model Tsky in kelvin.
    lsts
        ``(Ntime,)`` hours.
    flags
        Boolean flags like ``data`` (``True`` excludes the sample).
    weights
        See :func:`weights_for`.
    bandwidth_time
        ``dnu dt N`` for radiometer weights.
    reference
        Model power for the radiometer weights (second and later passes).
    engine
        ``"numba"`` (fused compiled kernel), ``"numpy"``, or ``"auto"`` (default, or the
        ``AUTOCAL_FIT_ENGINE`` environment variable): numba when it is installed and the
        chunk has at least :data:`NUMBA_MIN_SAMPLES` samples or a matching kernel is
        already compiled. Both give the same sums to rounding.
    threads
        Threads over antenna blocks (default: ``AUTOCAL_FIT_THREADS``, else
        ``OMP_NUM_THREADS``, else the usable CPUs, at most 8).
    into
        Running sums of the same model and shape to add this chunk's sums to, in place
        (the same values as ``into + accumulate(...)``, without a new set of arrays per
        chunk and a separate addition: for a Legendre-2 model the sums of a 7-integration
        block are 5x its data). On an error ``into`` may be partly updated.

    Returns
    -------
    NormalSums
        The chunk's sums, or ``into`` with them added.
    """
    data = np.ascontiguousarray(data, dtype=np.float64)
    if data.ndim != 4:
        raise FitError(f"data must be (Nant, Npol, Ntime, Nfreq), got shape {data.shape}")
    nant, npol, ntime, nfreq = data.shape
    if data.size == 0:
        raise FitError(
            f"nothing to fit: the chunk has shape {data.shape} (antennas, pols, integrations, "
            "channels); select at least one of each"
        )
    lsts = np.asarray(lsts, dtype=np.float64)
    if lsts.shape != (ntime,):
        raise FitError(f"{lsts.size} LSTs for {ntime} integrations")
    tsky = _offset_copy(_check_tsky(tsky, npol, ntime, nfreq), data)
    if flags is None:
        flag_bytes = np.zeros(data.shape, np.uint8)
    else:
        flag_bytes = np.ascontiguousarray(
            np.broadcast_to(np.asarray(flags, dtype=bool), data.shape)
        ).view(np.uint8)
    power = None
    num: np.ndarray | float = 0.0
    if isinstance(weights, str):
        if weights == "radiometer":
            if bandwidth_time is None:
                raise FitError("radiometer weights need the channel width and integration time")
            num = _num_array(bandwidth_time, data)
            if reference is not None:
                power = np.ascontiguousarray(
                    np.broadcast_to(np.asarray(reference, dtype=np.float64), data.shape)
                )
        elif weights != "identity":
            raise FitError(
                f"unknown weights {weights!r}: use 'radiometer', 'identity' or an array of "
                "1/sigma^2"
            )
        mode = weights
    else:
        mode = "user"
        num = _num_array(weights, data)
    coef, lin = _time_functions(model, lsts)
    chunk = _Chunk(data, flag_bytes, mode, num, power, tsky, coef, lin)
    lead = (nant, npol, nfreq)
    out = NormalSums.zeros(model, *lead) if into is None else into  # the engines add to it
    _check_into(out, model, lead)
    bufs = {
        "ata": out.ata,
        "aty": out.aty,
        "yty": out.yty,
        "count": out.count,
        "nflagged": out.nflagged,
        "bad": np.zeros(nant),
    }
    nthreads = _default_threads() if threads is None else max(1, int(threads))
    moments = _moments_numba if _choose_engine(engine, chunk) == "numba" else _moments_numpy
    blocks = _antenna_blocks(nant, nant if nthreads == 1 else -(-nant // (4 * nthreads)))
    if nthreads == 1 or len(blocks) == 1:
        nbad = sum(moments(chunk, a0, a1, bufs) for a0, a1 in blocks)
    else:
        with ThreadPoolExecutor(min(nthreads, len(blocks))) as pool:
            nbad = sum(pool.map(lambda ab: moments(chunk, *ab, bufs), blocks))
    if nbad:
        raise FitError("user weights (1/sigma^2) must be finite and >= 0")
    out.lst_min = min(out.lst_min, float(lsts.min()))
    out.lst_max = max(out.lst_max, float(lsts.max()))
    return out


def _check_into(out: NormalSums, model: FitModel, lead: tuple[int, int, int]) -> None:
    """Raise :class:`FitError` unless ``out`` can hold the sums of ``model`` over ``lead``."""
    m = model.nparam
    want = {
        "ata": ((*lead, m, m), np.float64),
        "aty": ((*lead, m), np.float64),
        "yty": (lead, np.float64),
        "count": (lead, np.int64),
        "nflagged": (lead, np.int64),
    }
    if out.model != model:
        raise FitError("into= holds the sums of another model")
    for name, (shape, dtype) in want.items():
        arr = getattr(out, name)
        if arr.shape != shape or arr.dtype != dtype or not arr.flags.c_contiguous:
            raise FitError(
                f"into.{name} must be a C-contiguous {np.dtype(dtype).name} array of shape "
                f"{shape}, got {arr.dtype.name} {arr.shape}"
            )


# solving --------------------------------------------------------------------------------


#: Channel systems solved per block by :func:`solve_sums`: its temporaries (scaled normal
#: matrices, inverses) are then a few MB per block instead of several copies of ``ata``
#: (for a Legendre-2 fit of 350 antennas x 2 pols x 1536 channels, 310 MB each).
SOLVE_BLOCK = 1 << 14


def solve_sums(
    sums: NormalSums,
    *,
    min_samples: int | None = None,
    scale_covariance: bool | Literal["inflate"] = False,
    max_condition: float = MAX_CONDITION,
    block: int = SOLVE_BLOCK,
    positive_gain: bool = True,
) -> dict[str, np.ndarray]:
    """Solve the normal equations of every channel.

    Parameters
    ----------
    sums
        Accumulated sums.
    min_samples
        Fewest used samples for a channel to be solved (default ``nparam + 1``).
    scale_covariance
        ``True``: multiply the covariance by ``chi^2 / dof`` (for weights that are not
        inverse variances, e.g. identity). ``"inflate"``: multiply by ``max(1, chi^2 /
        dof)``, so errors from inverse-variance weights also cover unmodelled structure
        in real data without being shrunk below the noise.
    max_condition
        Largest condition number of the column-scaled normal matrix.
    block
        Channel systems solved at once (bounds the temporaries; the result does not
        depend on it).
    positive_gain
        Flag (reason 3) channels whose first gain coefficient is not positive. ``False``
        keeps such solutions (refits that only serve an error estimate).

    Returns
    -------
    dict
        ``coeffs`` (..., M), ``cov`` (..., M, M), ``chi2``, ``dof``, ``flag_reason``.
    """
    m = sums.model.nparam
    min_samples = m + 1 if min_samples is None else int(min_samples)
    if min_samples < m:
        raise FitError(f"min_samples must be at least the number of parameters ({m})")
    if block < 1:
        raise FitError(f"block must be at least 1 channel system, got {block}")
    lead = sums.count.shape
    ata, aty = sums.ata.reshape(-1, m, m), sums.aty.reshape(-1, m)
    yty, count = sums.yty.reshape(-1), sums.count.reshape(-1)
    n = count.size
    out = {
        "coeffs": np.empty((n, m)),
        "cov": np.empty((n, m, m)),
        "chi2": np.empty(n),
        "dof": (count - m).astype(np.float64),
        "flag_reason": np.zeros(n, np.int8),
    }
    for i0 in range(0, n, block):
        sl = slice(i0, min(i0 + block, n))
        part = _solve_block(
            ata[sl],
            aty[sl],
            yty[sl],
            count[sl],
            min_samples,
            scale_covariance,
            max_condition,
            positive_gain,
        )
        for name, value in part.items():
            out[name][sl] = value
    return {name: value.reshape(*lead, *value.shape[1:]) for name, value in out.items()}


def _eigvalsh(a: np.ndarray) -> np.ndarray:
    """Eigenvalues of ``(..., M, M)`` symmetric matrices; closed form for ``M = 2``.

    The constant model's 2 x 2 systems (a million per HERA file) take ~20 ms this way
    against ~0.3 s through LAPACK.
    """
    if a.shape[-1] != 2:
        return np.linalg.eigvalsh(a)
    mean = (a[..., 0, 0] + a[..., 1, 1]) / 2
    radius = np.hypot((a[..., 0, 0] - a[..., 1, 1]) / 2, a[..., 1, 0])
    return np.stack([mean - radius, mean + radius], axis=-1)


def _inv(a: np.ndarray) -> np.ndarray:
    """Inverses of ``(..., M, M)`` symmetric matrices; closed form (adjugate) for ``M = 2``."""
    if a.shape[-1] != 2:
        return np.linalg.inv(a)
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 1, 0] * a[..., 1, 0]
    out = np.empty_like(a)
    out[..., 0, 0] = a[..., 1, 1] / det
    out[..., 1, 1] = a[..., 0, 0] / det
    out[..., 0, 1] = out[..., 1, 0] = -a[..., 1, 0] / det
    return out


def _solve_block(
    ata: np.ndarray,
    aty: np.ndarray,
    yty: np.ndarray,
    count: np.ndarray,
    min_samples: int,
    scale_covariance: bool | Literal["inflate"],
    max_condition: float,
    positive_gain: bool = True,
) -> dict[str, np.ndarray]:
    """Solve ``(n, M, M)`` normal systems (see :func:`solve_sums`)."""
    m = ata.shape[-1]
    reason = np.zeros(count.shape, np.int8)
    reason[count < min_samples] = 1
    diag = np.diagonal(ata, axis1=-2, axis2=-1)
    d = np.where(diag > 0, np.sqrt(np.where(diag > 0, diag, 1.0)), 1.0)
    scaled = ata / (d[..., :, None] * d[..., None, :])
    ok = (reason == 0) & np.all(diag > 0, axis=-1) & np.all(np.isfinite(scaled), axis=(-2, -1))
    reason[(reason == 0) & ~ok] = 2
    eye = np.eye(m)
    scaled = np.where(ok[..., None, None], scaled, eye)
    # 2-norm condition number of the symmetric matrix from its eigenvalues (as
    # np.linalg.cond, but eigvalsh is several times faster than an SVD per channel)
    ev = np.abs(_eigvalsh(scaled))
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = ev.max(axis=-1) / ev.min(axis=-1)
    singular = ok & ~(np.isfinite(cond) & (cond < max_condition))
    reason[singular] = 2
    ok &= ~singular
    scaled = np.where(ok[..., None, None], scaled, eye)
    inv = _inv(scaled)
    cov = inv / (d[..., :, None] * d[..., None, :])
    coeffs = (cov @ aty[..., None])[..., 0]
    # a difference of large sums: rounding can make a (near-)perfect fit's chi2 negative
    chi2 = np.maximum(yty - np.einsum("...m,...m->...", coeffs, aty), 0.0)
    dof = (count - m).astype(np.float64)
    if scale_covariance:
        with np.errstate(divide="ignore", invalid="ignore"):
            factor = np.where(dof > 0, chi2 / dof, np.nan)
        if scale_covariance == "inflate":
            factor = np.maximum(np.nan_to_num(factor, nan=1.0), 1.0)
        cov = cov * factor[..., None, None]
    if positive_gain:
        reason[ok & ~(coeffs[..., 0] > 0)] = 3
    bad = reason != 0
    coeffs = np.where(bad[..., None], np.nan, coeffs)
    cov = np.where(bad[..., None, None], np.nan, cov)
    chi2 = np.where(bad, np.nan, chi2)
    return {"coeffs": coeffs, "cov": cov, "chi2": chi2, "flag_reason": reason}


# the solution ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Solution:
    """Fitted receiver gain and noise per antenna, polarisation and channel.

    Parameters
    ----------
    model
        The fitted model.
    antennas
        ``(Nant,)`` antenna numbers.
    pols
        Polarisation names.
    freqs
        ``(Nfreq,)`` Hz.
    lsts, jds
        ``(Ntime,)`` the fitted integrations (hours; Julian dates).
    coeffs
        ``(Nant, Npol, Nfreq, nparam)``: ``(G, n)`` or ``(g_0..g_p, n_0..n_p)``.
    cov
        ``(Nant, Npol, Nfreq, nparam, nparam)`` parameter covariance.
    chi2, dof
        ``(Nant, Npol, Nfreq)`` chi-square and degrees of freedom (used samples minus
        parameters). With identity weights chi-square is in data units squared.
    count, nflagged
        Used and excluded samples per channel.
    flag_reason
        ``(Nant, Npol, Nfreq)`` int codes (:data:`FLAG_REASONS`); 0 = solved.
    config
        Resolved configuration: weights, iterations, sky, beam, Tsky conventions, inputs.
    residuals
        Optional ``(Nant, Npol, Ntime, Nfreq)`` normalised residuals ``(R - model) / sigma``
        (identity weights: divided by the fitted residual rms).
    antenna_names
        Names of the antennas.
    total
        The total uncertainty (:class:`autocal.fit.uncertainty.TotalUncertainty`): when set,
        ``sigma_G``, ``sigma_n``, ``sigma_Trxr`` and ``sigma_abs_g`` are total errors and
        the ``*_stat`` properties the statistical part alone.
    """

    model: FitModel
    antennas: np.ndarray
    pols: tuple[str, ...]
    freqs: np.ndarray
    lsts: np.ndarray
    jds: np.ndarray
    coeffs: np.ndarray
    cov: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    count: np.ndarray
    nflagged: np.ndarray
    flag_reason: np.ndarray
    config: dict[str, Any] = field(default_factory=dict)
    residuals: np.ndarray | None = None
    antenna_names: tuple[str, ...] = ()
    total: TotalUncertainty | None = None

    def __post_init__(self) -> None:
        lead = (len(self.antennas), len(self.pols), len(self.freqs))
        m = self.model.nparam
        checks = {
            "coeffs": (self.coeffs, (*lead, m)),
            "cov": (self.cov, (*lead, m, m)),
            "chi2": (self.chi2, lead),
            "dof": (self.dof, lead),
            "count": (self.count, lead),
            "nflagged": (self.nflagged, lead),
            "flag_reason": (self.flag_reason, lead),
        }
        for name, (arr, shape) in checks.items():
            if np.shape(arr) != shape:
                raise FitError(f"Solution.{name} has shape {np.shape(arr)}, expected {shape}")
        if np.shape(self.lsts) != np.shape(self.jds):
            raise FitError("Solution lsts and jds differ in length")
        if self.residuals is not None and self.residuals.shape != (
            lead[0],
            lead[1],
            len(self.lsts),
            lead[2],
        ):
            raise FitError("Solution.residuals has the wrong shape")
        if self.total is not None and self.total.cov.shape != (*lead, 2, 2):
            raise FitError("Solution.total has the wrong shape")

    @classmethod
    def from_solved(
        cls,
        model: FitModel,
        sums: NormalSums,
        solved: dict[str, np.ndarray],
        *,
        antennas: np.ndarray,
        pols: tuple[str, ...],
        freqs: np.ndarray,
        lsts: np.ndarray,
        jds: np.ndarray,
        antenna_names: tuple[str, ...] = (),
        config: dict[str, Any] | None = None,
        total: TotalUncertainty | None = None,
    ) -> Solution:
        """Build a solution from normal sums and their :func:`solve_sums` output."""
        return cls(
            model=model,
            antennas=np.asarray(antennas),
            pols=tuple(pols),
            freqs=freqs,
            lsts=lsts,
            jds=jds,
            coeffs=solved["coeffs"],
            cov=solved["cov"],
            chi2=solved["chi2"],
            dof=solved["dof"],
            count=sums.count,
            nflagged=sums.nflagged,
            flag_reason=solved["flag_reason"],
            config=config or {},
            antenna_names=antenna_names,
            total=total,
        )

    def __repr__(self) -> str:
        """Return one line: model, axes, ranges and medians (never the arrays)."""
        from autocal.core.reprs import list_summary, median, span

        ok = ~self.flags
        with np.errstate(invalid="ignore", divide="ignore"):
            gain = self.G
            abs_g, trxr = np.sqrt(gain), self.n / gain
        nant = len(self.antennas)
        model = (
            self.model.kind
            if self.model.kind == "constant"
            else (f"legendre order {self.model.order}")
        )
        errors = "statistical" if self.total is None else "total"
        return (
            f"Solution({model}: {nant} antenna{'s' * (nant != 1)} "
            f"{list_summary(self.antennas)}, pols {list_summary(self.pols)}, "
            f"{self.freqs.size} channels {span(self.freqs, 1e6, 'MHz')}, {self.lsts.size} "
            f"times LST {span(self.lsts, 1, 'h')}; {int(self.flags.sum())} flagged; median "
            f"|g| {median(abs_g, ok):.4g}, Trxr {median(trxr, ok):.4g} K "
            f"+- {median(self.sigma_Trxr, ok):.3g} K ({errors}), "
            f"chi2/dof {median(self.reduced_chi2, ok):.3g})"
        )

    # products -------------------------------------------------------------------------
    def to_uvcal(self, **kwargs: Any) -> Any:
        """Return the gains ``|g| = sqrt(G)`` as a pyuvdata ``UVCal``.

        The object the calh5/calfits products hold (:func:`autocal.io.calsol.solution_to_uvcal`;
        ``kwargs``: ``time_range``, ``per_time``, ``telescope``, ``site``, ``history``).
        """
        from autocal.io.calsol import solution_to_uvcal

        return solution_to_uvcal(self, **kwargs)

    def write(
        self,
        out: str | Path,
        products: tuple[str, ...] | list[str] = ("calh5", "hdf5"),
        *,
        overwrite: bool = False,
    ) -> dict[str, str]:
        """Write products of this solution into the folder ``out`` (created).

        The files and writers of ``autocal calibrate``
        (:func:`autocal.pipeline.calibrate.write_solution_products`): ``solution.calh5``,
        ``solution.calfits``, ``solution.h5``, ``solution.png``.

        Parameters
        ----------
        out
            Output folder.
        products
            Any of ``"calh5"``, ``"calfits"``, ``"hdf5"``, ``"png"``.
        overwrite
            Replace existing files (otherwise an existing file is a ``FileExistsError``).

        Returns
        -------
        dict
            Product name -> path.
        """
        from autocal.pipeline.calibrate import write_solution_products

        return write_solution_products(self, out, products, overwrite=overwrite)

    # basic quantities ------------------------------------------------------------------
    @property
    def flags(self) -> np.ndarray:
        """``(Nant, Npol, Nfreq)`` ``True`` where the channel could not be solved."""
        return self.flag_reason != 0

    @property
    def time_average(self) -> np.ndarray:
        """``(nbasis,)`` mean of each basis function over the fitted integrations."""
        return self.model.basis(self.lsts).mean(axis=1)

    def _mean_param(self, which: int) -> tuple[np.ndarray, np.ndarray]:
        nb = self.model.nbasis
        v = np.zeros(self.model.nparam)
        v[which * nb : (which + 1) * nb] = self.time_average
        value = self.coeffs @ v
        var = np.einsum("i,...ij,j->...", v, self.cov, v)
        return value, var

    @property
    def G(self) -> np.ndarray:
        """Gain ``G = |g|^2`` averaged over the fitted integrations."""
        return self._mean_param(0)[0]

    @property
    def n(self) -> np.ndarray:
        """Noise offset ``n = G Trxr`` averaged over the fitted integrations."""
        return self._mean_param(1)[0]

    @property
    def sigma_G(self) -> np.ndarray:
        """1-sigma uncertainty of :attr:`G`: the total when known, else statistical."""
        return self._sigmas()["sigma_G"]

    @property
    def sigma_n(self) -> np.ndarray:
        """1-sigma uncertainty of :attr:`n`: the total when known, else statistical."""
        return self._sigmas()["sigma_n"]

    @property
    def sigma_Trxr(self) -> np.ndarray:
        """1-sigma uncertainty of :attr:`Trxr`: the total when known, else statistical.

        Linear propagation, ``Var(Trxr) = Trxr^2 [C_GG / G^2 + C_nn / n^2 - 2 C_Gn / (G
        n)]``, the paper's ``sum_ij (-1)^(i+j) C_ij / (x_i x_j)`` written out (the cross
        term enters with a minus sign because ``d(n/G)/dG = -n/G^2``).
        """
        return self._sigmas()["sigma_Trxr"]

    @property
    def sigma_abs_g(self) -> np.ndarray:
        """1-sigma uncertainty of ``|g|``, ``sigma_G / (2 |g|)``: total when known."""
        return self._sigmas()["sigma_abs_g"]

    @property
    def sigma_G_stat(self) -> np.ndarray:
        """Statistical 1-sigma of :attr:`G` (the fit's covariance)."""
        return self._sigmas(stat=True)["sigma_G"]

    @property
    def sigma_n_stat(self) -> np.ndarray:
        """Statistical 1-sigma of :attr:`n`."""
        return self._sigmas(stat=True)["sigma_n"]

    @property
    def sigma_Trxr_stat(self) -> np.ndarray:
        """Statistical 1-sigma of :attr:`Trxr`."""
        return self._sigmas(stat=True)["sigma_Trxr"]

    @property
    def sigma_abs_g_stat(self) -> np.ndarray:
        """Statistical 1-sigma of ``|g|``."""
        return self._sigmas(stat=True)["sigma_abs_g"]

    @property
    def cov_mean(self) -> np.ndarray:
        """Statistical covariance ``(Nant, Npol, Nfreq, 2, 2)`` of the time-averaged ``(G, n)``."""
        gg, nn = self._mean_param(0)[1], self._mean_param(1)[1]
        gn = self._mean_cov_gn()
        return np.stack([np.stack([gg, gn], -1), np.stack([gn, nn], -1)], -2)

    @property
    def cov_mean_total(self) -> np.ndarray:
        """Total covariance of the time-averaged ``(G, n)`` (statistical without a total)."""
        return self.cov_mean if self.total is None else self.total.cov

    def _sigmas(self, stat: bool = False) -> dict[str, np.ndarray]:
        cov = self.cov_mean if stat or self.total is None else self.total.cov
        var_g, var_n, cgn = cov[..., 0, 0], cov[..., 1, 1], cov[..., 0, 1]
        g, n = self.G, self.n
        with np.errstate(invalid="ignore", divide="ignore"):
            sg = np.sqrt(var_g)
            return {
                "sigma_G": sg,
                "sigma_n": np.sqrt(var_n),
                "sigma_Trxr": trxr_sigma(g, n, var_g, var_n, cgn),
                "sigma_abs_g": sg / (2 * np.sqrt(g)),
            }

    def _mean_cov_gn(self) -> np.ndarray:
        nb = self.model.nbasis
        vg = np.zeros(self.model.nparam)
        vn = np.zeros(self.model.nparam)
        vg[:nb] = self.time_average
        vn[nb:] = self.time_average
        return np.einsum("i,...ij,j->...", vg, self.cov, vn)

    @property
    def Trxr(self) -> np.ndarray:
        """Receiver temperature ``n / G`` (time-averaged ``n`` over time-averaged ``G``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.n / self.G

    @property
    def abs_g(self) -> np.ndarray:
        """Gain amplitude ``|g| = sqrt(G)`` (NaN where flagged)."""
        with np.errstate(invalid="ignore"):
            return np.sqrt(self.G)

    @property
    def reduced_chi2(self) -> np.ndarray:
        """``chi^2 / dof`` (NaN where ``dof <= 0``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.dof > 0, self.chi2 / self.dof, np.nan)

    # the time model --------------------------------------------------------------------
    def evaluate(self, lsts: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Evaluate ``G(t)``, ``n(t)``, ``Trxr(t)`` and their statistical 1-sigma errors.

        The total uncertainty (:attr:`total`) is that of the time averages; these errors
        are the time model's covariance propagated to each LST.

        Parameters
        ----------
        lsts
            LSTs in hours (default: the fitted integrations).

        Returns
        -------
        dict
            ``G``, ``n``, ``Trxr``, ``sigma_G``, ``sigma_n``, ``sigma_Trxr``, each
            ``(Nant, Npol, Ntime, Nfreq)``.
        """
        lsts = self.lsts if lsts is None else np.atleast_1d(np.asarray(lsts, np.float64))
        nb = self.model.nbasis
        basis = self.model.basis(lsts)  # (K, T)
        g = np.einsum("kt,apfk->aptf", basis, self.coeffs[..., :nb])
        n = np.einsum("kt,apfk->aptf", basis, self.coeffs[..., nb:])
        cgg = self.cov[..., :nb, :nb]
        cnn = self.cov[..., nb:, nb:]
        cgn = self.cov[..., :nb, nb:]
        var_g = np.einsum("kt,apfkl,lt->aptf", basis, cgg, basis)
        var_n = np.einsum("kt,apfkl,lt->aptf", basis, cnn, basis)
        cov_gn = np.einsum("kt,apfkl,lt->aptf", basis, cgn, basis)
        with np.errstate(divide="ignore", invalid="ignore"):
            trxr = n / g
        return {
            "G": g,
            "n": n,
            "Trxr": trxr,
            "sigma_G": np.sqrt(var_g),
            "sigma_n": np.sqrt(var_n),
            "sigma_Trxr": trxr_sigma(g, n, var_g, var_n, cov_gn),
        }

    def predict(self, tsky: np.ndarray, lsts: np.ndarray | None = None) -> np.ndarray:
        """Model auto-correlations ``G(t) Tsky + n(t)``, ``(Nant, Npol, Ntime, Nfreq)``."""
        lsts = self.lsts if lsts is None else np.asarray(lsts, np.float64)
        a = design(self.model, _check_tsky(tsky, len(self.pols), lsts.size, self.freqs.size), lsts)
        return np.einsum("pftm,apfm->aptf", a, self.coeffs)

    def describe(self) -> dict[str, Any]:
        """Short JSON-serialisable summary (medians over unflagged channels)."""
        ok = ~self.flags

        def med(x: np.ndarray) -> float | None:
            with np.errstate(invalid="ignore", divide="ignore"):
                vals = x[ok & np.isfinite(x)]
            return float(np.median(vals)) if vals.size else None

        gain = self.G  # every property below is computed once (a HERA file: 1 M channels)
        total, stat = self._sigmas(), self._sigmas(stat=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            abs_g, trxr = np.sqrt(gain), self.n / gain
            frac, frac_stat = total["sigma_G"] / gain, stat["sigma_G"] / gain
        return {
            "model": self.model.describe(),
            "antennas": self.antennas.tolist(),
            "pols": list(self.pols),
            "nfreq": int(self.freqs.size),
            "ntime": int(self.lsts.size),
            "flagged_channels": int(self.flags.sum()),
            "median_G": med(gain),
            "median_abs_g": med(abs_g),
            "median_Trxr_K": med(trxr),
            "median_sigma_Trxr_K": med(total["sigma_Trxr"]),
            "median_sigma_Trxr_stat_K": med(stat["sigma_Trxr"]),
            "median_sigma_G_frac": med(frac),
            "median_sigma_G_stat_frac": med(frac_stat),
            "errors": "statistical" if self.total is None else "total",
            "weak_separation": None if self.total is None else int(np.sum(self.total.separation())),
            "median_reduced_chi2": med(self.reduced_chi2),
        }


def trxr_sigma(
    g: np.ndarray, n: np.ndarray, var_g: np.ndarray, var_n: np.ndarray, cov_gn: np.ndarray
) -> np.ndarray:
    """Propagate ``(G, n)`` errors to ``Trxr = n / G`` (first order).

    ``Var(Trxr) = Trxr^2 [Var(G)/G^2 + Var(n)/n^2 - 2 Cov(G, n)/(G n)]``.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        trxr = n / g
        var = trxr**2 * (var_g / g**2 + var_n / n**2 - 2 * cov_gn / (g * n))
    return np.sqrt(np.where(var >= 0, var, np.nan))


# passes and error scaling: one definition for every fit ---------------------------------

#: Radiometer weighting passes: ``"auto"`` (a second pass only when data weights would bias
#: ``G`` by more than :data:`REWEIGHT_THRESHOLD`), ``1`` or ``2``.
Passes = Literal["auto", 1, 2]
#: Relative bias ``2 / (dnu dt N)`` of data-derived radiometer weights above which
#: ``passes="auto"`` makes a second, model-weighted pass.
REWEIGHT_THRESHOLD = 1e-5
#: Default passes of every calibration (:class:`autocal.pipeline.calibrate.CalibrationConfig` and
#: :func:`fit` both use it).
DEFAULT_PASSES: Passes = "auto"
#: Default: radiometer-weighted covariances are multiplied by ``max(1, chi^2/dof)`` so the
#: errors cover unmodelled structure (:class:`autocal.pipeline.calibrate.CalibrationConfig` and
#: :func:`fit` both use it).
DEFAULT_INFLATE_ERRORS = True


def covariance_scaling(
    weights: str | np.ndarray, inflate_errors: bool = DEFAULT_INFLATE_ERRORS
) -> bool | Literal["inflate"]:
    """Return how :func:`solve_sums` scales the covariance for these weights.

    Parameters
    ----------
    weights
        ``"radiometer"``, ``"identity"`` or an array of inverse variances.
    inflate_errors
        Inflate inverse-variance errors by ``max(1, chi^2/dof)``.

    Returns
    -------
    bool or "inflate"
        ``True`` (times ``chi^2/dof``) for identity weights, which are not inverse
        variances; otherwise ``"inflate"`` or ``False`` as ``inflate_errors`` says.
    """
    if isinstance(weights, str) and weights == "identity":
        return True
    return "inflate" if inflate_errors else False


def data_weight_bias(bt_min: float) -> float:
    """Relative bias ``2 / (dnu dt N)`` of ``G`` from data-derived radiometer weights.

    ``bt_min`` is the smallest ``dnu dt N`` of the used samples (0 when there is none).
    """
    return 2.0 / bt_min if np.isfinite(bt_min) and bt_min > 0 else 0.0


def run_passes(
    one_pass: Callable[[np.ndarray | None, int, int], tuple[Any, NormalSums, float]],
    *,
    passes: Passes,
    radiometer: bool,
    min_samples: int | None = None,
) -> tuple[Any, int]:
    """Run the weighting passes of a fit: the one pass loop of autocal.

    Pass 1 weights by the data. With radiometer weights and ``passes`` 2 (or ``"auto"``
    when the first pass shows a data-weight bias :func:`data_weight_bias` of at least
    :data:`REWEIGHT_THRESHOLD`) a second pass weights by the first pass's model. The
    in-memory :func:`fit` and the streamed :func:`autocal.pipeline.calibrate.run_calibration`
    both run through here, so they decide the same.

    Parameters
    ----------
    one_pass
        ``one_pass(coeffs, ipass, npass) -> (result, sums, bt_min)``: accumulate the data
        once, weighting radiometer weights by the model of ``coeffs``
        (``(Nant, Npol, Nfreq, nparam)``; ``None`` in the first pass: by the data);
        ``npass`` is the number of passes planned so far (for progress). It returns
        anything the caller needs, the pass's fitted sums and the smallest ``dnu dt N``
        of the used samples (``inf`` when unknown).
    passes
        ``"auto"``, ``1`` or ``2``.
    radiometer
        Whether the weights are radiometer weights (other weights need one pass).
    min_samples
        Passed to :func:`solve_sums` for the model of the next pass.

    Returns
    -------
    tuple
        The last pass's ``result`` and the number of passes made.
    """
    if passes not in ("auto", 1, 2):
        raise FitError(f"passes must be 'auto', 1 or 2, got {passes!r}")
    npass = 1 if not radiometer or passes == 1 else 2
    coeffs = None
    ipass = 0
    result: Any = None
    while ipass < npass:
        result, sums, bt_min = one_pass(coeffs, ipass, npass)
        if ipass == 0 and passes == "auto" and npass == 2:
            bias = data_weight_bias(bt_min)
            if bias < REWEIGHT_THRESHOLD:
                logger.info(
                    "data-weight bias 2/(dnu dt N) = %.2g < %.0e: one pass",
                    bias,
                    REWEIGHT_THRESHOLD,
                )
                npass = 1
        if ipass + 1 < npass:
            coeffs = solve_sums(sums, min_samples=min_samples)["coeffs"]
        ipass += 1
    return result, npass


# the in-memory driver -------------------------------------------------------------------


def fit(
    obs: Observation,
    tsky: np.ndarray,
    *,
    model: str | FitModel = "constant",
    order: int = 1,
    weights: str | np.ndarray = "radiometer",
    passes: Passes = DEFAULT_PASSES,
    inflate_errors: bool = DEFAULT_INFLATE_ERRORS,
    min_samples: int | None = None,
    scale_covariance: bool | Literal["inflate"] | None = None,
    return_residuals: bool = False,
    config: dict[str, Any] | None = None,
    uncertainty: Literal["total", "statistical"] = "total",
    trxr_prior: Any = None,
) -> Solution:
    """Fit gain and receiver noise to an observation and a Tsky array held in memory.

    The low-level fit: no files, no Tsky computation, no products. Its defaults (passes,
    error inflation) are those of :class:`autocal.pipeline.calibrate.CalibrationConfig`
    (:data:`DEFAULT_PASSES`, :data:`DEFAULT_INFLATE_ERRORS`) and its passes run through
    :func:`run_passes`, like :func:`autocal.calibrate`; to calibrate files (or an
    observation, Tsky computed for you) call :func:`autocal.calibrate`.

    Parameters
    ----------
    obs
        The observation.
    tsky
        ``(Npol, Ntime, Nfreq)`` or ``(Ntime, Nfreq)`` model Tsky in kelvin at the
        observation's LSTs and frequencies.
    model
        ``"constant"``, ``"legendre"`` or a :class:`FitModel`.
    order
        Legendre order for ``model="legendre"``.
    weights
        ``"radiometer"``, ``"identity"`` or an array of ``1 / sigma^2``.
    passes
        Radiometer weighting passes (:func:`run_passes`): pass 1 weights by the data, a
        second pass by the fitted model (removes the weight-noise correlation bias);
        ``"auto"`` makes the second only when that bias exceeds
        :data:`REWEIGHT_THRESHOLD`. Other weights: one pass.
    inflate_errors
        Multiply the covariance of inverse-variance weights by ``max(1, chi^2/dof)``
        (identity weights are always scaled by ``chi^2/dof``).
    min_samples
        Fewest used samples per channel.
    scale_covariance
        Override the covariance scaling (:func:`solve_sums`): ``True``, ``False`` or
        ``"inflate"``; ``None`` (default): :func:`covariance_scaling` of ``weights`` and
        ``inflate_errors``.
    return_residuals
        Store normalised residuals in the solution.
    config
        Extra configuration recorded in the solution (sky, beam, inputs).
    uncertainty
        ``"total"`` (default): also compute the total uncertainty
        (:mod:`autocal.fit.uncertainty`: block jackknife and the model with one more time
        order), so ``sigma_*`` are total errors; ``"statistical"``: the covariance only.
    trxr_prior
        A receiver prior: an :class:`autocal.fit.priors.TrxrPrior` or ``(trxr_k, sigma_k)``
        arrays broadcastable to ``(Nant, Npol, Nfreq)``. The time-averaged ``n`` is held
        near ``G trxr_k`` (:func:`autocal.fit.priors.add_trxr_prior`); the errors include the
        prior's.

    Returns
    -------
    Solution
        The fitted solution.
    """
    from autocal.fit.priors import add_trxr_prior
    from autocal.fit.uncertainty import (
        accumulate_blocks,
        block_edges,
        extended_model,
        mean_vectors,
        sums_nbytes,
        total_uncertainty,
    )

    if isinstance(model, FitModel):
        fit_model = model
    else:
        fit_model = FitModel.for_lsts(obs.lsts, model, 0 if model == "constant" else order)
    tsky = _check_tsky(tsky, len(obs.pols), obs.ntime, obs.nfreq)
    is_radiometer = isinstance(weights, str) and weights == "radiometer"
    bt = obs.bandwidth_time() if is_radiometer else None
    bt_min = np.inf
    if bt is not None:
        used = np.broadcast_to(~obs.flags, bt.shape)
        if not np.all(bt[used] > 0):
            raise FitError(
                "radiometer weights need positive channel width, integration time and "
                "nsamples; the observation lacks them: use weights='identity'"
            )
        bt_min = float(np.min(bt, where=used, initial=np.inf))
    scale = (
        covariance_scaling(weights, inflate_errors)
        if scale_covariance is None
        else (scale_covariance)
    )
    if uncertainty not in ("total", "statistical"):
        raise FitError(f"uncertainty must be 'total' or 'statistical', got {uncertainty!r}")
    edges = None
    if uncertainty == "total":
        nbytes = sums_nbytes(extended_model(fit_model), obs.nant, len(obs.pols), obs.nfreq)
        edges = block_edges(obs.ntime, bytes_per_block=nbytes)

    def one_pass(
        coeffs: np.ndarray | None, ipass: int, npass: int
    ) -> tuple[tuple[NormalSums, Any, np.ndarray | None], NormalSums, float]:
        reference = None
        if coeffs is not None:
            pred = np.einsum("pftm,apfm->aptf", design(fit_model, tsky, obs.lsts), coeffs)
            # Channels that failed keep data-based weights.
            reference = np.where(np.isfinite(pred) & (pred > 0), pred, obs.data)
        kwargs = {"flags": obs.flags, "weights": weights, "bandwidth_time": bt}
        blocks = None
        if edges is None:
            sums = accumulate(fit_model, obs.data, tsky, obs.lsts, reference=reference, **kwargs)
        else:
            blocks = accumulate_blocks(
                fit_model, obs.data, tsky, obs.lsts, edges, reference=reference, **kwargs
            )
            sums = blocks.fitted_total()
        return (sums, blocks, reference), sums, bt_min

    (sums, blocks, reference), npass = run_passes(
        one_pass, passes=passes, radiometer=is_radiometer, min_samples=min_samples
    )
    prior_fn = None
    solve_from = sums
    if trxr_prior is not None:
        if hasattr(trxr_prior, "at"):
            ptrxr, psigma = trxr_prior.at(obs.freqs, antennas=obs.antennas, pols=obs.pols)
        else:
            ptrxr, psigma = trxr_prior

        def prior_fn(part: NormalSums, pvg: np.ndarray, pvn: np.ndarray) -> NormalSums:
            return add_trxr_prior(part, pvg, pvn, ptrxr, psigma, scale_covariance=scale)

        solve_from = prior_fn(sums, *mean_vectors(fit_model, obs.lsts))
    solved = solve_sums(solve_from, min_samples=min_samples, scale_covariance=scale)
    nbad = int(np.sum(solved["flag_reason"] != 0))
    if nbad:
        logger.warning(
            "%d of %d channels could not be solved: %s",
            nbad,
            solved["flag_reason"].size,
            {
                FLAG_REASONS[int(k)]: int(v)
                for k, v in zip(*np.unique(solved["flag_reason"], return_counts=True), strict=True)
                if k
            },
        )
    cfg = {
        "weights": weights if isinstance(weights, str) else "user",
        "passes": npass,
        "scale_covariance": scale,
        "min_samples": min_samples if min_samples is not None else fit_model.nparam + 1,
        **(config or {}),
    }
    total = None
    if blocks is not None:
        total = total_uncertainty(blocks, solved, scale_covariance=scale, prior=prior_fn)
        cfg["uncertainty"] = total.describe()
    solution = Solution.from_solved(
        fit_model,
        sums,
        solved,
        antennas=obs.antennas,
        pols=obs.pols,
        freqs=obs.freqs,
        lsts=obs.lsts,
        jds=obs.jds,
        antenna_names=obs.antenna_names,
        config=cfg,
        total=total,
    )
    if return_residuals:
        solution = _with_residuals(solution, obs, tsky, weights, reference, bt)
    return solution


def _with_residuals(
    solution: Solution,
    obs: Observation,
    tsky: np.ndarray,
    weights: str | np.ndarray,
    reference: np.ndarray | None,
    bt: np.ndarray | None,
) -> Solution:
    from dataclasses import replace

    pred = solution.predict(tsky)
    usable = np.isfinite(obs.data) & ~obs.flags
    w = weights_for(weights, obs.data, usable, bt, pred if bt is not None else reference)
    if isinstance(weights, str) and weights == "identity":
        rms = np.sqrt(solution.reduced_chi2)[:, :, None, :]
        w = w / rms**2
    resid = np.where(usable, (obs.data - pred) * np.sqrt(w), np.nan)
    return replace(solution, residuals=resid)
