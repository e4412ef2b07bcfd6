"""On-disk cache of Tsky tables.

Tables are stored as HDF5 (:mod:`autocal.io.tskyfile`) under ``$AUTOCAL_CACHE_DIR``
(default ``~/.cache/autocal/tsky``), named by a SHA-256 of the sky, beam (including the
beam file's checksum), site, frequencies, LSTs, ground temperature, nside, epoch and
engine version. Set ``AUTOCAL_CACHE_DIR=off`` to disable caching.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)


def cache_dir() -> Path | None:
    """Return the cache folder, or ``None`` when caching is disabled."""
    env = os.environ.get("AUTOCAL_CACHE_DIR", "")
    if env.strip().lower() in {"off", "none", "0", "false"}:
        return None
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "autocal" / "tsky"


def cache_key(meta: dict[str, Any], freqs: np.ndarray, lsts: np.ndarray, tgnd: np.ndarray) -> str:
    """Hash everything that determines a Tsky table."""
    digest = hashlib.sha256()
    digest.update(json.dumps(meta, sort_keys=True, default=str).encode())
    for arr in (freqs, lsts, tgnd):
        digest.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    return digest.hexdigest()[:32]


def load(key: str) -> Any | None:
    """Return the cached table for ``key``, or ``None``."""
    from autocal.io.tskyfile import read_tsky

    folder = cache_dir()
    if folder is None:
        return None
    path = folder / f"{key}.h5"
    if not path.is_file():
        return None
    try:
        return read_tsky(path)
    except (ValueError, KeyError, OSError) as err:  # corrupt entry: drop it
        logger.warning("dropping unreadable cache entry %s (%s)", path, err)
        path.unlink(missing_ok=True)
        return None


def store(key: str, result: Any) -> Path | None:
    """Store a table under ``key`` (atomically); failures only log a warning."""
    from autocal.io.tskyfile import write_tsky

    folder = cache_dir()
    if folder is None:
        return None
    try:
        return write_tsky(folder / f"{key}.h5", result)
    except OSError as err:
        logger.warning("could not write Tsky cache entry in %s: %s", folder, err)
        return None
