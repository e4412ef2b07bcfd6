"""The functions ``import autocal`` offers: one path for every caller.

``autocal.read`` -> :class:`~autocal.core.observation.Observation`, ``autocal.compute_tsky`` ->
:class:`~autocal.tsky.result.TskyResult`, ``autocal.calibrate`` ->
:class:`~autocal.fit.solution.Solution`
(the function ``autocal calibrate``, the job service and nightly runs call, with the
defaults of :class:`~autocal.pipeline.config.CalibrationConfig`), ``autocal.diagnose`` (the
diagnosis stage, :func:`diagnose` here). The package imports them lazily
(``autocal.__getattr__``), so ``import autocal`` stays fast.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from os import PathLike
from pathlib import Path
from typing import Any

from autocal.core.observation import Observation
from autocal.diagnosis.run import DiagnoseConfig, run_diagnosis
from autocal.diagnosis.run import read_summary as read_diagnosis
from autocal.fit.solution import Solution
from autocal.pipeline.calibrate import calibrate, read, read_summary
from autocal.pipeline.config import CalibrationConfig
from autocal.tsky.compute import compute_tsky
from autocal.tsky.result import TskyResult

__all__ = [
    "CalibrationConfig",
    "Observation",
    "Solution",
    "TskyResult",
    "calibrate",
    "compute_tsky",
    "diagnose",
    "read",
    "read_summary",
]


def diagnose(
    inputs: str | PathLike[str] | Sequence[str | PathLike[str]] | Any,
    *,
    out: str | Path,
    progress: Callable[[float, str], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    **options: Any,
) -> dict[str, Any]:
    """Name the effects the model misses in one observation (``autocal.diagnose``).

    A thin wrapper of :func:`autocal.diagnosis.run.run_diagnosis`, the function behind
    ``autocal diagnose`` and the service's diagnose jobs.

    Parameters
    ----------
    inputs
        UVH5 file(s) of one observation, or a whole
        :class:`autocal.diagnosis.run.DiagnoseConfig`.
    out
        Output folder of the products.
    progress, should_stop
        Progress callback and cancellation poll, as for :func:`autocal.calibrate`.
    **options
        :class:`~autocal.diagnosis.run.DiagnoseConfig` fields (``antennas``, ``sky``,
        ``freq_range_mhz``, ``trxr_prior``, ``max_steps``...); their defaults otherwise.

    Returns
    -------
    dict
        The diagnosis summary (``effects``, ``steps``, gaps, ``products``...).
    """
    if isinstance(inputs, DiagnoseConfig):
        config = DiagnoseConfig(**{**inputs.model_dump(), **options})
    else:
        paths = [inputs] if isinstance(inputs, str | PathLike) else list(inputs)
        config = DiagnoseConfig(inputs=[str(p) for p in paths], **options)
    folder = run_diagnosis(config, out, progress=progress, should_stop=should_stop)
    return read_diagnosis(folder)
