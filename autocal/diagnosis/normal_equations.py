"""The extended fit's normal equations: (G, n) projected out (variable projection).

For fixed global parameters every channel is a weighted linear fit of ``(G, n)``; the global
Gauss-Newton step uses the Jacobian projected orthogonally to each channel's ``(G, n)``
design, so the covariance of the global parameters is marginalised over all ``(G, n)``. An
optional receiver prior (``Trxr(nu) = Trxr0 +- sigma``) enters as one pseudo-observation per
channel, ``n - Trxr0 G = 0 +- G sigma``. :class:`FitProblem` holds one such problem and
streams the antennas through its sums (:func:`autocal.diagnosis.chunks.antenna_chunks`);
:func:`projected_normal_equations` is the reference form of the same sums.

The model's derivative with respect to each effect's parameters factorises into a part
that depends on the antenna and a part that does not: ``J[a, p, f, t, k] = X[a, p, f, t]
Y[p, f, t, k]``, with ``Y`` the time basis (gain and noise drifts; no ``p``, ``f``
dependence) or the Tsky template's derivative (shared by all antennas). The Gauss-Newton
normal matrix with the per-channel ``(G, n)`` projected out is::

    h = J^T W J - sum over channels of (c1 k1^T + c2 k2^T),
    c_i = sum_t w a_i J,  (k1, k2) = N^-1 (c1, c2),  N the channel's 2 x 2 normal matrix,

so only ``J^T W J`` (antennas summed first, then the small bases), the ``c_i`` (one matrix
product per effect over time) and K x K products are needed: never the (samples x K)
Jacobian, which took most of a diagnosis's time and ~8 bytes x samples x K of memory. Every
term is a sum over antennas, so the fit adds them up a chunk of antennas at a time.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import ParamSpec, TypeVar

import numpy as np
from threadpoolctl import threadpool_limits

from autocal.core.observation import Observation
from autocal.diagnosis.chunks import antenna_chunks, usable_weights
from autocal.diagnosis.effects import Effect, SkyTemplates
from autocal.diagnosis.errors import DiagnoseError

P = ParamSpec("P")
R = TypeVar("R")


#: Fraction of a template's Fisher information that must survive the (G, n) projection.
MIN_IDENTIFIABLE = 1e-6
#: Fisher fractions below this are rounding error (``h`` is a difference of sums of squares,
#: :func:`projected_normal_equations`): reported as 0, degenerate with ``(G, n)``.
IDENTIFIABLE_RESOLUTION = 1e-12
#: Smallest singular value (relative) of the scaled normal matrix that is inverted ...
PINV_RTOL = 1e-15
#: ... or this many times its rounding error, if larger (:func:`projected_normal_equations`).
ROUNDING_MARGIN = 100.0


def blas_single_thread(func: Callable[P, R]) -> Callable[P, R]:
    """Run ``func`` with BLAS/LAPACK on one thread.

    The extended fit does many small dense solves (a pseudo-inverse of a K x K matrix per
    Gauss-Newton step); multi-threaded OpenBLAS spends ~100x longer on them than one
    thread as soon as the cores are shared (pytest-xdist, other workers): 0.77 s vs 4 ms
    for K = 143 measured on the 2-core development machine under load.
    """

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with threadpool_limits(limits=1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper


def _split(effects: tuple[Effect, ...]) -> list[tuple[Effect, slice]]:
    out, i = [], 0
    for eff in effects:
        k = 0 if eff.fixed is not None else len(eff.params)
        out.append((eff, slice(i, i + k)))
        i += k
    return out


@dataclass
class FitState:
    """One evaluation of the fit: model columns, channel solutions and chi^2.

    ``tt`` ``(P, T, F)`` Tsky; ``gfac``, ``nfac`` ``(T,)`` the gain and noise factors;
    the model is ``G a1 + n a2`` with ``a1 = tt gfac`` and ``a2 = nfac gfac``.
    """

    tt: np.ndarray
    gfac: np.ndarray
    nfac: np.ndarray
    g: np.ndarray
    nn: np.ndarray
    inv: np.ndarray
    good: np.ndarray
    rp: np.ndarray
    chi2: float

    @property
    def a1(self) -> np.ndarray:
        """``(P, T, F)`` the gain's column: Tsky times the gain factor."""
        return self.tt * self.gfac[:, None]

    @property
    def a2(self) -> np.ndarray:
        """``(T,)`` the noise's column: the noise factor times the gain factor."""
        return self.nfac * self.gfac


def _contract(w: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``sum_t w[a, p, t, f] z[p, t, f]`` -> ``(a, P, F)`` (``z`` broadcast to ``(P, T, F)``)."""
    return np.einsum("aptf,ptf->apf", w, np.broadcast_to(z, w.shape[1:]))


def prior_gain_reference(
    obs: Observation, tpl: SkyTemplates, weights: np.ndarray, trxr_prior: np.ndarray | float
) -> np.ndarray:
    """Return the gain ``(Nant, Npol, Nfreq)`` the receiver prior's rows are weighted with.

    The prior on ``Trxr = n / G`` enters a fit as the row ``n - Trxr0 G`` of 1-sigma
    ``G sigma``, which needs a gain before any is fitted. This one is the data's own: the
    time-mean of the usable data (``weights > 0``) over the time-mean of the model sky
    plus the prior's ``Trxr0``, over the same samples, ``<D> / (<Tsky> + Trxr0)``, which
    needs no fit (NaN where ``<Tsky>`` and ``Trxr0`` nearly cancel: within a tenth of
    their magnitudes). The weights used to come from a fit without the prior, which over half
    an hour cannot tell ``G`` from ``n`` (the sky changes too little): its gain was 0.27 to
    1.55 times this one on a clean file and -21 to 28 times beside a gain drift (the
    independent simulator's ``clean_short``, seed 20260, and
    ``gain_drift+cable_reflection_short``, seeds 20261 and 20265); the search's fits,
    weighted with the gain of the first fit that used it, then had ``sigma_G`` 2.5x or
    half what it is, and missed or overstated a cable reflection. NaN where a channel has
    no usable sample, no finite prior or a non-positive result.
    """
    shape3 = (obs.nant, len(obs.pols), obs.nfreq)
    t0 = np.broadcast_to(np.asarray(trxr_prior, float), shape3)
    out = np.full(shape3, np.nan)
    tsky = np.broadcast_to(tpl.total, obs.shape[1:])
    for sl in antenna_chunks(obs.shape):
        usable = np.asarray(weights[sl]) > 0
        count = usable.sum(axis=2)
        with np.errstate(invalid="ignore"):
            data = np.einsum("aptf->apf", np.where(usable, obs.data[sl], 0.0), dtype=np.float64)
        sky = np.einsum("aptf,ptf->apf", usable.astype(np.float64), tsky)
        with np.errstate(divide="ignore", invalid="ignore"):
            total = sky / count + t0[sl]  # <Tsky> + Trxr0
            # where the two nearly cancel (a receiver temperature near -<Tsky>, as noise-wave
            # calibrated EDGES data can have), the ratio says nothing: no reference
            cancels = np.abs(total) < 0.1 * (np.abs(sky / count) + np.abs(t0[sl]))
            out[sl] = np.where(cancels, np.nan, data / count / total)
    return np.where(np.isfinite(out) & (out > 0), out, np.nan)


class FitProblem:
    """The extended fit of one observation, weights and set of effects.

    The problem :func:`autocal.diagnosis.extended_fit.fit_extended` solves. Holds what
    every evaluation shares (usable channels, prior, bases) and streams the antennas
    through :meth:`evaluate` (channel solutions and chi^2) and :meth:`normal_equations`
    (the projected normal equations of the global parameters, the sums of
    :func:`projected_normal_equations` contracted template by template, so that a chunk's
    samples are read a few times and never copied per parameter).
    """

    def __init__(
        self,
        obs: Observation,
        tpl: SkyTemplates,
        effects: tuple[Effect, ...],
        weights: np.ndarray,
        trxr_prior: np.ndarray | float | None,
        trxr_prior_sigma: np.ndarray | float,
        gain_ref: np.ndarray | None,
        chunk_antennas: int | None,
    ) -> None:
        if tpl.total.shape[0] != len(obs.pols) or tpl.total.shape[1:] != (
            obs.ntime,
            obs.nfreq,
        ):
            raise DiagnoseError("templates do not match the observation's grid")
        weights = np.asarray(weights)
        if weights.shape != obs.shape:
            raise DiagnoseError(f"weights have shape {weights.shape}, the data {obs.shape}")
        self.obs, self.tpl, self.effects, self.weights = obs, tpl, effects, weights
        self.chunks = antenna_chunks(obs.shape, chunk_antennas)
        self.shape3 = shape3 = (obs.nant, len(obs.pols), obs.nfreq)
        # channels with fewer than 3 usable samples cannot constrain (G, n): leave them out
        self.chan_ok = np.zeros(shape3, bool)
        self.used = 0
        # weights finite and >= 0, data finite: the chunks are used as they are
        self.clean_weights = self.finite_data = True
        for sl in self.chunks:
            w = weights[sl]
            usable = np.isfinite(w) & (w > 0)
            self.clean_weights &= bool(np.all(usable | (w == 0)))
            self.finite_data &= bool(np.all(np.isfinite(obs.data[sl])))
            nuse = usable.sum(axis=2)
            self.chan_ok[sl] = nuse >= 3
            self.used += int(nuse[self.chan_ok[sl]].sum())
        if not self.chan_ok.any():
            with np.errstate(invalid="ignore"):
                positive = np.isfinite(obs.data) & (obs.data > 0)
            why = (
                "the data hold no positive, finite value (all NaN, inf, zero or negative: "
                "check the file)"
                if not positive.any()
                else "the data's own flags, the band edges and RFI leave too few samples"
            )
            raise DiagnoseError(f"no channel has 3 or more unflagged samples to fit: {why}")
        self.blocks = _split(effects)
        self.nfree = sum(b.stop - b.start for _, b in self.blocks)
        self.fixed = {e.name: np.asarray(e.fixed, float) for e in effects if e.fixed is not None}
        self.bases = {
            (e.basis, e.order): e.time_basis(obs.lsts) for e in effects if e.kind != "tsky"
        }
        self.prior = trxr_prior is not None
        t0 = np.broadcast_to(np.asarray(trxr_prior if self.prior else 0.0, float), shape3)
        sig0 = np.broadcast_to(np.asarray(trxr_prior_sigma, float), shape3)
        has_prior = np.isfinite(t0) & np.isfinite(sig0) & (sig0 > 0)
        self.t0 = np.where(has_prior, t0, 0.0)
        # prior weights from a reference gain
        self.wp = np.zeros(shape3)
        if self.prior:
            with np.errstate(over="ignore", invalid="ignore", under="ignore"):
                if gain_ref is None:
                    gain_ref = prior_gain_reference(obs, tpl, weights, t0)
                    if not np.isfinite(gain_ref).all():  # else: the fit's own, as before
                        fitted = np.abs(self.evaluate(np.zeros(self.nfree)).g)
                        gain_ref = np.where(np.isfinite(gain_ref), gain_ref, fitted)
                gain_ref = np.where(np.abs(gain_ref) > 0, np.abs(gain_ref), np.inf)
                self.wp = np.where(self.chan_ok & has_prior, 1.0 / (gain_ref * sig0) ** 2, 0.0)

    def values(self, eff: Effect, sl: slice, pv: np.ndarray) -> np.ndarray:
        """Return an effect's parameter values (its fixed values, or ``pv[sl]``)."""
        return self.fixed[eff.name] if eff.fixed is not None else pv[sl]

    def chunk_arrays(self, sl: slice) -> tuple[np.ndarray, np.ndarray]:
        """Return weights and data of antennas ``sl``, ``(a, P, T, F)`` float64.

        Weights are zero where unusable (channels without a solution included), data
        zero where not finite; both are views of the inputs when nothing needs zeroing.
        """
        ok = self.chan_ok[sl]
        if self.clean_weights:
            w = np.asarray(self.weights[sl], np.float64)
            if not ok.all():
                w = w * ok[:, :, None, :]
        else:
            w = usable_weights(self.weights[sl], ok)
        y = self.obs.data[sl]
        if not self.finite_data:
            with np.errstate(invalid="ignore"):
                y = np.where(w > 0, y, 0.0)
        return w, y

    def columns(self, pv: np.ndarray) -> tuple[np.ndarray, ...]:
        """Return Tsky ``(P, T, F)`` and the gain and noise factors ``(T,)`` at ``pv``."""
        tsky = self.tpl.total.copy()
        gfac = np.ones(self.obs.ntime)
        nfac = np.ones(self.obs.ntime)
        for eff, sl in self.blocks:
            v = self.values(eff, sl, pv)
            if eff.kind == "tsky":
                tsky = tsky + eff.delta(v, self.tpl)
            elif eff.kind == "gain":
                gfac = gfac + v @ self.bases[eff.basis, eff.order]
            else:
                nfac = nfac + v @ self.bases[eff.basis, eff.order]
        return tsky, gfac, nfac

    @staticmethod
    def residual(
        y: np.ndarray, g: np.ndarray, nn: np.ndarray, a1: np.ndarray, a2: np.ndarray
    ) -> np.ndarray:
        """Return ``y - G a1 - n a2`` of a chunk (``a1`` ``(P, T, F)``, ``a2`` ``(T,)``)."""
        r = g[:, :, None, :] * a1
        r += nn[:, :, None, :] * a2[:, None]
        np.subtract(y, r, out=r)
        return r

    def evaluate(self, pv: np.ndarray) -> FitState:
        """Solve every channel's ``(G, n)`` at global parameters ``pv``; chi^2."""
        tt, gfac, nfac = self.columns(pv)
        a1 = tt * gfac[:, None]
        a2 = nfac * gfac
        a1sq, a12, a2sq = a1 * a1, a1 * a2[:, None], (a2 * a2)[:, None]
        shape3 = self.shape3
        g, nn = np.zeros(shape3), np.zeros(shape3)
        inv, good = np.zeros((3, *shape3)), np.zeros(shape3, bool)
        chi2 = 0.0
        for sl in self.chunks:
            w, y = self.chunk_arrays(sl)
            wp, t0 = self.wp[sl], self.t0[sl]
            wy = w * y
            n11 = _contract(w, a1sq) + wp * t0**2
            n12 = _contract(w, a12) - wp * t0
            n22 = _contract(w, a2sq) + wp
            b1 = _contract(wy, a1)
            b2 = _contract(wy, a2[:, None])
            det = n11 * n22 - n12**2
            ok = self.chan_ok[sl] & np.isfinite(det) & (det > 1e-12 * np.abs(n11 * n22))
            det = np.where(ok, det, 1.0)
            iv = np.where(ok, np.stack([n22 / det, -n12 / det, n11 / det]), 0.0)
            gc = iv[0] * b1 + iv[1] * b2
            nc = iv[1] * b1 + iv[2] * b2
            g[sl], nn[sl], inv[:, sl], good[sl] = gc, nc, iv, ok
            r = self.residual(y, gc, nc, a1, a2)
            chi2 += float(np.einsum("aptf,aptf,aptf->", w, r, r))
        rp = np.where(good, -(nn - self.t0 * g), 0.0)
        chi2 += float((self.wp * rp**2).sum())
        return FitState(tt, gfac, nfac, g, nn, inv, good, rp, chi2)

    def _terms(self, pv: np.ndarray, st: FitState) -> list[tuple[slice, list, np.ndarray, str]]:
        """Return each free block's factorised derivative ``sum_m alpha_m beta_m Y``.

        ``(slice, [(alpha, beta)], Y, form)``: ``alpha`` ``"g"`` or ``"n"`` (the channel's
        fitted gain or noise), ``beta`` broadcastable to ``(P, T, F)``, ``Y`` ``(P, T, F,
        k)`` (``form`` ``"tsky"``), a time basis ``(T, k)`` (``"time"``) or the
        per-integration basis (``"integration"``, parameter ``k`` = integration ``k + 1``).
        """
        out = []
        gcol, ncol = st.gfac[:, None], st.nfac[:, None]
        for eff, sl in self.blocks:
            if sl.stop == sl.start:
                continue
            if eff.kind == "tsky":
                terms = [("g", gcol)]
                ymat, form = eff.jacobian(pv[sl], self.tpl), "tsky"
            else:
                terms = [("g", st.tt), ("n", ncol)] if eff.kind == "gain" else [("n", gcol)]
                ymat = self.bases[eff.basis, eff.order].T
                form = "integration" if eff.basis == "integration" else "time"
            out.append((sl, terms, ymat, form))
        return out

    def normal_equations(
        self, pv: np.ndarray, st: FitState, groups: list[int] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``h``, ``grad``, ``raw`` (:func:`projected_normal_equations`) at ``st``.

        ``groups``: one per free block; the ``J^T W J`` block of two blocks of different
        nonzero groups is not computed (left 0; see
        :func:`autocal.diagnosis.screening.screen_candidates`).
        """
        specs = self._terms(pv, st)
        nfree = self.nfree
        a1, a2 = st.a1, st.a2
        a2col = a2[:, None]
        products = {
            tuple(sorted(a + b))
            for _, t1, _, _ in specs
            for _, t2, _, _ in specs
            for a, _ in t1
            for b, _ in t2
        }
        wsum = {key: np.zeros(a1.shape) for key in products}  # sum_a w alpha alpha'
        proj = np.zeros((nfree, nfree))
        grad = np.zeros(nfree)
        for sl in self.chunks:
            w, y = self.chunk_arrays(sl)
            alpha = {"g": st.g[sl], "n": st.nn[sl]}
            wr = w * self.residual(y, alpha["g"], alpha["n"], a1, a2)
            rp, wp, t0 = st.rp[sl], self.wp[sl], self.t0[sl]
            # A^T W r per channel (data and prior rows): ~0 at the channel solution
            q1 = _contract(wr, a1) - wp * t0 * rp
            q2 = _contract(wr, a2col) + wp * rp
            for key in wsum:
                wsum[key] += np.einsum("aptf,apf->ptf", w, alpha[key[0]] * alpha[key[1]])
            c1 = np.zeros((*alpha["g"].shape, nfree))
            c2 = np.zeros_like(c1)
            for bsl, terms, ymat, form in specs:
                for name, beta in terms:
                    al = alpha[name]
                    if form == "integration":
                        # one parameter per integration: the sums over time are the samples
                        for col, dst in ((a1 * beta, c1), (a2col * beta, c2)):
                            dst[..., bsl] += al[..., None] * np.moveaxis(
                                (w * col)[:, :, 1:, :], 2, -1
                            )
                        grad[bsl] += np.einsum("apf,aptf->t", al, wr * beta)[1:]
                        continue
                    for k in range(ymat.shape[-1]):
                        z = beta * (ymat[..., k] if form == "tsky" else ymat[:, k, None])
                        i = bsl.start + k
                        c1[..., i] += al * _contract(w, a1 * z)
                        c2[..., i] += al * _contract(w, a2col * z)
                        grad[i] += float(np.sum(al * _contract(wr, z)))
            inv = st.inv[:, sl]
            k1 = inv[0][..., None] * c1 + inv[1][..., None] * c2
            k2 = inv[1][..., None] * c1 + inv[2][..., None] * c2
            c1, c2, k1, k2 = (x.reshape(-1, nfree) for x in (c1, c2, k1, k2))
            proj += c1.T @ k1 + c2.T @ k2
            grad -= k1.T @ q1.reshape(-1) + k2.T @ q2.reshape(-1)
        # J^T W J from the antenna sums: sum_{p,t,f} (sum_a w alpha alpha') beta beta' Y Y'
        jwj = np.zeros((nfree, nfree))
        grp = [0] * len(specs) if groups is None else groups
        for i, (sl1, t1, y1, f1) in enumerate(specs):
            for j in range(i, len(specs)):
                sl2, t2, y2, f2 = specs[j]
                if grp[i] and grp[j] and grp[i] != grp[j]:
                    continue
                v = sum(wsum[tuple(sorted(n1 + n2))] * b1 * b2 for n1, b1 in t1 for n2, b2 in t2)
                block = _pair_sum(np.broadcast_to(v, a1.shape), y1, f1, y2, f2)
                jwj[sl1, sl2] = block
                jwj[sl2, sl1] = block.T
        h = jwj - proj
        return 0.5 * (h + h.T), grad, np.diag(jwj).copy()


def _pair_sum(v: np.ndarray, y1: np.ndarray, f1: str, y2: np.ndarray, f2: str) -> np.ndarray:
    """``sum_{p,t,f} v Y1[..., k] Y2[..., l]`` for Tsky ``(P, T, F, k)`` or time ``(T, k)`` Y."""
    if f1 != "tsky" and f2 != "tsky":
        return (y1.T * v.sum(axis=(0, 2))) @ y2
    if f1 == "tsky" and f2 == "tsky":
        return np.einsum("ptf,ptfk,ptfl->kl", v, y1, y2)
    if f1 == "tsky":
        return np.einsum("ptf,ptfk->tk", v, y1).T @ y2
    return y1.T @ np.einsum("ptf,ptfl->tl", v, y2)


def identifiable_fractions(
    blocks: list[tuple[Effect, slice]], h: np.ndarray, raw: np.ndarray
) -> dict[str, float]:
    """Return each free block's Fisher fraction left after the ``(G, n)`` projection.

    Parameters without any data (``raw`` 0: e.g. the jitter factor of an integration
    flagged whole) take no part: they are not constrained, and not degenerate with ``(G,
    n)`` either; a block with no constrained parameter gets 0.
    """
    ident: dict[str, float] = {}
    for eff, sl in blocks:
        if sl.stop > sl.start:
            projected, unprojected = np.diag(h)[sl], raw[sl]
            seen = unprojected > 0
            frac = float(np.min(projected[seen] / unprojected[seen])) if seen.any() else 0.0
            ident[eff.name] = frac if frac >= IDENTIFIABLE_RESOLUTION else 0.0
    return ident


def scaled_pinv(h: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of the projected normal matrix ``h`` (``raw``: its unprojected diagonal).

    ``h`` is scaled to unit diagonal first (parameters differ by 1e6); it is ``J^T W J``
    less the ``(G, n)`` part, so its rounding error is ~eps * raw / diag(h) of the scaled
    matrix: directions below that are left out, not inverted.
    """
    hdiag = np.diag(h)
    dscale = 1.0 / np.sqrt(np.where(hdiag > 0, hdiag, 1.0))
    lost = np.max(np.where(hdiag > 0, raw * dscale**2, 1.0))  # raw / projected
    rtol = max(PINV_RTOL, ROUNDING_MARGIN * np.finfo(float).eps * lost)
    return dscale[:, None] * np.linalg.pinv(dscale[:, None] * h * dscale, rtol=rtol) * dscale


# the reference sums ---------------------------------------------------------------------


def _sum_time(v: np.ndarray, ymat: np.ndarray) -> np.ndarray:
    """``sum_t v[a, p, f, t] Y[p, f, t, k]`` -> ``(A, P, F, k)``."""
    if ymat.shape[:2] == (1, 1):
        return (v.reshape(-1, v.shape[-1]) @ ymat[0, 0]).reshape(*v.shape[:3], -1)
    return np.matmul(v[..., None, :], ymat)[..., 0, :]


def _sum_all(z: np.ndarray, ymat: np.ndarray) -> np.ndarray:
    """``sum_{p, f, t} z[p, f, t] Y[p, f, t, k]`` -> ``(k,)``."""
    if ymat.shape[:2] == (1, 1):
        return z.sum(axis=(0, 1)) @ ymat[0, 0]
    return np.einsum("pft,pftk->k", z, ymat)


def _sum_pair(z: np.ndarray, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """``sum_{p, f, t} z Y1[..., k] Y2[..., l]`` -> ``(k, l)``."""
    if y1.shape[:2] == (1, 1) and y2.shape[:2] == (1, 1):
        return (y1[0, 0].T * z.sum(axis=(0, 1))) @ y2[0, 0]
    b1 = np.broadcast_to(y1, (*z.shape, y1.shape[-1])).reshape(-1, y1.shape[-1])
    b2 = np.broadcast_to(y2, (*z.shape, y2.shape[-1])).reshape(-1, y2.shape[-1])
    return (z.reshape(-1, 1) * b1).T @ b2


def projected_normal_equations(
    factors: list[tuple[slice, np.ndarray, np.ndarray]],
    w: np.ndarray,
    wa1: np.ndarray,
    wa2: np.ndarray,
    inv: np.ndarray,
    r: np.ndarray,
    q1: np.ndarray,
    q2: np.ndarray,
    nfree: int,
    groups: list[int] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton normal equations of the global parameters, ``(G, n)`` projected out.

    Parameters
    ----------
    factors
        ``(slice, X, Y)`` of the free parameters: ``X`` broadcastable to ``w``, ``Y``
        ``(P, F, T, k)`` or, for a time basis, ``(1, 1, T, k)``.
    w, wa1, wa2
        ``(A, P, F, T)`` weights and the weighted ``(G, n)`` columns ``w a1``, ``w a2``.
    inv
        ``(3, A, P, F)`` inverse of each channel's 2 x 2 normal matrix (``[0, 0]``,
        ``[0, 1]``, ``[1, 1]``; zero for channels without a solution).
    r
        ``(A, P, F, T)`` residuals.
    q1, q2
        ``(A, P, F)`` ``A^T W r`` of each channel (data and prior rows).
    nfree
        Number of free global parameters.
    groups
        One per factor: the ``J^T W J`` block of two factors whose groups differ and are
        both nonzero is left 0 (its projection part is still subtracted); default all 0.

    Returns
    -------
    h, grad, raw
        ``(K, K)`` normal matrix and ``(K,)`` gradient of the projected problem (those the
        projected Jacobian ``J - a1 k1 - a2 k2`` gives, with the prior rows), and the
        diagonal of ``J^T W J`` before the projection (identifiability).
    """
    jwj = np.zeros((nfree, nfree))
    grad = np.zeros(nfree)
    c1 = np.zeros((*w.shape[:3], nfree))
    c2 = np.zeros_like(c1)
    grp = [0] * len(factors) if groups is None else groups
    for i, (sl, x, ymat) in enumerate(factors):
        wx = w * x
        c1[..., sl] = _sum_time(wa1 * x, ymat)
        c2[..., sl] = _sum_time(wa2 * x, ymat)
        grad[sl] = _sum_all((wx * r).sum(axis=0), ymat)
        for j, (sl2, x2, y2) in enumerate(factors[i:], i):
            if grp[i] and grp[j] and grp[i] != grp[j]:
                continue
            block = _sum_pair(np.broadcast_to(wx * x2, w.shape).sum(axis=0), ymat, y2)
            jwj[sl, sl2] = block
            jwj[sl2, sl] = block.T
    k1 = inv[0][..., None] * c1 + inv[1][..., None] * c2
    k2 = inv[1][..., None] * c1 + inv[2][..., None] * c2
    c1, c2, k1, k2 = (a.reshape(-1, nfree) for a in (c1, c2, k1, k2))
    h = jwj - c1.T @ k1 - c2.T @ k2
    grad -= k1.T @ q1.reshape(-1) + k2.T @ q2.reshape(-1)
    return 0.5 * (h + h.T), grad, np.diag(jwj).copy()
