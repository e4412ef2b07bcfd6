"""autocal: calibration of radio-telescope auto-correlations against sky models.

One import calibrates::

    import autocal

    sol = autocal.calibrate("zen.2458116.30448.HH.uvh5", antennas=[23])
    sol  # shown in a notebook: model, axes, ranges and medians (repr)
    sol.write("cal116", products=["calh5", "hdf5"])

``autocal.calibrate`` is the function ``autocal calibrate``, the job service and nightly
runs call (:func:`autocal.pipeline.calibrate.calibrate`); ``autocal.read``, ``autocal.compute_tsky``
and ``autocal.diagnose`` are the other stages (:mod:`autocal.api`). They are imported on
first use, so ``import autocal`` stays fast. Every error a user can cause is an
:class:`AutocalError`.

Importing the package configures astropy for offline use (see :mod:`autocal.core.offline`);
nothing in autocal reaches for the internet at run time.
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from autocal.core.offline import configure_offline
from autocal.errors import AutocalError

try:
    __version__ = version("autocal")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

configure_offline()

#: Public names imported on first use: name -> module that defines it.
_LAZY = {
    "calibrate": "autocal.pipeline.calibrate",
    "read": "autocal.pipeline.calibrate",
    "read_summary": "autocal.pipeline.calibrate",
    "CalibrationConfig": "autocal.pipeline.config",
    "compute_tsky": "autocal.tsky.compute",
    "TskyResult": "autocal.tsky.result",
    "Observation": "autocal.core.observation",
    "Solution": "autocal.fit.solution",
    "read_solution": "autocal.io.products",
    "diagnose": "autocal.api",
}

__all__ = [
    "AutocalError",
    "CalibrationConfig",
    "Observation",
    "Solution",
    "TskyResult",
    "__version__",
    "calibrate",
    "compute_tsky",
    "configure_offline",
    "diagnose",
    "read",
    "read_solution",
    "read_summary",
]


def __getattr__(name: str) -> Any:
    """Import a public name on first use (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'autocal' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
