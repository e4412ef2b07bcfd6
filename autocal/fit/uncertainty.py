"""Total uncertainties: statistics, correlated residuals and what a short span cannot decide.

The covariance of a least-squares fit (:func:`autocal.fit.lsq.solve_sums`) is honest only when
the model is right and the residuals are independent radiometer noise. On real data neither
holds, and over a short span a third problem dominates: the sky changes by a few per cent of
the system temperature (or less), so a gain that drifts by a fraction of a per cent is
indistinguishable from a different ``(G, n)``. This module turns per-block normal sums into a
*total* 1-sigma that covers all three, without a second pass over the data.

Blocks
    The integrations are split into ``B`` contiguous time blocks (:func:`block_edges`) and
    the normal sums of the fitted model are kept per block (:class:`BlockSums`), those of
    the model with one more order once. The ordinary fit is the lower orders of the latter
    (equal to a direct fit to rounding, ~1e-11 relative).

Correlated residuals and an unstable fit: delete-a-block jackknife
    ``B`` refits, each without one block, give the jackknife covariance of the
    time-averaged ``(G, n)``: ``V_jk = (B - 1)/B sum_b (x_-b - xbar)(x_-b - xbar)^T``.
    Residuals correlated over less than a block and any instability of the fit over the
    span (a gain that wanders, a solution that depends on which part of the span is used)
    show up in it; the radiometer covariance does not see them. Its size relative to the
    jackknife covariance ``E`` the statistical model itself predicts (from the blocks'
    normal matrices: the delete-a-block estimator over-weights the ends of a time model)
    and to the chi2/dof scaling ``s`` of the statistical covariance is the factor
    ``f_jk = tr(E^-1 V_jk) / (2 s)``; the statistical covariance ``C`` is scaled by
    ``max(1, f_jk)`` (the correlation of ``G`` and ``n`` is kept from ``C``, far better
    determined than ``V_jk`` with ``B - 1`` degrees of freedom).

What the span cannot decide: the time model averaged over one more order
    The fitted model is compared with the model that has one more Legendre order in both
    ``G(t)`` and ``n(t)`` (for the constant model: a gain and offset that drift linearly over
    the span). Its sums are accumulated with the data (its lower orders are the fitted
    model's), so it costs no second pass. Each channel weighs the two by the Bayesian
    information criterion of a quasi-likelihood (chi-square divided by the larger model's
    ``max(1, chi^2/dof)``, or ``chi^2/dof`` for identity weights, Burnham & Anderson's
    QAIC/QBIC): ``w_1 = 1 / (1 + exp(-(dchi2 / phi - 2 ln N) / 2))``, ``dchi2 = dx^T A dx``
    of the nested fits (exact, not a difference of two chi-squares). Each channel takes the
    larger of its own weight and its antenna-pol's over all channels (the sum of the
    channels' statistics: a drifting gain drifts at every frequency). Both models are
    restricted to ``G > 0`` (:func:`positive_gain`): each estimate is its Gaussian truncated
    there and the statistic gains ``2 ln [P_1(G > 0) / P_0(G > 0)]``. When the data prefer a
    drift, ``w_1 -> 1`` and the total covers both the drift model's (much larger) uncertainty and
    the difference between the two estimates; on data that follow the fitted model
    ``w_1 ~ 1e-2`` and the total stays at the statistical error.

The total covariance of the time-averaged ``(G, n)`` is

    ``C_tot = max(1, f_jk) [w_0 C_0 + w_1 C_1] + w_1 d d^T``,   ``d = x_1 - x_0``,

the second moment about the reported (fitted-model) estimate of the two models' mixture.
Undefined parts are left out and reported: with fewer than :data:`MIN_BLOCKS` blocks (fewer
than ``2 MIN_BLOCKS`` integrations) there is no jackknife, and a model that cannot take one
more order (too few samples, an extension that does not solve) gets ``w_1 = 0``.

Assumptions: the blocks are long compared with the correlation time of the residuals (else
the jackknife under-estimates); an unmodelled drift is smooth enough over the span for one
more Legendre order to represent it; the BIC weights assume the residual scatter is the same
in both models up to the factor ``phi``. Errors with no time signature (a sky model's
spectrum, a flux scale) are not covered: they belong to a systematics budget
(:mod:`autocal.compare.gains`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from autocal.fit.lsq import FitError, FitModel, NormalSums, solve_sums

logger = logging.getLogger(__name__)

#: Fewest blocks for a jackknife (``B - 1`` degrees of freedom in ``V_jk``).
MIN_BLOCKS = 4
#: Blocks used when the observation has enough integrations.
DEFAULT_BLOCKS = 10
#: Bytes the per-block sums may take; larger problems use fewer blocks (at least
#: :data:`MIN_BLOCKS`, else no jackknife and no drift model).
BLOCK_MEMORY = 1 << 30
#: Above this median drift sensitivity ``(dG/G)/delta`` an antenna-pol's ``G`` and ``n``
#: separate weakly: a 1 % gain drift over the span would move ``G`` by more than 10 %.
WEAK_SENSITIVITY = 10.0
#: Assumed receiver temperatures (K) of the ``G(Trxr)`` profile, extended to cover the
#: fitted ``Trxr`` when it lies outside.
PROFILE_TRXR = np.arange(0.0, 501.0, 50.0)
#: A description of the method, recorded in the products.
METHOD = (
    "total = jackknife-scaled statistical covariance averaged (BIC weights) with the model of "
    "one more time order, plus the weighted difference of the two estimates"
)


def block_edges(ntime: int, nblocks: int | None = None, *, bytes_per_block: int = 0) -> np.ndarray:
    """Return the integration indices that split ``ntime`` integrations into blocks.

    Parameters
    ----------
    ntime
        Number of integrations of the observation.
    nblocks
        Blocks wanted (default :data:`DEFAULT_BLOCKS`), reduced to ``ntime // 2`` (at least
        two integrations a block) and to what :data:`BLOCK_MEMORY` allows.
    bytes_per_block
        Size of one block's normal sums.

    Returns
    -------
    numpy.ndarray
        ``(B + 1,)`` increasing indices from 0 to ``ntime``; ``B = 1`` (``[0, ntime]``) when
        fewer than :data:`MIN_BLOCKS` blocks are possible.
    """
    want = DEFAULT_BLOCKS if nblocks is None else int(nblocks)
    if want < 1:
        raise FitError(f"the number of blocks must be at least 1, got {want}")
    nb = min(want, ntime // 2)
    if bytes_per_block > 0:
        nb = min(nb, BLOCK_MEMORY // bytes_per_block)
    if nb < MIN_BLOCKS:
        nb = 1
    return np.linspace(0, ntime, nb + 1).round().astype(np.int64)


def sums_nbytes(model: FitModel, nant: int, npol: int, nfreq: int) -> int:
    """Bytes of one set of :class:`~autocal.fit.lsq.NormalSums` of this shape."""
    m = model.nparam
    return 8 * nant * npol * nfreq * (m * m + m + 3)


@dataclass
class BlockSums:
    """Normal sums of contiguous time blocks of one observation.

    Attributes
    ----------
    blocks
        One :class:`~autocal.fit.lsq.NormalSums` per block, in time order, of the fitted
        ``model`` (the jackknife's and the halves' refits).
    model
        The fitted model.
    edges
        ``(B + 1,)`` integration indices of the block boundaries.
    lsts
        ``(Ntime,)`` LSTs (hours) of all integrations of the fit.
    extended
        The sums over all blocks of the *extended* model (:func:`extended_model`): the
        drift term's fit, and (its lower orders) the ordinary fit. One set, not one per
        block: a HERA file's extended sums are ~200 MB.
    """

    blocks: list[NormalSums]
    model: FitModel
    edges: np.ndarray
    lsts: np.ndarray
    extended: NormalSums

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        from autocal.core.reprs import compact_repr

        return compact_repr(self)

    def __post_init__(self) -> None:
        if len(self.blocks) != len(self.edges) - 1:
            raise FitError(f"{len(self.blocks)} block sums for {len(self.edges) - 1} blocks")
        if self.edges[0] != 0 or self.edges[-1] != len(self.lsts):
            raise FitError("block edges must run from 0 to the number of integrations")
        if any(b.model != self.model for b in self.blocks):
            raise FitError("block sums must be of the fitted model")
        if self.extended.model != extended_model(self.model):
            raise FitError("the extended sums must be of the fitted model's extended model")

    @classmethod
    def from_extended(
        cls,
        blocks: list[NormalSums],
        model: FitModel,
        edges: np.ndarray,
        lsts: np.ndarray,
    ) -> BlockSums:
        """Build from per-block sums of the extended model (their sum is kept once)."""
        total = NormalSums.zeros(blocks[0].model, *blocks[0].count.shape)
        for part in blocks:
            total += part
        return cls([base_sums(b, model) for b in blocks], model, edges, lsts, total)

    def fitted_total(self) -> NormalSums:
        """Return the fitted model's sums over all blocks (the ordinary fit)."""
        return base_sums(self.extended, self.model)

    @property
    def nblocks(self) -> int:
        """Number of blocks ``B``."""
        return len(self.blocks)

    def total(self) -> NormalSums:
        """Return the extended model's sums over all blocks."""
        return self.extended


def _minus(total: NormalSums, part: NormalSums) -> NormalSums:
    return NormalSums(
        total.model,
        total.ata - part.ata,
        total.aty - part.aty,
        total.yty - part.yty,
        total.count - part.count,
        total.nflagged - part.nflagged,
    )


@dataclass(frozen=True, eq=False)
class TotalUncertainty:
    """The total uncertainty of a solution's time-averaged ``(G, n)`` and its parts.

    Arrays are ``(Nant, Npol, Nfreq)`` unless noted.

    Attributes
    ----------
    cov
        ``(Nant, Npol, Nfreq, 2, 2)`` total covariance of the time-averaged ``(G, n)``.
    jackknife_factor
        ``f_jk``: jackknife over statistical variance (NaN where undefined).
    drift_weight
        ``w_1``: weight of the model with one more time order (0 where undefined).
    G_drift, n_drift
        Time-averaged ``G`` and ``n`` of that model.
    sigma_G_drift
        Its statistical 1-sigma of ``G``.
    G_halves
        ``(2, Nant, Npol, Nfreq)`` the span's mean ``G`` estimated from the first and from
        the second half of the blocks alone (NaN without blocks).
    sky_contrast
        Weighted rms of ``Tsky`` over the span divided by the system temperature
        ``mean(Tsky) + Trxr``: how much the sky varies to separate ``G`` from ``n``.
    corr_G_n
        Statistical correlation coefficient of ``G`` and ``n`` (near -1: weakly separated).
    drift_sensitivity
        Fractional change of the fitted ``G`` per unit fractional gain change of the shape
        of the next time order (for the constant model: a linear drift, 0.01 = the gain
        changing by 1 % from the first to the last integration), ``dG/G / delta``.
    profile_trxr
        ``(Ngrid,)`` assumed receiver temperatures (K) of the profile.
    profile_G
        ``(Nant, Npol, Ngrid, Nfreq)`` time-averaged ``G`` fitted with ``n(t) = G(t) Trxr``
        held at each assumed ``Trxr``: what ``G`` is if the receiver temperature is known.
    nblocks
        Number of blocks ``B`` (1: no jackknife).
    notes
        What was undefined and why.
    """

    cov: np.ndarray
    jackknife_factor: np.ndarray
    drift_weight: np.ndarray
    G_drift: np.ndarray
    n_drift: np.ndarray
    sigma_G_drift: np.ndarray  # noqa: N815 - the physics symbol
    G_halves: np.ndarray
    sky_contrast: np.ndarray
    corr_G_n: np.ndarray  # noqa: N815 - the physics symbol
    drift_sensitivity: np.ndarray
    profile_trxr: np.ndarray
    profile_G: np.ndarray  # noqa: N815 - the physics symbol
    nblocks: int
    notes: tuple[str, ...] = ()

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        from autocal.core.reprs import compact_repr

        return compact_repr(self)

    def separation(self) -> np.ndarray:
        """``(Nant, Npol)`` ``True`` where ``G`` and ``n`` separate weakly.

        Weak: the median over channels of :attr:`drift_sensitivity` exceeds
        :data:`WEAK_SENSITIVITY` (a 1 % gain drift over the span would move ``G`` by more
        than 10 %).
        """
        with np.errstate(all="ignore"):
            med = _nanmedian_last(np.abs(self.drift_sensitivity))
        return med > WEAK_SENSITIVITY  # NaN (nothing solved) is not "weak"

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description of the method and its settings."""
        return {
            "method": METHOD,
            "blocks": self.nblocks,
            "jackknife": self.nblocks >= MIN_BLOCKS,
            "notes": list(self.notes),
        }


def mean_vectors(model: FitModel, lsts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the vectors ``(vg, vn)`` that give the time-averaged ``G`` and ``n``.

    ``G = vg . x`` and ``n = vn . x`` for the parameters ``x`` of ``model``, averaged over
    the integrations at ``lsts``.
    """
    tavg = model.basis(lsts).mean(axis=1)
    nb = model.nbasis
    vg = np.zeros(model.nparam)
    vn = np.zeros(model.nparam)
    vg[:nb] = tavg
    vn[nb:] = tavg
    return vg, vn


def _project(coeffs: np.ndarray, cov: np.ndarray, vg: np.ndarray, vn: np.ndarray):
    """Time-averaged ``(G, n)`` and their 2 x 2 covariance from parameters.

    Matrix-vector products (BLAS) rather than one ``einsum`` over the batch: ~10x faster
    for a HERA file's million channels.
    """
    theta = np.stack([coeffs @ vg, coeffs @ vn], axis=-1)
    cvg = np.tensordot(cov, vg, axes=([-1], [0]))  # (..., M)
    cvn = np.tensordot(cov, vn, axes=([-1], [0]))
    cgn = cvg @ vn
    c2 = np.stack([np.stack([cvg @ vg, cgn], axis=-1), np.stack([cgn, cvn @ vn], axis=-1)], axis=-2)
    return theta, c2


def extended_model(model: FitModel) -> FitModel:
    """Return the fitted model with one more Legendre order in ``G(t)`` and ``n(t)``.

    Its time axis is the fitted model's (for the constant model: the LST span of the data,
    which :meth:`FitModel.for_lsts` records), so the fitted model's sums are a sub-block of
    its sums (:func:`base_sums`).
    """
    return FitModel("legendre", model.order + 1, model.lst_start, model.lst_span)


def _base_index(model: FitModel) -> np.ndarray:
    """Return the indices of the fitted model's parameters among the extended model's."""
    nb = model.nbasis
    return np.r_[np.arange(nb), nb + 1 + np.arange(nb)]


def base_sums(sums: NormalSums, model: FitModel) -> NormalSums:
    """Return the fitted model's sums: a sub-block of the extended model's sums.

    Legendre polynomials of a lower order are the first basis functions of a higher one,
    so ``P_0 .. P_p`` columns of the extended design are exactly the fitted design.
    """
    idx = _base_index(model)
    return NormalSums(
        model,
        np.ascontiguousarray(sums.ata[..., idx[:, None], idx[None, :]]),
        np.ascontiguousarray(sums.aty[..., idx]),
        sums.yty.copy(),
        sums.count.copy(),
        sums.nflagged.copy(),
        sums.lst_min,
        sums.lst_max,
        dict(sums.info),
    )


def total_uncertainty(
    blocks: BlockSums,
    solved: dict[str, np.ndarray],
    *,
    scale_covariance: bool | Literal["inflate"] = "inflate",
    prior: Any = None,
) -> TotalUncertainty:
    """Compute the total uncertainty of a solution from its block sums.

    Parameters
    ----------
    blocks
        Per-block normal sums of the extended model.
    solved
        :func:`autocal.fit.lsq.solve_sums` output of ``blocks.fitted_total()`` (with the same
        ``scale_covariance`` and prior): the reported solution.
    scale_covariance
        As given to :func:`~autocal.fit.lsq.solve_sums` for the reported solution; the refits
        use the same.
    prior
        Optional callable ``prior(sums, vg, vn) -> sums`` adding a receiver prior's
        pseudo-observation to a set of sums, ``vg`` and ``vn`` the vectors that give the
        time-averaged ``G`` and ``n`` from the parameters (applied to every refit alike).

    Returns
    -------
    TotalUncertainty
        The total covariance of the time-averaged ``(G, n)`` and its parts.
    """
    model = blocks.model
    ext_model = extended_model(model)
    lsts = blocks.lsts
    vg, vn = mean_vectors(model, lsts)
    evg, evn = mean_vectors(ext_model, lsts)
    total = blocks.total()
    fitted = blocks.fitted_total()
    notes: list[str] = []

    def solve(sums: NormalSums) -> dict[str, np.ndarray]:
        """Refit the fitted model from ``sums`` (with the prior, if any)."""
        if prior is not None:
            sums = prior(sums, vg, vn)
        return solve_sums(sums, scale_covariance=scale_covariance, positive_gain=False)

    def project(res: dict[str, np.ndarray], ext: bool = False) -> tuple[np.ndarray, np.ndarray]:
        return _project(res["coeffs"], res["cov"], *((evg, evn) if ext else (vg, vn)))

    theta0, c0 = project(solved)
    lead = theta0.shape[:-1]
    nblk = blocks.nblocks
    c0_ok = np.all(np.isfinite(c0), axis=(-2, -1))

    # delete-a-block jackknife of the fitted model, and its two halves
    fjk = np.full(lead, np.nan)
    halves = np.full((2, *lead), np.nan)
    if nblk >= MIN_BLOCKS:
        reps = np.empty((nblk, *lead, 2))
        for b, part in enumerate(blocks.blocks):
            reps[b] = project(solve(_minus(fitted, part)))[0]
        ok = np.all(np.isfinite(reps), axis=-1)  # (B, ...)
        nok = ok.sum(axis=0)
        mean = np.where(ok[..., None], reps, 0.0).sum(axis=0) / np.maximum(nok, 1)[..., None]
        dev = np.where(ok[..., None], reps - mean, 0.0)
        frac = (nok - 1) / np.maximum(nok, 1)
        vjk = frac[..., None, None] * np.einsum("b...i,b...j->...ij", dev, dev)
        # against the jackknife covariance the statistical model itself predicts (the
        # delete-a-block estimator over-weights the ends of a time model: a Legendre fit's
        # refits extrapolate), times the chi2/dof scaling the statistical covariance has
        expected = _expected_jackknife(blocks, fitted, prior, vg, vn)
        scaling = _covariance_scaling(solved, scale_covariance)
        einv = _inv2(np.where(np.isfinite(expected), expected, np.eye(2)))
        with np.errstate(divide="ignore", invalid="ignore"):
            fjk = np.einsum("...ij,...ji->...", einv, vjk) / 2.0 / scaling
        good_e = np.all(np.isfinite(expected), axis=(-2, -1)) & (scaling > 0)
        fjk = np.where((nok >= MIN_BLOCKS) & c0_ok & good_e, fjk, np.nan)
        half = nblk // 2
        for h, ids in enumerate((range(half), range(half, nblk))):
            sub = blocks.blocks[ids[0]]
            for b in ids[1:]:
                sub = sub + blocks.blocks[b]
            # the span's mean G estimated from each half's data (for a time model, each
            # half's fit evaluated over the whole span; its own half's mean is no better
            # determined: measured on a clean day, order 1, 23 % against 3 % off)
            halves[h] = project(solve(sub))[0][..., 0]
    else:
        notes.append(
            f"no jackknife: {len(lsts)} integrations make fewer than {MIN_BLOCKS} blocks of two "
            "or more (or their sums would not fit in memory); the total has no term for "
            "residuals correlated in time"
        )

    # the model with one more time order (exact: the blocks hold its sums)
    ext_sums = total if prior is None else prior(total, evg, evn)
    ext = solve_sums(ext_sums, scale_covariance=scale_covariance, positive_gain=False)
    theta1, c1 = project(ext, ext=True)
    dof1 = ext["dof"]
    count = total.count.astype(np.float64)
    # the chi2 drop of nested least squares, dx^T A_ext dx (dx: the extended solution less
    # the fitted one embedded), instead of a difference of two chi2 that are each a small
    # difference of large sums (rounding noise of eps x condition x y^T W y)
    embedded = np.zeros_like(ext["coeffs"])
    embedded[..., _base_index(model)] = solved["coeffs"]
    dx = np.nan_to_num(ext["coeffs"] - embedded)
    dchi2 = np.einsum("...i,...ij,...j->...", dx, ext_sums.ata, dx)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        phi = np.where(dof1 > 0, ext["chi2"] / dof1, np.nan)
        if scale_covariance != True:  # noqa: E712 - identity weights: chi2 in data units
            phi = np.maximum(phi, 1.0)  # inverse-variance weights: never below the noise
        stat = dchi2 / phi - 2.0 * np.log(np.maximum(count, 1.0))
    # a gain is positive: each model's estimate is the Gaussian restricted to G > 0, and
    # its evidence is scaled by the probability it gives to G > 0
    theta1, c1, logp1 = positive_gain(theta1, c1)
    logp0 = positive_gain(theta0, c0)[2]
    stat = stat + 2.0 * (logp1 - logp0)
    good = np.isfinite(stat) & np.all(np.isfinite(theta1), axis=-1)
    good &= np.all(np.isfinite(c1), axis=(-2, -1))
    # per channel, and for each antenna-pol as a whole (a drifting gain drifts at every
    # frequency; channels that cannot see it alone are told by the others)
    stat = np.where(good, stat, 0.0)
    joint = np.where(good.any(axis=-1), stat.sum(axis=-1), -np.inf)[..., None]
    w1 = np.maximum(_logistic(stat / 2.0), _logistic(joint / 2.0))
    if not good[c0_ok].all():
        notes.append(
            f"{int((~good & c0_ok).sum())} solved channels could not take one more time order "
            "(too few samples or a singular system): no drift term there"
        )
    w1 = np.where(good, w1, 0.0)
    theta1 = np.where(good[..., None], theta1, theta0)
    c1 = np.where(good[..., None, None], c1, 0.0)

    scale = np.where(np.isfinite(fjk), np.maximum(fjk, 1.0), 1.0)[..., None, None]
    d = np.nan_to_num(theta1 - theta0)
    w1e = w1[..., None, None]
    ctot = scale * ((1.0 - w1e) * c0 + w1e * c1) + w1e * np.einsum("...i,...j->...ij", d, d)
    ctot = np.where(c0_ok[..., None, None], ctot, np.nan)
    bad = ~c0_ok
    base_total = fitted
    contrast = _sky_contrast(base_total, model, theta0)
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = c0[..., 0, 1] / np.sqrt(c0[..., 0, 0] * c0[..., 1, 1])
    sens = _drift_sensitivity(total, model, theta0, vg)
    grid = _profile_grid(theta0)
    profile = profile_gain(base_total, model, vg, grid)
    return TotalUncertainty(
        cov=ctot,
        jackknife_factor=fjk,
        drift_weight=np.where(bad, np.nan, w1),
        G_drift=np.where(bad | ~good, np.nan, theta1[..., 0]),
        n_drift=np.where(bad | ~good, np.nan, theta1[..., 1]),
        sigma_G_drift=np.where(bad | ~good, np.nan, np.sqrt(np.abs(c1[..., 0, 0]))),
        G_halves=halves,
        sky_contrast=np.where(bad, np.nan, contrast),
        corr_G_n=np.where(bad, np.nan, corr),
        drift_sensitivity=np.where(bad, np.nan, sens),
        profile_trxr=grid,
        profile_G=profile,
        nblocks=nblk,
        notes=tuple(notes),
    )


def _nanmedian_last(x: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN (NaN where all are NaN), without warnings."""
    srt = np.sort(x, axis=-1)  # NaN last
    n = np.sum(np.isfinite(x), axis=-1)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[..., None], axis=-1)[..., 0]
    return np.where(n > 0, (lo + hi) / 2, np.nan)


def _sky_contrast(sums: NormalSums, model: FitModel, theta: np.ndarray) -> np.ndarray:
    """Weighted rms of Tsky over ``mean(Tsky) + Trxr`` from the fitted model's sums."""
    nb = model.nbasis
    sw = sums.ata[..., nb, nb]  # sum w P_0^2
    swt = sums.ata[..., 0, nb]  # sum w T
    swt2 = sums.ata[..., 0, 0]  # sum w T^2
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = swt / sw
        var = np.maximum(swt2 / sw - mean**2, 0.0)
        tsys = mean + theta[..., 1] / theta[..., 0]
        return np.sqrt(var) / np.abs(tsys)


def _drift_sensitivity(
    ext_sums: NormalSums, model: FitModel, theta: np.ndarray, vg: np.ndarray
) -> np.ndarray:
    """``(dG/G)/delta`` of the fitted model for a gain change of the next order's shape.

    The unmodelled gain ``G (1 + delta P_{p+1}(s) / 2)`` (and ``n`` in proportion, a gain
    that multiplies the whole system temperature) adds ``delta/2 (G, n)`` to the next
    order's coefficients; least squares maps that onto the fitted parameters by
    ``A^-1 B`` (``A`` the fitted model's normal matrix, ``B`` its cross terms with the
    next order's columns).
    """
    nb = model.nbasis
    idx = _base_index(model)
    new = np.array([nb, 2 * nb + 1])
    a = ext_sums.ata[..., idx[:, None], idx[None, :]]
    b = ext_sums.ata[..., idx[:, None], new[None, :]]
    ok = np.all(np.isfinite(theta), axis=-1)
    rhs = b @ np.where(ok[..., None], theta, 0.0)[..., None] / 2.0  # (..., m, 1)
    eye = np.eye(a.shape[-1])
    good = ok & (np.linalg.det(np.where(ok[..., None, None], a, eye)) != 0)
    with np.errstate(all="ignore"):
        dx = np.linalg.solve(np.where(good[..., None, None], a, eye), rhs)[..., 0]
        return np.where(good, (dx @ vg) / theta[..., 0], np.nan)


def _profile_grid(theta: np.ndarray) -> np.ndarray:
    """:data:`PROFILE_TRXR`, extended in 50 K steps to cover the fitted ``Trxr``."""
    with np.errstate(all="ignore"):
        trxr = theta[..., 1] / theta[..., 0]
    trxr = trxr[np.isfinite(trxr)]
    lo, hi = float(PROFILE_TRXR[0]), float(PROFILE_TRXR[-1])
    if trxr.size:
        lo = min(lo, 50.0 * np.floor(np.percentile(trxr, 5) / 50.0))
        hi = max(hi, 50.0 * np.ceil(np.percentile(trxr, 95) / 50.0))
    return np.arange(lo, hi + 1.0, 50.0)


def profile_gain(sums: NormalSums, model: FitModel, vg: np.ndarray, trxr: np.ndarray) -> np.ndarray:
    """Time-averaged ``G`` fitted with ``n(t) = G(t) Trxr`` for each assumed ``Trxr``.

    The model ``R = G(t) (Tsky + Trxr)`` is linear in the gain coefficients alone; its
    normal equations follow from the fitted model's sums.

    Parameters
    ----------
    sums
        The fitted model's normal sums.
    model
        The fitted model.
    vg
        Time-average vector of the gain coefficients (length ``nparam``).
    trxr
        ``(Ngrid,)`` assumed receiver temperatures, K.

    Returns
    -------
    numpy.ndarray
        ``(Nant, Npol, Ngrid, Nfreq)``; NaN where the reduced system is singular.
    """
    nb = model.nbasis
    g, n = slice(0, nb), slice(nb, 2 * nb)
    agg, agn, ann = sums.ata[..., g, g], sums.ata[..., g, n], sums.ata[..., n, n]
    ag, an = sums.aty[..., g], sums.aty[..., n]
    out = np.empty((*sums.count.shape[:2], len(trxr), sums.count.shape[2]))
    eye = np.eye(nb)
    for i, t in enumerate(np.asarray(trxr, np.float64)):
        a = agg + t * (agn + np.swapaxes(agn, -1, -2)) + t * t * ann
        rhs = ag + t * an
        if nb == 1:
            with np.errstate(all="ignore"):
                coef = rhs / a[..., 0]
        else:
            ok = np.linalg.det(a) > 0
            coef = np.linalg.solve(np.where(ok[..., None, None], a, eye), rhs[..., None])[..., 0]
            coef = np.where(ok[..., None], coef, np.nan)
        out[:, :, i] = np.where(sums.count > nb, coef @ vg[:nb], np.nan)
    return out


def positive_gain(theta: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Restrict a Gaussian estimate of ``(G, n)`` to ``G > 0``.

    Parameters
    ----------
    theta
        ``(..., 2)`` means of ``(G, n)``.
    cov
        ``(..., 2, 2)`` covariances.

    Returns
    -------
    theta, cov, logp
        Mean and covariance of the Gaussian conditioned on ``G > 0`` (a truncated normal in
        ``G``; ``n`` follows through its regression on ``G``) and ``log P(G > 0)``.
        Unchanged where the variance of ``G`` is zero or not finite (``logp`` 0).
    """
    from scipy.special import erfcx, log_ndtr

    mg, vg = theta[..., 0], cov[..., 0, 0]
    ok = np.isfinite(mg) & np.isfinite(vg) & (vg > 0)
    sg = np.sqrt(np.where(ok, vg, 1.0))
    alpha = np.where(ok, -mg / sg, 0.0)
    logp = np.where(ok, log_ndtr(-alpha), 0.0)
    lam = np.sqrt(2.0 / np.pi) / erfcx(alpha / np.sqrt(2.0))  # phi(a) / (1 - Phi(a)), stable
    mean_g = mg + sg * lam
    var_g = vg * np.maximum(1.0 + alpha * lam - lam * lam, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.where(ok, cov[..., 0, 1] / np.where(ok, vg, 1.0), 0.0)
    out_t = theta.copy()
    out_c = cov.copy()
    out_t[..., 0] = np.where(ok, mean_g, mg)
    out_t[..., 1] = np.where(ok, theta[..., 1] + beta * (mean_g - mg), theta[..., 1])
    cond_n = cov[..., 1, 1] - beta * cov[..., 0, 1]
    out_c[..., 0, 0] = np.where(ok, var_g, vg)
    out_c[..., 0, 1] = out_c[..., 1, 0] = np.where(ok, beta * var_g, cov[..., 0, 1])
    out_c[..., 1, 1] = np.where(ok, cond_n + beta * beta * var_g, cov[..., 1, 1])
    return out_t, out_c, logp


def _logistic(x: np.ndarray) -> np.ndarray:
    """``1 / (1 + exp(-x))`` without overflow warnings."""
    return 1.0 / (1.0 + np.exp(-np.clip(x, -700.0, 700.0)))


def _covariance_scaling(
    solved: dict[str, np.ndarray], scale_covariance: bool | Literal["inflate"]
) -> np.ndarray:
    """Return the factor :func:`autocal.fit.lsq.solve_sums` applied to each channel's covariance."""
    if not scale_covariance:
        return np.ones(solved["chi2"].shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(solved["dof"] > 0, solved["chi2"] / solved["dof"], np.nan)
    if scale_covariance == "inflate":
        factor = np.maximum(np.nan_to_num(factor, nan=1.0), 1.0)
    return factor


def _expected_jackknife(
    blocks: BlockSums, fitted: NormalSums, prior: Any, vg: np.ndarray, vn: np.ndarray
) -> np.ndarray:
    """Return the jackknife covariance of ``(G, n)`` the statistical model predicts.

    With inverse-variance weights a block's right-hand side has covariance ``A_b`` (its
    normal matrix) and blocks are independent; the refit without block ``b`` is
    ``x_b = K_b (v - v_b)``, ``K_b = (A - A_b + P)^-1`` (``P``: the prior's rows, noiseless),
    so ``Cov(x_b, x_c) = K_b (A - A_b - A_c + delta_bc A_b) K_c``. With ``Y_b`` the projection
    of ``K_b`` onto the time-averaged ``(G, n)`` the expectation of the jackknife estimator
    ``(B-1)/B sum_b (t_b - tbar)(t_b - tbar)^T`` needs only sums over blocks:
    ``(B-1)/B [sum_b Y_b (A - A_b) Y_b^T - (Ysum A Ysum^T - sum_b Y_b A_b Ysum^T -
    Ysum sum_c A_c Y_c^T + sum_b Y_b A_b Y_b^T) / B]``.
    """
    nblk = blocks.nblocks
    a = fitted.ata
    p = 0.0
    if prior is not None:
        p = prior(fitted, vg, vn).ata - a
    proj = np.stack([vg, vn])  # (2, M)
    m = a.shape[-1]
    eye = np.eye(m)
    lead = a.shape[:-2]
    ysum = np.zeros((*lead, 2, m))  # sum_b Y_b
    own = np.zeros((*lead, 2, 2))  # sum_b Y_b (A - A_b) Y_b^T
    same = np.zeros((*lead, 2, 2))  # sum_b Y_b A_b Y_b^T
    cross = np.zeros((*lead, 2, m))  # sum_b Y_b A_b
    with np.errstate(all="ignore"):
        for part in blocks.blocks:
            rest = a - part.ata + p
            ok = np.all(np.isfinite(rest), axis=(-2, -1)) & (np.linalg.det(rest) != 0)
            k = np.where(
                ok[..., None, None], np.linalg.inv(np.where(ok[..., None, None], rest, eye)), np.nan
            )
            y = proj @ k  # (..., 2, M)
            yt = np.swapaxes(y, -1, -2)
            yab = y @ part.ata
            ysum += y
            own += (y @ (a - part.ata)) @ yt
            same += yab @ yt
            cross += yab
        ysum_t = np.swapaxes(ysum, -1, -2)
        # sum_{b,c} Y_b (A - A_b - A_c) Y_c^T + sum_b Y_b A_b Y_b^T
        every = (ysum @ a) @ ysum_t - cross @ ysum_t - ysum @ np.swapaxes(cross, -1, -2) + same
        return (nblk - 1) / nblk * (own - every / nblk)


def _inv2(a: np.ndarray) -> np.ndarray:
    """Inverses of ``(..., 2, 2)`` matrices (adjugate; singular ones give inf/NaN)."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    out = np.empty_like(a)
    with np.errstate(divide="ignore", invalid="ignore"):
        out[..., 0, 0] = a[..., 1, 1] / det
        out[..., 1, 1] = a[..., 0, 0] / det
        out[..., 0, 1] = -a[..., 0, 1] / det
        out[..., 1, 0] = -a[..., 1, 0] / det
    return out


def accumulate_blocks(
    model: FitModel,
    data: np.ndarray,
    tsky: np.ndarray,
    lsts: np.ndarray,
    edges: np.ndarray,
    **kwargs: Any,
) -> BlockSums:
    """Accumulate the normal sums of an in-memory chunk block by block.

    Parameters
    ----------
    model
        The fitted model (the blocks hold the sums of its :func:`extended_model`).
    data, tsky, lsts
        As for :func:`autocal.fit.lsq.accumulate` (the whole observation).
    edges
        Block boundaries from :func:`block_edges`.
    **kwargs
        Passed to :func:`autocal.fit.lsq.accumulate` (``flags``, ``weights``,
        ``bandwidth_time``, ``reference``); arrays ``(..., Ntime, Nfreq)`` are sliced per
        block.
    """
    from autocal.fit.lsq import accumulate

    tsky = np.asarray(tsky)
    ntime = data.shape[2]

    def part(value: Any, sl: slice) -> Any:
        if isinstance(value, np.ndarray) and value.ndim >= 2 and value.shape[-2] == ntime:
            return value[..., sl, :]  # (..., Ntime, Nfreq)
        return value

    ext = extended_model(model)
    blocks = []
    for b in range(len(edges) - 1):
        sl = slice(int(edges[b]), int(edges[b + 1]))
        tpart = tsky[..., sl, :]
        blocks.append(
            accumulate(
                ext,
                data[:, :, sl],
                tpart,
                lsts[sl],
                **{k: part(v, sl) for k, v in kwargs.items()},
            )
        )
    return BlockSums.from_extended(blocks, model, np.asarray(edges), np.asarray(lsts, np.float64))


def _median(x: np.ndarray) -> float | None:
    vals = np.asarray(x, np.float64)
    vals = vals[np.isfinite(vals)]
    return float(np.median(vals)) if vals.size else None


def separation_summary(solution: Any) -> list[dict[str, Any]]:
    """Per antenna and polarisation: how well ``G`` and ``n`` separate, and the error budget.

    Parameters
    ----------
    solution
        An :class:`autocal.fit.lsq.Solution` with a total uncertainty.

    Returns
    -------
    list of dict
        One entry per antenna-pol (medians over the solved channels): ``sky_contrast``,
        ``corr_G_n``, ``drift_sensitivity``, ``separation`` (``"weak"`` or ``"adequate"``),
        ``G``, ``sigma_G_frac`` and ``sigma_G_stat_frac`` (total and statistical 1-sigma
        over ``G``), ``jackknife_factor``, ``drift_weight``, ``G_halves``, ``G_if_trxr_K``
        (the profile: ``{Trxr: G}``) and ``message``, a sentence for people. Empty without
        a total uncertainty.
    """
    total = solution.total
    if total is None:
        return []
    out = []
    ok = ~solution.flags
    weak = total.separation()
    gain, trxr = solution.G, solution.Trxr  # properties: computed once, not per antenna
    with np.errstate(all="ignore"):
        frac_tot = solution.sigma_G / gain
        frac_stat = solution.sigma_G_stat / gain
    for ia, ant in enumerate(np.asarray(solution.antennas).tolist()):
        for ip, pol in enumerate(solution.pols):
            sel = ok[ia, ip]

            def med(arr: np.ndarray, ia: int = ia, ip: int = ip, sel: np.ndarray = sel) -> Any:
                return _median(arr[ia, ip][sel])

            profile = {
                f"{t:g}": _median(total.profile_G[ia, ip, i][sel])
                for i, t in enumerate(total.profile_trxr)
            }
            entry = {
                "antenna": int(ant),
                "pol": pol,
                "channels": int(sel.sum()),
                "G": med(gain),
                "Trxr_K": med(trxr),
                "sky_contrast": med(total.sky_contrast),
                "corr_G_n": med(total.corr_G_n),
                "drift_sensitivity": med(total.drift_sensitivity),
                "separation": "weak" if weak[ia, ip] else "adequate",
                "sigma_G_frac": med(frac_tot),
                "sigma_G_stat_frac": med(frac_stat),
                "jackknife_factor": med(total.jackknife_factor),
                "drift_weight": med(total.drift_weight),
                "G_halves": [_median(total.G_halves[h, ia, ip][sel]) for h in range(2)],
                "G_if_trxr_K": profile,
            }
            entry["message"] = _message(entry)
            out.append(entry)
    return out


def _message(e: dict[str, Any]) -> str:
    """One sentence on an antenna-pol's separation and error budget."""
    head = f"ant {e['antenna']} {e['pol']}: "
    if e["G"] is None:
        return head + "no solved channel"
    sens = e["drift_sensitivity"]
    text = head + (
        f"G = {e['G']:.4g} +- {100 * (e['sigma_G_frac'] or np.nan):.3g} % total "
        f"({100 * (e['sigma_G_stat_frac'] or np.nan):.2g} % statistical)"
    )
    if e["separation"] == "weak":
        trxr = e["Trxr_K"] if e["Trxr_K"] is not None else 150.0
        near = sorted(e["G_if_trxr_K"], key=lambda k: abs(float(k) - trxr))[:3]
        near = sorted(near, key=float)
        prof = ", ".join(
            f"{e['G_if_trxr_K'][k]:.4g} if Trxr = {k} K"
            for k in near
            if e["G_if_trxr_K"][k] is not None
        )
        text += (
            f"; weak separation: the sky varies by {100 * (e['sky_contrast'] or np.nan):.2g} % "
            f"of Tsys, so a 1 % gain drift over the span moves G by "
            f"{abs(sens or np.nan):.3g} %; G = {prof}"
        )
    return text
