"""Shared fixtures.

Tests that read the reference data folder request the ``data_root`` fixture: it skips
when the folder is absent on a developer machine, and FAILS under ``CI=true``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

# Keep the Tsky cache of the test session out of the user's cache.
if "AUTOCAL_CACHE_DIR" not in os.environ:
    os.environ["AUTOCAL_CACHE_DIR"] = "off"

from autocal.io.datasets import data_dir


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in {"1", "true", "yes"}


@pytest.fixture(scope="session")
def data_root() -> Path:
    """The reference data folder (``AUTOCAL_DATA_DIR`` or ``../shared/data``)."""
    root = data_dir()
    if root is None:
        message = "reference data folder not found: set AUTOCAL_DATA_DIR"
        if _in_ci():
            pytest.fail(message + " (required under CI=true)")
        pytest.skip(message)
    return root


@pytest.fixture(scope="session")
def lst_day() -> np.ndarray:
    """48 LSTs over 24 hours."""
    return np.linspace(0.0, 24.0, 49)[:-1]


@pytest.fixture
def tmp_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A private Tsky cache folder for one test."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("AUTOCAL_CACHE_DIR", str(folder))
    return folder
