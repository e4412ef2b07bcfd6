"""Total uncertainties: statistics, correlated residuals and what a short span cannot decide.

The covariance of a least-squares fit (:func:`autocal.fit.solve.solve_sums`) is honest only when
the model is right and the residuals are independent radiometer noise. On real data neither
holds, and over a short span a third problem dominates: the sky changes by a few per cent of
the system temperature (or less), so a gain that drifts by a fraction of a per cent is
indistinguishable from a different ``(G, n)``. This module turns per-block normal sums into a
*total* 1-sigma that covers all three, without a second pass over the data.

Blocks
    The integrations are split into ``B`` contiguous time blocks
    (:func:`autocal.fit.blocks.block_edges`) and the normal sums of the fitted model are kept
    per block (:class:`autocal.fit.blocks.BlockSums`), those of the model with one more order
    once. The ordinary fit is the lower orders of the latter
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
    channels' statistics: a drifting gain drifts at every frequency; a channel whose fit is
    flagged, e.g. a non-positive gain, has no statistic and takes no part). Both models are
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

Numerics
    Every solve and inverse here (the fit, the jackknife refits and halves, the extended
    fit, the expected jackknife's refit inverses) is done in the sky-centred frame of
    :mod:`autocal.fit.centring` (:func:`autocal.fit.solve.solve_sums`), and so is the chi2
    drop ``dx^T A dx``. Over a short span ``Tsky P_k`` is nearly ``c P_k``: on a 10-minute
    HERA file the extended model's column-scaled normal matrix has a condition number of
    ~5e10 (up to 4e13) in the original frame, and solving there moved individual channels'
    total ``sigma_G`` by up to x300 against exact rational solves of the same float64 sums
    (median 27 %): the extended fit kept ~6 digits (1e-6 median, 6e-4 at worst), enough to
    flip ``w_1`` between 0 and 1 and to flag ~2 % of the extended fits as singular. Centred
    (condition ~5e5, up to 2e9), the same comparison on the nine 10-minute files of JD
    2458043-45 (2846 channels) gives the extended fit to 1e-10 (median; 1e-6 at worst) and
    the total ``sigma_G`` to 6e-10 (7e-7 at worst). The float64 sums themselves are only
    as exact as their accumulation: moving each of them by ~1 ulp (as another summation
    order may) moves the extended solution by 4e-6 (median; 1e-2 at worst) whatever the
    solver, and now the total ``sigma_G`` by 2e-6 (5e-3 at worst; before: x600). The
    jackknife factor's 2 x 2 covariances are formed in the basis ``(G, n + c G)`` of that
    frame (the trace ``tr(E^-1 V_jk)`` is the same in any basis): in ``(G, n)`` their
    condition number reaches ~1e15 on a short span, and a Legendre-1 fit over ten minutes
    had ``f_jk`` move by 46 % (median, up to x12) when the data were scaled by
    ``1 + 3.6e-15``; now by < 2.1e-5 (``tests/fit/test_total_uncertainty.py`` requires
    < 1e-4).

Assumptions: the blocks are long compared with the correlation time of the residuals (else
the jackknife under-estimates); an unmodelled drift is smooth enough over the span for one
more Legendre order to represent it; the BIC weights assume the residual scatter is the same
in both models up to the factor ``phi``. Errors with no time signature (a sky model's
spectrum, a flux scale) are not covered: they belong to a systematics budget
(:mod:`autocal.compare.comparison`).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np
from scipy.special import erfcx, log_ndtr
from threadpoolctl import threadpool_limits

from autocal.core.reprs import compact_repr
from autocal.fit.blocks import (
    MIN_BLOCKS,
    BlockSums,
    base_index,
    extended_model,
    subtract_sums,
)
from autocal.fit.centring import centre, sky_mean
from autocal.fit.finite import finite_trailing
from autocal.fit.model import FitModel, mean_vectors
from autocal.fit.separation import (
    WEAK_SENSITIVITY,
    drift_sensitivity,
    nanmedian_last,
    profile_gain,
    profile_grid,
    sky_contrast,
)
from autocal.fit.solve import solve_sums
from autocal.fit.sums import NormalSums, antenna_blocks, default_threads
from autocal.fit.threads import in_threads

logger = logging.getLogger(__name__)

#: A description of the method, recorded in the products.
METHOD = (
    "total = jackknife-scaled statistical covariance averaged (BIC weights) with the model of "
    "one more time order, plus the weighted difference of the two estimates"
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
        return compact_repr(self)

    def separation(self) -> np.ndarray:
        """``(Nant, Npol)`` ``True`` where ``G`` and ``n`` separate weakly.

        Weak: the median over channels of :attr:`drift_sensitivity` exceeds
        :data:`WEAK_SENSITIVITY` (a 1 % gain drift over the span would move ``G`` by more
        than 10 %).
        """
        with np.errstate(all="ignore"):
            med = nanmedian_last(np.abs(self.drift_sensitivity))
        return med > WEAK_SENSITIVITY  # NaN (nothing solved) is not "weak"

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description of the method and its settings."""
        return {
            "method": METHOD,
            "blocks": self.nblocks,
            "jackknife": self.nblocks >= MIN_BLOCKS,
            "notes": list(self.notes),
        }


def _project(
    coeffs: np.ndarray, cov: np.ndarray | None, vg: np.ndarray, vn: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None]:
    """Time-averaged ``(G, n)`` and their 2 x 2 covariance from parameters.

    Matrix-vector products (BLAS) rather than one ``einsum`` over the batch: ~10x faster
    for a HERA file's million channels. Without ``cov`` (the refits, whose means are all
    the jackknife uses) only the means; the covariance is filled in place rather than
    stacked (the stacking took two thirds of the time).
    """
    theta = np.stack([coeffs @ vg, coeffs @ vn], axis=-1)
    if cov is None:
        return theta, None
    cvg = np.tensordot(cov, vg, axes=([-1], [0]))  # (..., M)
    cvn = np.tensordot(cov, vn, axes=([-1], [0]))
    cgn = cvg @ vn
    c2 = np.empty((*theta.shape, 2))
    c2[..., 0, 0] = cvg @ vg
    c2[..., 0, 1] = cgn
    c2[..., 1, 0] = cgn
    c2[..., 1, 1] = cvn @ vn
    return theta, c2


@dataclass(frozen=True, eq=False)
class _Refits:
    """How :func:`total_uncertainty` solves and projects its refits (all alike)."""

    scale_covariance: bool | Literal["inflate"]
    prior: Any
    vg: np.ndarray
    vn: np.ndarray
    evg: np.ndarray
    evn: np.ndarray

    def solve(self, sums: NormalSums) -> dict[str, np.ndarray]:
        """Refit the fitted model from ``sums`` (with the prior, if any)."""
        if self.prior is not None:
            sums = self.prior(sums, self.vg, self.vn)
        return solve_sums(sums, scale_covariance=self.scale_covariance, positive_gain=False)

    def project(
        self, res: dict[str, np.ndarray], ext: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Time-averaged ``(G, n)`` and covariance of a (fitted or ``ext``ended) solution."""
        theta, cov = _project(
            res["coeffs"], res["cov"], *((self.evg, self.evn) if ext else (self.vg, self.vn))
        )
        assert cov is not None
        return theta, cov

    def means(self, res: dict[str, np.ndarray]) -> np.ndarray:
        """Time-averaged ``(G, n)`` of a refit (its covariance is not needed)."""
        return _project(res["coeffs"], None, self.vg, self.vn)[0]


def total_uncertainty(
    blocks: BlockSums,
    solved: dict[str, np.ndarray],
    *,
    scale_covariance: bool | Literal["inflate"] = "inflate",
    prior: Any = None,
    threads: int | None = None,
) -> TotalUncertainty:
    """Compute the total uncertainty of a solution from its block sums.

    Every quantity is per antenna-pol and channel but for the profile's grid of receiver
    temperatures (:func:`~autocal.fit.separation.profile_grid`, from all channels), so the
    antennas are done in parts of about :data:`PART_SYSTEMS` channels on threads
    (:func:`autocal.fit.threads.in_threads`, BLAS on one thread meanwhile): the numpy steps
    run side by side, and the temporaries are a part's, not the observation's (a HERA
    file's were ~0.7 GB). With fewer parts than threads (a few antennas, EDGES), or a prior
    that cannot be cut by antenna, the whole is one part and its compiled kernels use the
    threads. The values are those of one part, bit for bit
    (``tests/fit/test_total_uncertainty.py``).

    Parameters
    ----------
    blocks
        Per-block normal sums of the extended model.
    solved
        :func:`autocal.fit.solve.solve_sums` output of ``blocks.fitted_total()`` (with the
        same ``scale_covariance`` and prior): the reported solution.
    scale_covariance
        As given to :func:`~autocal.fit.solve.solve_sums` for the reported solution; the
        refits use the same.
    prior
        Optional callable ``prior(sums, vg, vn) -> sums`` adding a receiver prior's
        pseudo-observation to a set of sums, ``vg`` and ``vn`` the vectors that give the
        time-averaged ``G`` and ``n`` from the parameters (applied to every refit alike).
        One with an ``antennas(lo, hi)`` method giving the prior of antennas ``lo`` to
        ``hi - 1`` (:class:`autocal.fit.priors.PriorTerm`) lets the antennas be done in
        parts; any other is applied to all antennas at once.
    threads
        Threads for the parts (default :func:`~autocal.fit.sums.default_threads`).

    Returns
    -------
    TotalUncertainty
        The total covariance of the time-averaged ``(G, n)`` and its parts.
    """
    model = blocks.model
    lsts = blocks.lsts
    vg, vn = mean_vectors(model, lsts)
    evg, evn = mean_vectors(extended_model(model), lsts)
    lead = solved["chi2"].shape
    grid = profile_grid(_project(solved["coeffs"], None, vg, vn)[0])
    nthreads = default_threads() if threads is None else max(1, int(threads))
    per_antenna = max(1, int(np.prod(lead[1:])))
    # parts start at multiples of 4 antennas: BLAS's groups of rows line up with the whole's
    per = -(-max(1, PART_SYSTEMS // per_antenna) // 4) * 4
    parts = antenna_blocks(lead[0], per)
    splittable = prior is None or callable(getattr(prior, "antennas", None))
    if len(parts) < nthreads or not splittable:
        parts = [(0, lead[0])]  # one part: its own kernels run on the threads
    out = _empty(lead, grid.size)
    unsolvable = np.zeros(len(parts), np.int64)

    def run(i0: int, i1: int) -> None:
        for i in range(i0, i1):
            lo, hi = parts[i]
            whole = (lo, hi) == (0, lead[0])
            part_prior = prior if prior is None or whole else prior.antennas(lo, hi)
            refits = _Refits(scale_covariance, part_prior, vg, vn, evg, evn)
            sub = {k: v[lo:hi] if _per_channel(v, lead) else v for k, v in solved.items()}
            unsolvable[i] = _total_part(
                blocks if whole else blocks.antennas(lo, hi), sub, refits, grid, out, lo, hi
            )

    if len(parts) == 1:
        run(0, 1)
    else:  # the parts are the parallelism: BLAS's own threads would only spin beside them
        with _BLAS_LIMIT, threadpool_limits(limits=1, user_api="blas"):
            in_threads(run, len(parts), nthreads)
    notes: list[str] = []
    if blocks.nblocks < MIN_BLOCKS:
        notes.append(
            f"no jackknife: {len(lsts)} integrations make fewer than {MIN_BLOCKS} blocks of two "
            "or more (or their sums would not fit in memory); the total has no term for "
            "residuals correlated in time"
        )
    if unsolvable.sum():
        notes.append(
            f"{int(unsolvable.sum())} solved channels could not take one more time order "
            "(too few samples or a singular system): no drift term there"
        )
    return TotalUncertainty(
        **out,
        profile_trxr=grid,
        nblocks=blocks.nblocks,
        notes=tuple(notes),
    )


#: Channels (antennas x pols x frequencies) per part of :func:`total_uncertainty`.
PART_SYSTEMS = 1 << 16
#: Held while BLAS is limited to one thread: the limit is process-wide, so two calls on
#: different threads must not interleave their set and restore.
_BLAS_LIMIT = threading.Lock()


def _per_channel(value: Any, lead: tuple[int, ...]) -> bool:
    """Whether ``value`` is an array with the ``(Nant, Npol, Nfreq)`` leading axes."""
    return isinstance(value, np.ndarray) and value.shape[: len(lead)] == lead


#: The arrays of a :class:`TotalUncertainty` that :func:`_total_part` fills, part by part.
_PER_CHANNEL = tuple(
    f.name for f in fields(TotalUncertainty) if f.name not in ("profile_trxr", "nblocks", "notes")
)


def _empty(lead: tuple[int, ...], ngrid: int) -> dict[str, np.ndarray]:
    """Return NaN arrays for :data:`_PER_CHANNEL`, ``lead = (Nant, Npol, Nfreq)``."""
    nant, npol, nfreq = lead
    shapes = {"cov": (*lead, 2, 2), "G_halves": (2, *lead), "profile_G": (nant, npol, ngrid, nfreq)}
    return {name: np.full(shapes.get(name, lead), np.nan) for name in _PER_CHANNEL}


def _total_part(
    blocks: BlockSums,
    solved: dict[str, np.ndarray],
    refits: _Refits,
    grid: np.ndarray,
    out: dict[str, np.ndarray],
    lo: int,
    hi: int,
) -> int:
    """Fill antennas ``lo`` to ``hi - 1`` of ``out`` (:func:`total_uncertainty` of them).

    Returns the number of solved channels that could not take one more time order.
    """
    model = blocks.model
    fitted = blocks.fitted_total()
    theta0, c0 = refits.project(solved)
    c0_ok = finite_trailing(c0, 2)
    sl = slice(lo, hi)
    # delete-a-block jackknife of the fitted model, and its two halves
    fjk = np.full(c0_ok.shape, np.nan)
    if blocks.nblocks >= MIN_BLOCKS:
        fjk = _jackknife_factor(blocks, fitted, solved, refits, c0_ok)
        out["G_halves"][:, sl] = _half_estimates(blocks, refits)
    out["jackknife_factor"][sl] = fjk
    # the model with one more time order (exact: the blocks hold its sums)
    drift = _drift_model(blocks, solved, refits, theta0, c0, c0_ok)
    w1, theta1, c1, good = drift.weight, drift.theta, drift.cov, drift.good
    out["cov"][sl] = _total_covariance(fjk, drift, theta0, c0, c0_ok)
    bad = ~c0_ok
    out["drift_weight"][sl] = np.where(bad, np.nan, w1)
    out["G_drift"][sl] = np.where(bad | ~good, np.nan, theta1[..., 0])
    out["n_drift"][sl] = np.where(bad | ~good, np.nan, theta1[..., 1])
    out["sigma_G_drift"][sl] = np.where(bad | ~good, np.nan, np.sqrt(np.abs(c1[..., 0, 0])))
    out["sky_contrast"][sl] = np.where(bad, np.nan, sky_contrast(fitted, model, theta0))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = c0[..., 0, 1] / np.sqrt(c0[..., 0, 0] * c0[..., 1, 1])
    out["corr_G_n"][sl] = np.where(bad, np.nan, corr)
    sens = drift_sensitivity(blocks.total(), model, theta0, refits.vg)
    out["drift_sensitivity"][sl] = np.where(bad, np.nan, sens)
    out["profile_G"][sl] = profile_gain(fitted, model, refits.vg, grid)
    return int((~good & c0_ok).sum())


def _jackknife_factor(
    blocks: BlockSums,
    fitted: NormalSums,
    solved: dict[str, np.ndarray],
    refits: _Refits,
    c0_ok: np.ndarray,
) -> np.ndarray:
    """``f_jk``: the delete-a-block jackknife covariance over the one the statistics predict.

    NaN where undefined (fewer than :data:`~autocal.fit.blocks.MIN_BLOCKS` refits solved,
    no statistical covariance or no prediction).
    """
    nblk = blocks.nblocks
    lead = solved["chi2"].shape
    reps = np.empty((nblk, *lead, 2))
    for b, part in enumerate(blocks.blocks):
        reps[b] = refits.means(refits.solve(subtract_sums(fitted, part)))
    # the refits as (G, n + c G), the sky-centred frame's time-averaged parameters (the
    # product exact): the trace below is the same in any basis, but on a short span the
    # covariance of (G, n) is too ill-conditioned to invert (condition ~1e15 for a
    # Legendre-1 fit of a 10-minute HERA file, where f_jk changed by 43 % between two
    # solvers exact to rounding)
    c = sky_mean(fitted.ata)
    nb = refits.vg.size // 2  # the mapping needs vn's offsets to weigh as vg's gains do
    assert np.array_equal(refits.vn[nb:], refits.vg[:nb]) and not refits.vn[:nb].any()
    from autocal.fit.centring_kernel import minus_product_array  # numba

    with np.errstate(invalid="ignore"):
        reps[..., 1] = minus_product_array(reps[..., 1], -c, reps[..., 0])
    ok = finite_trailing(reps)  # (B, ...)
    nok = ok.sum(axis=0)
    # in place (the values of np.where(ok, reps, 0) and np.where(ok, reps - mean, 0); no
    # copies of the refits, 86 MB each for a HERA-size file)
    bad = ~ok[..., None]
    np.copyto(reps, 0.0, where=bad)
    mean = reps.sum(axis=0) / np.maximum(nok, 1)[..., None]
    reps -= mean
    np.copyto(reps, 0.0, where=bad)
    dev = reps
    frac = (nok - 1) / np.maximum(nok, 1)
    vjk = frac[..., None, None] * np.einsum("b...i,b...j->...ij", dev, dev)
    # against the jackknife covariance the statistical model itself predicts (the
    # delete-a-block estimator over-weights the ends of a time model: a Legendre fit's
    # refits extrapolate), times the chi2/dof scaling the statistical covariance has
    expected = expected_jackknife(blocks, fitted, refits.prior, refits.vg, refits.vn, c=c)
    scaling = _covariance_scaling(solved, refits.scale_covariance)
    einv = _inv2(np.where(np.isfinite(expected), expected, np.eye(2)))
    with np.errstate(divide="ignore", invalid="ignore"):
        fjk = np.einsum("...ij,...ji->...", einv, vjk) / 2.0 / scaling
    good_e = finite_trailing(expected, 2) & (scaling > 0)
    return np.where((nok >= MIN_BLOCKS) & c0_ok & good_e, fjk, np.nan)


def _half_estimates(blocks: BlockSums, refits: _Refits) -> np.ndarray:
    """``(2, ...)`` the span's mean ``G`` from the first and from the second half of the blocks."""
    nblk = blocks.nblocks
    halves = np.full((2, *blocks.blocks[0].count.shape), np.nan)
    half = nblk // 2
    for h, ids in enumerate((range(half), range(half, nblk))):
        sub = blocks.blocks[ids[0]]
        for b in ids[1:]:
            sub = sub + blocks.blocks[b]
        # the span's mean G estimated from each half's data (for a time model, each
        # half's fit evaluated over the whole span; its own half's mean is no better
        # determined: measured on a clean day, order 1, 23 % against 3 % off)
        halves[h] = refits.means(refits.solve(sub))[..., 0]
    return halves


def _total_covariance(
    fjk: np.ndarray, drift: _Drift, theta0: np.ndarray, c0: np.ndarray, c0_ok: np.ndarray
) -> np.ndarray:
    """``C_tot = max(1, f_jk) [w_0 C_0 + w_1 C_1] + w_1 d d^T`` (NaN without ``C_0``)."""
    w1, theta1, c1 = drift.weight, drift.theta, drift.cov
    scale = np.where(np.isfinite(fjk), np.maximum(fjk, 1.0), 1.0)[..., None, None]
    d = np.nan_to_num(theta1 - theta0)
    w1e = w1[..., None, None]
    ctot = scale * ((1.0 - w1e) * c0 + w1e * c1) + w1e * np.einsum("...i,...j->...ij", d, d)
    return np.where(c0_ok[..., None, None], ctot, np.nan)


@dataclass(frozen=True, eq=False)
class _Drift:
    """The model with one more time order, as :func:`total_uncertainty` mixes it in."""

    weight: np.ndarray  # w_1 (0 where undefined)
    theta: np.ndarray  # (..., 2) its time-averaged (G, n), G > 0 (theta0 where undefined)
    cov: np.ndarray  # (..., 2, 2) their covariance (0 where undefined)
    good: np.ndarray  # where it is defined


def _drift_model(
    blocks: BlockSums,
    solved: dict[str, np.ndarray],
    refits: _Refits,
    theta0: np.ndarray,
    c0: np.ndarray,
    c0_ok: np.ndarray,
) -> _Drift:
    """Fit the model with one more time order and weigh it against the fitted one (BIC)."""
    model, total = blocks.model, blocks.total()
    scale_covariance, prior = refits.scale_covariance, refits.prior
    ext_sums = total if prior is None else prior(total, refits.evg, refits.evn)
    ext = solve_sums(ext_sums, scale_covariance=scale_covariance, positive_gain=False)
    theta1, c1 = refits.project(ext, ext=True)
    del ext["cov"]  # projected: (Nant, Npol, Nfreq, M, M) not held through the rest
    dof1 = ext["dof"]
    count = total.count.astype(np.float64)
    dchi2 = _chi2_drop(ext["coeffs"], solved["coeffs"], ext_sums.ata, model)
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
    good = np.isfinite(stat) & finite_trailing(theta1)
    good &= finite_trailing(c1, 2)
    # per channel, and for each antenna-pol as a whole (a drifting gain drifts at every
    # frequency; channels that cannot see it alone are told by the others)
    stat = np.where(good, stat, 0.0)
    joint = np.where(good.any(axis=-1), stat.sum(axis=-1), -np.inf)[..., None]
    w1 = np.maximum(_logistic(stat / 2.0), _logistic(joint / 2.0))
    return _Drift(
        weight=np.where(good, w1, 0.0),
        theta=np.where(good[..., None], theta1, theta0),
        cov=np.where(good[..., None, None], c1, 0.0),
        good=good,
    )


def _chi2_drop(
    ext_coeffs: np.ndarray, coeffs: np.ndarray, ext_ata: np.ndarray, model: FitModel
) -> np.ndarray:
    """Return the chi2 drop of nested least squares from the fitted to the extended model.

    ``dx^T A_ext dx`` (``dx``: the extended solution less the fitted one embedded) rather
    than a difference of two chi2 that are each a small difference of large sums. Evaluated
    in the sky-centred frame (:func:`autocal.fit.centring_kernel.quadratic_forms`): ``dx`` lies near
    the null direction of ``A_ext`` on a short span, where the plain quadratic form keeps
    only ~6 digits (errors up to ~1 in statistics of ~1e3 on 10-minute HERA files). NaN
    where either solution is not finite: without the fitted solution (e.g. a non-positive
    gain) the extended one's extra coefficients alone are no chi2 drop.
    """
    from autocal.fit.centring_kernel import quadratic_forms  # numba, imported when needed

    embedded = np.zeros_like(ext_coeffs)
    embedded[..., base_index(model)] = coeffs
    dx = ext_coeffs - embedded
    finite = finite_trailing(dx)
    return np.where(finite, quadratic_forms(np.where(finite[..., None], dx, 0.0), ext_ata), np.nan)


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
    """Return the factor :func:`~autocal.fit.solve.solve_sums` applied to each covariance."""
    if not scale_covariance:
        return np.ones(solved["chi2"].shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(solved["dof"] > 0, solved["chi2"] / solved["dof"], np.nan)
    if scale_covariance == "inflate":
        factor = np.maximum(np.nan_to_num(factor, nan=1.0), 1.0)
    return factor


def expected_jackknife(
    blocks: BlockSums,
    fitted: NormalSums,
    prior: Any,
    vg: np.ndarray,
    vn: np.ndarray,
    *,
    c: np.ndarray | None = None,
) -> np.ndarray:
    """Return the jackknife covariance of ``(G, n + c G)`` the statistical model predicts.

    The algebra is :func:`expected_jackknife_numpy`'s; computed channel by channel by the
    compiled :func:`autocal.fit.jackknife_kernel.expected_jackknife` (~20 x faster on a
    HERA file's million 2 x 2 systems). ``c``: the sky mean of the frame
    (default :func:`autocal.fit.centring.sky_mean` of ``fitted``).
    """
    from autocal.fit.jackknife_kernel import expected_jackknife as kernel  # numba

    p = None if prior is None else prior(fitted, vg, vn).ata - fitted.ata
    parts = [part.ata for part in blocks.blocks]
    c = sky_mean(fitted.ata) if c is None else c
    return kernel(fitted.ata, parts, p, np.stack([vg, vn]), c)


def expected_jackknife_numpy(
    blocks: BlockSums,
    fitted: NormalSums,
    prior: Any,
    vg: np.ndarray,
    vn: np.ndarray,
    *,
    c: np.ndarray | None = None,
) -> np.ndarray:
    """Return the jackknife covariance of ``(G, n + c G)`` the statistical model predicts.

    Everything is computed in the sky-centred frame of one ``c`` per channel
    (:mod:`autocal.fit.centring`; default the sky mean of ``fitted``), whose time-averaged
    offset is ``n + c G``: the covariance of ``(G, n)`` itself is, on a short span, too
    ill-conditioned to be inverted afterwards (``R^-1 E R^-T`` gives it, ``R = [[1, 0],
    [c, 1]]``).

    With inverse-variance weights a block's right-hand side has covariance ``A_b`` (its
    normal matrix) and blocks are independent; the refit without block ``b`` is
    ``x_b = K_b (v - v_b)``, ``K_b = (A - A_b + P)^-1`` (``P``: the prior's rows, noiseless),
    so ``Cov(x_b, x_c) = K_b (A - A_b - A_c + delta_bc A_b) K_c``. With ``Y_b`` the projection
    of ``K_b`` onto the time-averaged ``(G, n)`` the expectation of the jackknife estimator
    ``(B-1)/B sum_b (t_b - tbar)(t_b - tbar)^T`` needs only sums over blocks:
    ``(B-1)/B [sum_b Y_b (A - A_b) Y_b^T - (Ysum A Ysum^T - sum_b Y_b A_b Ysum^T -
    Ysum sum_c A_c Y_c^T + sum_b Y_b A_b Y_b^T) / B]``. As numpy batched array operations:
    the reference of the compiled :func:`expected_jackknife`.
    """
    nblk = blocks.nblocks
    c = sky_mean(fitted.ata) if c is None else np.asarray(c, np.float64)
    a = centre(fitted.ata, c)
    p = 0.0
    if prior is not None:
        p = prior(fitted, vg, vn).ata - fitted.ata
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
            rest = centre(fitted.ata - part.ata + p, c)
            ab = centre(part.ata, c)
            ok = finite_trailing(rest, 2) & (np.linalg.det(rest) != 0)
            inv = np.linalg.inv(np.where(ok[..., None, None], rest, eye))
            k = np.where(ok[..., None, None], inv, np.nan)
            y = proj @ k  # (..., 2, M)
            yt = np.swapaxes(y, -1, -2)
            yab = y @ ab
            ysum += y
            own += (y @ (a - ab)) @ yt
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
