"""Where autocal keeps its per-user caches.

Three caches, each in its own folder, each disabled by setting its variable to ``off``:

========================  ===========================  ======================================
variable                  default folder               what
========================  ===========================  ======================================
``AUTOCAL_CACHE_DIR``     ``~/.cache/autocal/tsky``    Tsky harmonics (:mod:`autocal.tsky`)
``AUTOCAL_KERNEL_CACHE``  ``.../autocal/fit_kernels``  compiled fit kernels (:mod:`autocal.fit`)
``AUTOCAL_IERS_CACHE``    ``.../autocal/iers``         astropy's parsed Earth-orientation
                                                       table (:mod:`autocal.core.offline`)
========================  ===========================  ======================================

``~/.cache`` is ``$XDG_CACHE_HOME`` when that is set. Everything in them can be deleted at
any time; it is rebuilt on first use.
"""

from __future__ import annotations

import os
from pathlib import Path

#: Values of a cache variable that switch the cache off.
OFF_VALUES = frozenset({"off", "none", "0", "false"})


def user_cache_dir(variable: str, name: str) -> Path | None:
    """Return a cache folder, or ``None`` when the user switched that cache off.

    Parameters
    ----------
    variable
        Environment variable naming the folder (or ``off``), e.g. ``"AUTOCAL_CACHE_DIR"``.
    name
        Sub-folder of ``$XDG_CACHE_HOME/autocal`` (``~/.cache/autocal``) used when the
        variable is unset or empty.

    Returns
    -------
    Path or None
        The folder (not created here); also ``None`` when the default is wanted but there
        is no home folder to put it in (the XDG rule: a relative ``XDG_CACHE_HOME`` is
        ignored), rather than a ``~`` folder in the working directory.
    """
    value = os.environ.get(variable, "").strip()
    if value.lower() in OFF_VALUES:
        return None
    if value:
        return Path(value).expanduser()
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    if not base.is_absolute():  # no home folder (HOME unset, no passwd entry): no cache
        return None
    return base / "autocal" / name
