"""autocal: calibration of radio-telescope auto-correlations against sky models.

One import calibrates::

    import autocal

    sol = autocal.calibrate("zen.2458116.30448.HH.uvh5", antennas=[23])
    print(sol)  # model, axes, ranges and medians
    sol.write("cal116", products=["calh5", "hdf5"])

``autocal.calibrate`` is the function ``autocal calibrate``, the job service and nightly
runs call (:func:`autocal.pipeline.calibrate`); ``autocal.read``, ``autocal.compute_tsky``
and ``autocal.diagnose`` are the other stages (:mod:`autocal.api`). They are imported on
first use, so ``import autocal`` stays fast. Every error a user can cause is an
:class:`AutocalError`.

Importing the package configures astropy for offline use (see :mod:`autocal.offline`);
nothing in autocal reaches for the internet at run time.
"""

from __future__ import annotations

import importlib
import sys
import types
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from autocal.errors import AutocalError
from autocal.offline import configure_offline

try:
    __version__ = version("autocal")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

configure_offline()

#: Public names imported on first use: name -> module that defines it.
_LAZY = {
    "calibrate": "autocal.pipeline",
    "read": "autocal.pipeline",
    "read_summary": "autocal.pipeline",
    "CalibrationConfig": "autocal.pipeline",
    "compute_tsky": "autocal.tsky",
    "TskyResult": "autocal.tsky",
    "Observation": "autocal.observation",
    "Solution": "autocal.fit",
    "read_solution": "autocal.io.products",
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
    if name == "diagnose":  # the module autocal.diagnose, callable as autocal.api.diagnose
        return importlib.import_module("autocal.diagnose")
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'autocal' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


class _DiagnoseModule(types.ModuleType):
    """The module :mod:`autocal.diagnose`, also callable as :func:`autocal.api.diagnose`.

    ``autocal.diagnose`` names both the diagnosis module and the top-level function; a
    submodule is bound to its package's attribute whenever it is imported, so the module
    itself is made callable. ``autocal.diagnose(...)`` runs the diagnosis and
    ``autocal.diagnose.DiagnoseError`` (and every other name) stay the module's.
    """

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        from autocal.api import diagnose

        return diagnose(*args, **kwargs)


class _Package(types.ModuleType):
    """The ``autocal`` package: makes the :mod:`autocal.diagnose` module callable on import."""

    def __setattr__(self, name: str, value: Any) -> None:
        if (
            name == "diagnose"
            and isinstance(value, types.ModuleType)
            and type(value) is types.ModuleType
        ):
            value.__class__ = _DiagnoseModule
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
