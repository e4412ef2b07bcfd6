"""Inputs of the reference comparison's systematics budget, from the calibration's data.

With reference gains the comparison (:func:`autocal.compare.comparison.compare`) reports the
spread of the gain ratio over other sky models (:func:`alternative_solutions`, one more pass
over the data each) and the raw autos' trend over the span, taken from the time blocks'
sums the main fit already holds (:func:`block_trend`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from autocal.compare.drift import auto_trend
from autocal.fit.model import FitModel, mean_vectors
from autocal.fit.solution import Solution
from autocal.fit.solve import solve_sums
from autocal.fit.sums import NormalSums
from autocal.pipeline.config import CalibrationConfig
from autocal.pipeline.passes import PassesResult, solution_of, sum_passes
from autocal.pipeline.rfi import RfiMask
from autocal.pipeline.sources import Source, tsky_per_pol

#: Sky models whose fits the comparison's systematics budget sets beside the main one.
ALTERNATIVE_SKIES = (
    "gsm2008",
    "powerlaw:gsm2008@408:-2.5",
    "powerlaw:gsm2008@408:-2.55",
)


def alternative_solutions(
    config: CalibrationConfig,
    source: Source,
    pols: tuple[str, ...],
    model: FitModel,
    epoch: float,
    scaling: bool | str,
    block_size: int | None,
    prior_fn: Callable[..., NormalSums] | None = None,
    rfi: RfiMask | None = None,
) -> dict[str, Solution]:
    """Fit the data again with the other sky models of :data:`ALTERNATIVE_SKIES`.

    One pass over the data each (data-derived weights), with the main fit's receiver prior
    (``prior_fn``) and flags (``rfi``) if any; only for a comparison with reference gains,
    whose systematics budget reports the spread of the ratio over them.
    """
    out: dict[str, Solution] = {}
    for sky in ALTERNATIVE_SKIES:
        if sky == config.sky:
            continue
        tsky = tsky_per_pol(sky, config, source, pols, epoch)[0]
        alt = config.model_copy(update={"sky": sky, "passes": 1})
        run = sum_passes(
            alt, source, pols, tsky, model, lambda f, m: None, None, None, block_size, rfi
        )
        sums = run.sums
        if prior_fn is not None:
            sums = prior_fn(sums, *mean_vectors(model, source.lsts))
        solved = solve_sums(sums, scale_covariance=scaling)
        out[sky] = solution_of(
            model, run, solved, source, pols, {"calibration": alt.model_dump(mode="json")}
        )
    return out


def block_trend(
    run: PassesResult, source: Source, tsky_all: np.ndarray, pols: tuple[str, ...]
) -> dict[str, Any]:
    """Return the raw autos' trend over the span from the time blocks' sums.

    A block's weighted mean power is its sums' ``sum w R / sum w``; the first and the last
    block are the ends of :func:`autocal.compare.drift.auto_trend` (10 blocks: 10 % each).
    """
    blocks = run.blocks
    if blocks is None or blocks.nblocks < 2:
        return {}
    nb = blocks.model.nbasis
    power = []
    for part in blocks.blocks:
        with np.errstate(invalid="ignore", divide="ignore"):
            power.append(part.aty[..., nb] / part.ata[..., nb, nb])
    edges = blocks.edges
    spans = [slice(int(edges[b]), int(edges[b + 1])) for b in range(blocks.nblocks)]
    jds = np.array([source.jds[sl].mean() for sl in spans])
    tsky = np.stack([tsky_all[:, sl].mean(axis=1) for sl in spans], axis=1)  # (P, B, F)
    return auto_trend(
        np.stack(power, axis=2),  # (A, P, B, F)
        jds,
        run.antennas,
        list(pols),
        tsky=tsky,
        end_fraction=1.0 / blocks.nblocks,
    )
