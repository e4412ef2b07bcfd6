"""Keep astropy (and everything built on it) offline.

Three things in the stack try to download at run time:

* astropy's IERS tables (Earth orientation) -- the bundled ``astropy-iers-data``
  tables cover the dates used here, so auto-download is switched off;
* astropy's site registry, which pyuvdata asks for when reading calfits files -- an
  empty registry still triggers a download, so a non-empty one is installed;
* pygdsm's sky-model files -- handled in :mod:`autocal.io.datasets`, which registers
  local copies in astropy's download cache.

Set ``AUTOCAL_ALLOW_DOWNLOAD=1`` to let astropy download (e.g. on a machine with
internet that lacks the local data files).
"""

from __future__ import annotations

import logging
import os

logger = logging.getLogger(__name__)

_CONFIGURED = False


def downloads_allowed() -> bool:
    """Return whether the user explicitly allowed downloads (``AUTOCAL_ALLOW_DOWNLOAD``)."""
    return os.environ.get("AUTOCAL_ALLOW_DOWNLOAD", "").strip().lower() in {"1", "true", "yes"}


def configure_offline() -> None:
    """Configure astropy so that no code path needs the internet.

    Idempotent; called when :mod:`autocal` is imported.
    """
    global _CONFIGURED
    if _CONFIGURED:
        return
    from astropy.coordinates import EarthLocation
    from astropy.coordinates.sites import SiteRegistry
    from astropy.utils import iers
    from astropy.utils.data import conf as data_conf

    allow = downloads_allowed()
    iers.conf.auto_download = allow
    iers.conf.auto_max_age = None
    data_conf.allow_internet = allow
    if not allow and getattr(EarthLocation, "_site_registry", None) is None:
        registry = SiteRegistry()
        # A non-empty registry stops astropy from fetching the online one.  The
        # entries are the two sites autocal knows; pyuvdata falls back to its own
        # built-in telescope locations for everything else.
        from autocal.sites import SITES

        for site in SITES.values():
            registry.add_site([site.name], site.location)
        EarthLocation._site_registry = registry
    _CONFIGURED = True
    logger.debug("astropy configured for %s use", "online" if allow else "offline")
