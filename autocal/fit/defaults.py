"""The fit's defaults, shared by :func:`autocal.fit.passes.fit` and the pipeline's settings.

A module of constants only, so that :class:`autocal.pipeline.config.CalibrationConfig`
(parsed before a command-line usage error is reported) does not import the fit itself
(1.3 s: astropy's coordinates, the solution products).
"""

from __future__ import annotations

from typing import Literal

#: Radiometer weighting passes: ``"auto"`` (a second pass only when data weights would bias
#: ``G`` by more than :data:`autocal.fit.passes.REWEIGHT_THRESHOLD`), ``1`` or ``2``.
Passes = Literal["auto", 1, 2]
#: Default passes of every calibration (:class:`autocal.pipeline.config.CalibrationConfig` and
#: :func:`autocal.fit.passes.fit` both use it).
DEFAULT_PASSES: Passes = "auto"
#: Default: radiometer-weighted covariances are multiplied by ``max(1, chi^2/dof)`` so the
#: errors cover unmodelled structure (:class:`autocal.pipeline.config.CalibrationConfig` and
#: :func:`autocal.fit.passes.fit` both use it).
DEFAULT_INFLATE_ERRORS = True
