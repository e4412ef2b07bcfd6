"""Keep astropy (and everything built on it) offline.

Three things in the stack try to download at run time:

* astropy's IERS tables (Earth orientation) -- the bundled ``astropy-iers-data``
  tables cover the dates used here, so auto-download is switched off;
* astropy's site registry, which pyuvdata asks for when reading calfits files -- an
  empty registry still triggers a download, so a non-empty one is installed;
* pygdsm's sky-model files -- handled in :mod:`autocal.io.datasets`, which registers
  local copies in astropy's download cache.

Offline, astropy's Earth-orientation table is also given from a binary copy
(:func:`install_iers_table`): parsing the bundled IERS-A and IERS-B text files took 0.6 s
of every new process that converts a time (each CLI run, test worker and Dask worker).

Set ``AUTOCAL_ALLOW_DOWNLOAD=1`` to let astropy download (e.g. on a machine with
internet that lacks the local data files).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import pickle
import sys
from pathlib import Path
from typing import Any

import astropy
import astropy_iers_data
import numpy as np
from astropy.utils import iers
from astropy.utils.data import conf as data_conf

from autocal.core.sites import SITES
from autocal.core.user_cache import user_cache_dir

logger = logging.getLogger(__name__)

_CONFIGURED = False


def downloads_allowed() -> bool:
    """Return whether the user explicitly allowed downloads (``AUTOCAL_ALLOW_DOWNLOAD``)."""
    return os.environ.get("AUTOCAL_ALLOW_DOWNLOAD", "").strip().lower() in {"1", "true", "yes"}


def configure_offline(sites: bool = True) -> None:
    """Configure astropy so that no code path needs the internet.

    Idempotent; called when :mod:`autocal` is imported (or astropy, after it).

    Parameters
    ----------
    sites
        Also give astropy's ``EarthLocation`` a site registry (:func:`configure_sites`),
        which imports astropy's coordinates (~0.3 s). The import hook of :mod:`autocal`
        passes False and configures the registry when the coordinates are first imported.
    """
    global _CONFIGURED
    if not _CONFIGURED:
        allow = downloads_allowed()
        iers.conf.auto_download = allow
        iers.conf.auto_max_age = None
        data_conf.allow_internet = allow
        if not allow:
            install_iers_table()
        _CONFIGURED = True
        logger.debug("astropy configured for %s use", "online" if allow else "offline")
    if sites:
        configure_sites()


def configure_sites() -> None:
    """Give ``EarthLocation`` a registry of autocal's sites, so astropy fetches none.

    A non-empty registry stops astropy from fetching the online one. The entries are the two
    sites autocal knows; pyuvdata falls back to its own built-in telescope locations for
    everything else. Nothing changes when downloads are allowed or a registry is set.
    """
    from astropy.coordinates import EarthLocation
    from astropy.coordinates.sites import SiteRegistry

    if downloads_allowed() or getattr(EarthLocation, "_site_registry", None) is not None:
        return
    registry = SiteRegistry()
    for site in SITES.values():
        registry.add_site([site.name], site.location)
    EarthLocation._site_registry = registry


def iers_cache_file() -> Path | None:
    """Return the file of the parsed IERS table, or ``None`` when it is not to be cached.

    The name hashes the versions of Python, numpy, astropy and astropy-iers-data and the
    size and time stamp of the bundled IERS-A and IERS-B files, so a new release of any
    of them gets a new entry. No entry while a ``finals2000A.all`` in the working folder
    would make astropy read that file instead of the bundled one, nor when
    ``AUTOCAL_IERS_CACHE=off``.
    """
    folder = user_cache_dir("AUTOCAL_IERS_CACHE", "iers")
    if folder is None or os.path.exists("finals2000A.all"):
        return None
    stamp: list[Any] = [
        sys.version,
        np.__version__,
        astropy.__version__,
        astropy_iers_data.__version__,
    ]
    for name in (iers.IERS_A_FILE, iers.IERS_B_FILE):
        try:
            stat = os.stat(name)
        except OSError:  # pragma: no cover - astropy-iers-data always ships both
            return None
        stamp += [str(name), stat.st_size, stat.st_mtime_ns]
    key = hashlib.sha256(json.dumps(stamp).encode()).hexdigest()[:24]
    return folder / f"IERS_Auto-{key}.pickle"


def install_iers_table() -> None:
    """Make astropy's Earth-orientation table the bundled one, read from a binary copy.

    astropy parses the bundled IERS-A and IERS-B text tables the first time a process
    converts a time to UT1 or computes an LST (0.6 s). This keeps the parsed
    :class:`~astropy.utils.iers.IERS_Auto` table as a pickle in the user's cache
    (:func:`iers_cache_file`; 4.7 MB) and installs it with
    :data:`astropy.utils.iers.earth_orientation_table`, astropy's documented way to choose
    the table of a session, so later processes load it in ~10 ms. The table is the one
    astropy would build, so times and coordinates are unchanged. An unreadable entry is
    replaced; an unwritable cache folder only costs the parse. Loading a pickle runs code,
    so an entry or folder owned by another user or writable by everyone is not loaded (a
    warning says so and the text tables are parsed instead).
    """
    path = iers_cache_file()
    if path is None:
        return
    table = None
    try:
        untrusted = _writable_by_others(path)
        if untrusted:
            raise PermissionError(
                f"{untrusted} is owned by another user or writable by everyone; not loading it"
            )
        data: bytes | None = path.read_bytes()
    except FileNotFoundError:
        data = None
    except OSError as err:  # e.g. the folder's parent is a file: parse, don't cache
        logger.warning("not using the IERS table cache %s: %s", path, err)
        iers.earth_orientation_table.set(iers.IERS_Auto.open())
        return
    if data is not None:
        try:
            table = pickle.loads(data)
            if not isinstance(table, iers.IERS_Auto):
                raise TypeError(f"holds a {type(table).__name__}, not an IERS_Auto table")
        except Exception as err:  # any damage to the entry (truncated, foreign): rebuild it
            logger.warning("replacing the unreadable IERS table cache %s (%s)", path, err)
            table = None
    if table is None:
        table = iers.IERS_Auto.open()
        _store_iers_table(path, table)
    iers.earth_orientation_table.set(table)


def _writable_by_others(path: Path) -> Path | None:
    """Return the entry or its folder if another user could have written it, else ``None``.

    Trusted: owned by this user or root and not writable by everyone. (A group-writable
    folder is the administrator's choice, e.g. one cache for a service's workers.)
    """
    for item in (path.parent, path):
        try:
            stat = item.stat()
        except FileNotFoundError:
            return None
        if stat.st_uid not in (os.getuid(), 0) or stat.st_mode & 0o002:
            return item
    return None


def _store_iers_table(path: Path, table: Any) -> None:
    """Write ``table`` to ``path`` atomically; failures only log."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tmp.open("wb") as stream:
            pickle.dump(table, stream, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, path)
        logger.debug("cached the parsed IERS table in %s", path)
    except OSError as err:
        logger.info("not caching the parsed IERS table in %s: %s", path.parent, err)
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
