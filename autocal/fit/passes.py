"""The weighting passes of every fit and the in-memory fit, the stage's public entry.

:func:`run_passes` is the one pass loop of autocal: the in-memory :func:`fit` and the
streamed :func:`autocal.pipeline.calibrate.run_calibration` both run through it, with the
same defaults (:data:`DEFAULT_PASSES`, :data:`DEFAULT_INFLATE_ERRORS`) and covariance
scaling (:func:`covariance_scaling`). :func:`fit` fits an observation and a Tsky array held
in memory: normal sums (:mod:`autocal.fit.sums`), per time block when the total uncertainty
is wanted (:mod:`autocal.fit.blocks`), an optional receiver prior
(:mod:`autocal.fit.priors`), the solve (:mod:`autocal.fit.solve`) and the total uncertainty
(:mod:`autocal.fit.total_uncertainty`), into a :class:`~autocal.fit.solution.Solution`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace
from typing import Any, Literal

import numpy as np

from autocal.core.observation import Observation
from autocal.fit.blocks import accumulate_blocks, block_edges, extended_model, sums_nbytes
from autocal.fit.defaults import DEFAULT_INFLATE_ERRORS, DEFAULT_PASSES, Passes
from autocal.fit.model import FitError, FitModel, check_tsky, design, mean_vectors, weights_for
from autocal.fit.priors import PriorTerm
from autocal.fit.solution import Solution
from autocal.fit.solve import FLAG_REASONS, solve_sums
from autocal.fit.sums import NormalSums, accumulate
from autocal.fit.total_uncertainty import total_uncertainty

logger = logging.getLogger(__name__)

#: Relative bias ``2 / (dnu dt N)`` of data-derived radiometer weights above which
#: ``passes="auto"`` makes a second, model-weighted pass.
REWEIGHT_THRESHOLD = 1e-5


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
    error inflation) are those of :class:`autocal.pipeline.config.CalibrationConfig`
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
        (:mod:`autocal.fit.total_uncertainty`: block jackknife and the model with one more time
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
    fit_model = _fit_model(obs, model, order)
    tsky = check_tsky(tsky, len(obs.pols), obs.ntime, obs.nfreq)
    is_radiometer = isinstance(weights, str) and weights == "radiometer"
    bt, bt_min = _bandwidth_time(obs) if is_radiometer else (None, np.inf)
    scale = (
        covariance_scaling(weights, inflate_errors)
        if scale_covariance is None
        else (scale_covariance)
    )
    edges = _uncertainty_edges(fit_model, obs, uncertainty)
    one_pass = _pass_function(fit_model, obs, tsky, weights, bt, bt_min, edges)
    (sums, blocks, reference), npass = run_passes(
        one_pass, passes=passes, radiometer=is_radiometer, min_samples=min_samples
    )
    prior_fn = _prior_function(trxr_prior, obs, scale)
    solved = _solve(sums, obs.lsts, prior_fn, min_samples, scale)
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


def _fit_model(obs: Observation, model: str | FitModel, order: int) -> FitModel:
    """Return the model to fit: ``model`` itself, or one of that kind spanning the LSTs."""
    if isinstance(model, FitModel):
        return model
    return FitModel.for_lsts(obs.lsts, model, 0 if model == "constant" else order)


def _bandwidth_time(obs: Observation) -> tuple[np.ndarray, float]:
    """``dnu dt N`` of every sample and its smallest value over the unflagged ones."""
    bt = obs.bandwidth_time()
    used = np.broadcast_to(~obs.flags, bt.shape)
    if not np.all(bt[used] > 0):
        raise FitError(
            "radiometer weights need positive channel width, integration time and "
            "nsamples; the observation lacks them: use weights='identity'"
        )
    return bt, float(np.min(bt, where=used, initial=np.inf))


def _uncertainty_edges(
    fit_model: FitModel, obs: Observation, uncertainty: str
) -> np.ndarray | None:
    """Return the time blocks of the total uncertainty (``None``: statistical errors only)."""
    if uncertainty not in ("total", "statistical"):
        raise FitError(f"uncertainty must be 'total' or 'statistical', got {uncertainty!r}")
    if uncertainty != "total":
        return None
    nbytes = sums_nbytes(extended_model(fit_model), obs.nant, len(obs.pols), obs.nfreq)
    return block_edges(obs.ntime, bytes_per_block=nbytes)


def _pass_function(
    fit_model: FitModel,
    obs: Observation,
    tsky: np.ndarray,
    weights: str | np.ndarray,
    bt: np.ndarray | None,
    bt_min: float,
    edges: np.ndarray | None,
) -> Callable[[np.ndarray | None, int, int], tuple[Any, NormalSums, float]]:
    """Return the ``one_pass`` of :func:`run_passes` for an observation in memory.

    Its result is ``(sums, blocks, reference)``: the fitted sums, the block sums (``None``
    without ``edges``) and the radiometer reference power (``None`` in the first pass).
    """

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

    return one_pass


def _prior_function(
    trxr_prior: Any, obs: Observation, scale: bool | Literal["inflate"]
) -> Callable[[NormalSums, np.ndarray, np.ndarray], NormalSums] | None:
    """``prior(sums, vg, vn) -> sums`` adding the receiver prior, or ``None`` without one."""
    if trxr_prior is None:
        return None
    if hasattr(trxr_prior, "at"):
        ptrxr, psigma = trxr_prior.at(obs.freqs, antennas=obs.antennas, pols=obs.pols)
    else:
        ptrxr, psigma = trxr_prior
    return PriorTerm(ptrxr, psigma, scale)


def _solve(
    sums: NormalSums,
    lsts: np.ndarray,
    prior_fn: Callable[[NormalSums, np.ndarray, np.ndarray], NormalSums] | None,
    min_samples: int | None,
    scale: bool | Literal["inflate"],
) -> dict[str, np.ndarray]:
    """Solve the fitted sums (with the prior, if any) and warn of unsolved channels."""
    solve_from = sums
    if prior_fn is not None:
        solve_from = prior_fn(sums, *mean_vectors(sums.model, lsts))
    solved = solve_sums(solve_from, min_samples=min_samples, scale_covariance=scale)
    _log_unsolved(solved)
    return solved


def _log_unsolved(solved: dict[str, np.ndarray]) -> None:
    """Warn of the channels that could not be solved, by reason."""
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


def _with_residuals(
    solution: Solution,
    obs: Observation,
    tsky: np.ndarray,
    weights: str | np.ndarray,
    reference: np.ndarray | None,
    bt: np.ndarray | None,
) -> Solution:
    """Return ``solution`` with its normalised residuals ``(R - model) / sigma``."""
    pred = solution.predict(tsky)
    usable = np.isfinite(obs.data) & ~obs.flags
    w = weights_for(weights, obs.data, usable, bt, pred if bt is not None else reference)
    if isinstance(weights, str) and weights == "identity":
        rms = np.sqrt(solution.reduced_chi2)[:, :, None, :]
        w = w / rms**2
    resid = np.where(usable, (obs.data - pred) * np.sqrt(w), np.nan)
    return replace(solution, residuals=resid)
