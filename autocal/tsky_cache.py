"""On-disk cache of the Tsky engine's output.

What is cached is the LST-free part, :class:`autocal.tsky.TskyHarmonics` (Tsky's Fourier
series in LST and the beam integrals), not tables: one entry then gives the table for
any LST grid and ground temperature with one inverse FFT, so every observation of a night
(the same sky frame, :func:`autocal.coords.night_epoch`) reuses the first one's. Entries
are HDF5 (:func:`autocal.io.tskyfile.write_harmonics`; 3.2 MB per polarisation for 1536
channels at nside 64, the default, 6.3 MB at nside 128) under ``$AUTOCAL_CACHE_DIR``
(default ``~/.cache/autocal/tsky``), named by a SHA-256 of the sky, beam (including the
beam file's checksum), site, frequencies, nside, epoch, horizon and engine version. Set
``AUTOCAL_CACHE_DIR=off`` to disable caching.
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


def cache_key(meta: dict[str, Any], freqs: np.ndarray) -> str:
    """Hash everything that determines the harmonics: their description and frequencies."""
    digest = hashlib.sha256()
    digest.update(json.dumps(meta, sort_keys=True, default=str).encode())
    digest.update(np.ascontiguousarray(freqs, dtype=np.float64).tobytes())
    return digest.hexdigest()[:32]


def load(key: str) -> Any | None:
    """Return the cached harmonics for ``key``, or ``None``."""
    from autocal.io.tskyfile import read_harmonics

    folder = cache_dir()
    if folder is None:
        return None
    path = folder / f"{key}.h5"
    if not path.is_file():
        return None
    try:
        return read_harmonics(path)
    except (ValueError, KeyError, OSError) as err:  # corrupt entry: drop it
        logger.warning("dropping unreadable cache entry %s (%s)", path, err)
        path.unlink(missing_ok=True)
        return None


def store(key: str, harmonics: Any) -> Path | None:
    """Store harmonics under ``key`` (atomically); failures only log a warning."""
    from autocal.io.tskyfile import write_harmonics

    folder = cache_dir()
    if folder is None:
        return None
    try:
        return write_harmonics(folder / f"{key}.h5", harmonics)
    except OSError as err:
        logger.warning("could not write Tsky cache entry in %s: %s", folder, err)
        return None
