"""Cooperative stopping: long computations call :func:`checkpoint` between their steps.

A caller that may have to stop a run (the job service's worker on a cancellation or a
shutdown) passes ``should_stop`` to :func:`autocal.calibrate` or
:func:`autocal.diagnose`; they install it with :func:`stop_when` for the run, and every
:func:`checkpoint` inside (between the pipeline's stages, and within the long stages
that have no stage boundary for many seconds: the sky's band limit, the Tsky engine's
chunks) raises :class:`~autocal.errors.RunCancelledError` once it returns ``True``. The check
lives in a :mod:`contextvars` variable, so concurrent runs in threads do not see each
other's, and code below the pipeline needs no extra parameter.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

from autocal.errors import RunCancelledError

logger = logging.getLogger(__name__)

_SHOULD_STOP: ContextVar[Callable[[], bool] | None] = ContextVar(
    "autocal_should_stop", default=None
)


@contextmanager
def stop_when(should_stop: Callable[[], bool] | None) -> Iterator[None]:
    """Make :func:`checkpoint` raise once ``should_stop()`` is true, inside the block.

    ``None`` keeps the check of an enclosing block (a run inside a run stops with it).
    """
    if should_stop is None:
        yield
        return
    token = _SHOULD_STOP.set(should_stop)
    try:
        yield
    finally:
        _SHOULD_STOP.reset(token)


def checkpoint(where: str = "") -> None:
    """Raise :class:`~autocal.errors.RunCancelledError` when the current run was asked to stop.

    Parameters
    ----------
    where
        What was about to happen (logged with the stop).
    """
    should_stop = _SHOULD_STOP.get()
    if should_stop is not None and should_stop():
        logger.info("stopped%s", f" before {where}" if where else "")
        raise RunCancelledError("cancelled")
