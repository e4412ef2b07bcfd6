"""Small helpers shared by the modules that go through pyuvdata (UVH5, Miriad, UVCal)."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


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
