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
nothing in autocal reaches for the internet at run time. astropy itself is not imported by
``import autocal`` (it takes ~0.5-1 s): if it is already loaded it is configured at once,
otherwise as soon as it is first imported, by whoever imports it (autocal, pyuvdata or the
user): a meta-path hook (:data:`sys.meta_path`) runs the configuration when that import
returns (or, when an autocal module the configuration needs is the importer, when that
module's import returns).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from types import ModuleType
from typing import TYPE_CHECKING, Any

from autocal.errors import AutocalError

if TYPE_CHECKING:
    # importlib.abc imports importlib.resources, tempfile and random (~50 ms): the hook
    # below follows the finder and loader protocols without subclassing their ABCs.
    from importlib.abc import Loader
    from importlib.machinery import ModuleSpec

#: autocal modules :func:`autocal.core.offline.configure_offline` imports: it runs only
#: when none of them is half-way through its own import (one of them may be what imported
#: astropy).
_OFFLINE_NEEDS = frozenset(
    {"autocal.core.offline", "autocal.core.sites", "autocal.core.user_cache"}
)
#: Modules whose import is running under :class:`_ConfigureAfterImport`.
_EXECUTING: set[str] = set()
_offline_state = {"configured": False, "configuring": False, "sites": False}

#: astropy's coordinates, whose ``EarthLocation`` gets autocal's site registry when first
#: imported (importing them with astropy itself would cost every process ~0.3 s).
_COORDINATES = "astropy.coordinates"


class _ConfigureAfterImport:
    """A module's own loader, then :func:`_configure_when_ready` once the module is loaded."""

    def __init__(self, loader: Loader) -> None:
        self._loader = loader

    def __getattr__(self, name: str) -> Any:
        # get_code (runpy), is_package, get_resource_reader...: the module's own loader's.
        return getattr(self._loader, name)

    def create_module(self, spec: ModuleSpec) -> ModuleType | None:
        return self._loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        # The module keeps its own loader (importlib.resources and pickle look at it).
        module.__loader__ = self._loader
        if module.__spec__ is not None:
            module.__spec__.loader = self._loader
        _EXECUTING.add(module.__name__)
        try:
            self._loader.exec_module(module)
        finally:
            _EXECUTING.discard(module.__name__)
        _configure_when_ready()


class _OfflineImportHook:
    """Configure astropy offline right after it is first imported, without importing it here.

    Finds nothing itself: for ``astropy`` and autocal's own modules it asks the finders
    after it for the spec and wraps the loader (:class:`_ConfigureAfterImport`), so the
    configuration runs as soon as astropy is loaded and no module it needs is importing.
    It leaves :data:`sys.meta_path` once astropy is configured.
    """

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        if fullname not in ("astropy", _COORDINATES) and not fullname.startswith("autocal."):
            return None
        finders = sys.meta_path[sys.meta_path.index(self) + 1 :] if self in sys.meta_path else []
        for finder in finders:
            find = getattr(finder, "find_spec", None)
            spec = None if find is None else find(fullname, path, target)
            if spec is not None:
                if spec.loader is not None:
                    spec.loader = _ConfigureAfterImport(spec.loader)
                return spec
        return None


def _configure_when_ready() -> None:
    """Configure astropy offline once it is loaded and its configuration can be imported.

    That is: no module in :data:`_OFFLINE_NEEDS` is half-way through its import. The site
    registry follows once astropy's coordinates are loaded; then the hook leaves
    :data:`sys.meta_path`.
    """
    state = _offline_state
    if state["configuring"] or "astropy" not in sys.modules:
        return
    if "astropy" in _EXECUTING or _EXECUTING & _OFFLINE_NEEDS:
        return
    state["configuring"] = True
    try:
        from autocal.core import offline  # deferred: imports astropy

        if not state["configured"]:
            offline.configure_offline(sites=False)
            state["configured"] = True
        if not state["sites"] and _COORDINATES in sys.modules and _COORDINATES not in _EXECUTING:
            offline.configure_sites()
            state["sites"] = True
    finally:
        state["configuring"] = False
    if state["sites"]:
        sys.meta_path[:] = [f for f in sys.meta_path if not isinstance(f, _OfflineImportHook)]


if not any(isinstance(f, _OfflineImportHook) for f in sys.meta_path):
    sys.meta_path.insert(0, _OfflineImportHook())
_configure_when_ready()

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
    "configure_offline": "autocal.core.offline",
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


def _version() -> str:
    """Return the installed version (package metadata: ~0.1 s, so looked up on first use)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("autocal")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "0+unknown"


def __getattr__(name: str) -> Any:
    """Import a public name on first use (PEP 562); ``__version__`` is looked up then too."""
    if name == "__version__":
        globals()[name] = value = _version()
        return value
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'autocal' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
