"""Small helpers shared by the modules that go through pyuvdata (UVH5, Miriad, UVCal)."""

from __future__ import annotations

import functools
import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

logger = logging.getLogger(__name__)


@contextmanager
def warnings_to_log(
    context: str, logger: logging.Logger, level: int = logging.INFO
) -> Iterator[None]:
    """Route the warnings raised inside the block (pyuvdata's) to ``logger``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for item in caught:
        logger.log(level, "%s: %s", context, item.message)


def x_orientation(telescope: Any) -> str | None:
    """Return the x feed's orientation (``"east"``/``"north"``) of a pyuvdata Telescope."""
    getter = getattr(telescope, "get_x_orientation_from_feeds", None)
    try:
        value = getter() if getter is not None else getattr(telescope, "x_orientation", None)
    except Exception:  # pragma: no cover - feeds missing or inconsistent
        value = None
    return None if value is None else str(value).lower()


def uvdata_class() -> Any:
    """Return pyuvdata's ``UVData``, its compiled helpers cached on disk (:func:`cache_jit`)."""
    cache_jit()
    # pyuvdata takes a second to import: this module's warning helpers are used without it
    from pyuvdata import UVData

    return UVData


@functools.cache
def cache_jit() -> int:
    """Let numba keep pyuvdata's compiled baseline helpers on disk; return how many.

    pyuvdata 3.2 compiles the functions of ``pyuvdata.utils.bls_numba`` with
    ``numba.njit()`` but no ``cache=True``, so every process compiled them again on its
    first UVH5 read. Numba's own :meth:`Dispatcher.enable_caching` keeps the machine code
    beside the module (or under ``NUMBA_CACHE_DIR``), so a later process loads it.
    Measured on a HERA-size night file in fresh processes, when every header scan went
    through pyuvdata: ``scan_uvh5`` 3.3-3.8 s -> 1.4-1.5 s (the rest is astropy reading its
    IERS table); ``autocal calibrate`` of the file with its Tsky cached 13.6-14.6 s ->
    12.5-13.3 s (three runs each, alternated). Plain headers are now read with h5py
    (:mod:`autocal.io.uvh5_header`); this serves the headers pyuvdata still reads and its
    other readers. Where nothing is writable, or pyuvdata changes, the functions compile as
    before.
    """
    try:  # numba and pyuvdata are heavy: imported on the first UVH5 read only
        from numba.core.dispatcher import Dispatcher
        from pyuvdata.utils import bls_numba
    except ImportError:  # pragma: no cover - a pyuvdata without numba helpers
        return 0
    count = 0
    for name, obj in vars(bls_numba).items():
        if isinstance(obj, Dispatcher):
            try:
                obj.enable_caching()
            except Exception as err:  # e.g. no writable cache folder
                logger.debug("numba cannot cache pyuvdata's %s: %s", name, err)
                continue
            count += 1
    return count
