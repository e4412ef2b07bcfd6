"""The root of every error a user of autocal can cause.

Every error autocal raises for bad input (an unknown sky or beam, a malformed file, a
selection that leaves no data, an option out of range) is an :class:`AutocalError`; the
modules keep their own subclasses (:class:`autocal.fit.model.FitError`,
:class:`autocal.io.uvh5.UVH5FormatError`, ...) so a caller can be as specific as it likes.
:class:`AutocalError` is a :class:`ValueError`, so ``except ValueError`` keeps working.

The command line reports an :class:`AutocalError` (and a missing file, and options
pydantic rejects) as bad input: a one-line message and exit status 2. Anything else is a
bug in autocal or below it and is shown with its traceback (exit status 1).

This module imports nothing, so any module may import it.
"""

from __future__ import annotations

__all__ = ["AutocalError", "RunCancelledError"]


class AutocalError(ValueError):
    """An error the user can fix: bad input, options or files; the message says how."""


class RunCancelledError(AutocalError):
    """The run was asked to stop (a cancelled job, a worker shutting down).

    Raised at a checkpoint (:func:`autocal.core.stopping.checkpoint`) once the run's
    ``should_stop`` returns ``True``; nothing half-written is left behind.
    """
