"""Modules imported on first use: healpy for the sky and beam code.

``import healpy`` takes 0.7-1 s in a fresh process (it imports matplotlib and astropy). A
calibration whose Tsky comes from the cache never calls it, yet every module of the Tsky
stage imported it at the top. These modules bind the name to a :class:`LazyModule` instead;
the real module is imported the first time one of its attributes is used.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any


class LazyModule:
    """A stand-in for a module that imports it when one of its attributes is first read.

    Parameters
    ----------
    name
        The module's import name, e.g. ``"healpy"``.
    """

    def __init__(self, name: str) -> None:
        self._name = name

    def _module(self) -> ModuleType:
        return importlib.import_module(self._name)  # a dictionary look-up once imported

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._module(), attr)

    def __repr__(self) -> str:
        """Return which module this stands in for."""
        return f"<lazy module {self._name!r}>"


#: healpy, imported when first used.
healpy = LazyModule("healpy")
