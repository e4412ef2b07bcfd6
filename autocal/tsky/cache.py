"""On-disk cache of the Tsky engine's output.

What is cached is the LST-free part, :class:`autocal.tsky.result.TskyHarmonics` (Tsky's
Fourier series in LST and the beam integrals), not tables: one entry then gives the table for
any LST grid and ground temperature with one inverse FFT, so every observation of a night
(the same sky frame, :func:`autocal.core.coords.night_epoch`) reuses the first one's. Entries
are HDF5 (:func:`autocal.io.tskyfile.write_harmonics`; 3.2 MB per polarisation for 1536
channels at nside 64, the default, 6.3 MB at nside 128) under ``$AUTOCAL_CACHE_DIR``
(default ``~/.cache/autocal/tsky``), named by a SHA-256 of the sky, beam (including the
beam file's checksum), site, frequencies, nside, epoch, horizon and engine version. Set
``AUTOCAL_CACHE_DIR=off`` to disable caching.

A night's first jobs often start together (one per service worker): :func:`computing`
lets one process compute an entry while the others wait for it and then read it, instead
of each computing it (seconds of CPU each, and for a HERA-size job a peak of 1.45 GB
against 1.05 GB for a job that reads the entry: deploy/README.md).
The lock is an advisory ``flock`` on an empty ``KEY.lock`` file beside the entry.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.user_cache import user_cache_dir
from autocal.io.tskyfile import read_harmonics, write_harmonics
from autocal.tsky.result import TskyHarmonics

logger = logging.getLogger(__name__)

#: Longest wait (s) for another process computing the same entry; then compute anyway.
LOCK_TIMEOUT_S = 600.0


def cache_dir() -> Path | None:
    """Return the cache folder, or ``None`` when caching is disabled."""
    return user_cache_dir("AUTOCAL_CACHE_DIR", "tsky")


def cache_key(meta: dict[str, Any], freqs: np.ndarray) -> str:
    """Hash everything that determines the harmonics: their description and frequencies."""
    digest = hashlib.sha256()
    digest.update(json.dumps(meta, sort_keys=True, default=str).encode())
    digest.update(np.ascontiguousarray(freqs, dtype=np.float64).tobytes())
    return digest.hexdigest()[:32]


def load(key: str) -> TskyHarmonics | None:
    """Return the cached harmonics for ``key``, or ``None``."""
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


def store(key: str, harmonics: TskyHarmonics) -> Path | None:
    """Store harmonics under ``key`` (atomically); failures only log a warning."""
    folder = cache_dir()
    if folder is None:
        return None
    try:
        return write_harmonics(folder / f"{key}.h5", harmonics)
    except OSError as err:
        logger.warning("could not write Tsky cache entry in %s: %s", folder, err)
        return None


@contextmanager
def computing(key: str, timeout: float = LOCK_TIMEOUT_S) -> Iterator[None]:
    """Hold the lock of ``key``'s entry while computing it.

    Another process (or thread) computing the same entry makes this wait until it is done,
    so the caller should look in the cache again once inside. Where no lock can be taken
    (caching off, a file system without ``flock``, a read-only folder) or the wait passes
    ``timeout`` seconds, the caller computes without it: the lock only saves work, the
    entries stay correct without it (they are written atomically).
    """
    handle = _lock_file(key)
    if handle is None:
        yield
        return
    import fcntl  # POSIX only: _lock_file returned None where it is missing

    try:
        start = time.monotonic()
        waiting = False
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() - start > timeout:
                    logger.warning("waited %.0f s for Tsky entry %s; computing it", timeout, key)
                    break
                if not waiting:
                    logger.info("waiting for another process computing Tsky entry %s", key)
                    waiting = True
                time.sleep(0.1)
            except OSError as err:  # no flock on this file system
                logger.debug("computing %s without the cache lock: %s", key, err)
                break
        yield
    finally:
        handle.close()  # releases the lock


def _lock_file(key: str) -> Any | None:
    """Open ``key``'s lock file, or return ``None`` where there can be no lock."""
    folder = cache_dir()
    if folder is None:
        return None
    try:
        import fcntl  # noqa: F401 - POSIX only
    except ImportError:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        return open(folder / f"{key}.lock", "a")  # closed by computing()
    except OSError as err:
        logger.debug("computing %s without the cache lock: %s", key, err)
        return None
