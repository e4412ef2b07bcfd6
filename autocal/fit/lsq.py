"""Temporary re-exports for the layout merge."""

from autocal.fit.kernels import kernel_cache_dir  # noqa: F401
from autocal.fit.model import FitError, FitModel, design, unwrap_lsts, weights_for  # noqa: F401
from autocal.fit.passes import (  # noqa: F401
    DEFAULT_INFLATE_ERRORS,
    DEFAULT_PASSES,
    REWEIGHT_THRESHOLD,
    Passes,
    covariance_scaling,
    fit,
    run_passes,
)
from autocal.fit.solution import Solution  # noqa: F401
from autocal.fit.solve import FLAG_REASONS, solve_sums  # noqa: F401
from autocal.fit.sums import NormalSums, accumulate  # noqa: F401
