"""Graceful shutdown of a worker process on SIGTERM / SIGINT.

A signal handler runs in the main thread between two bytecodes of whatever that thread
was doing, which for a worker is usually the job: possibly inside a job-store transaction
that holds the job's row lock, or inside a lock of the connection pool or of the logging
machinery. Anything the handler does that waits on such a lock waits on its own
interrupted frame, forever. (It happened: the handler's log line went through the
job-log handler into the store, whose ``SELECT ... FOR UPDATE`` waited for the row lock
held by the interrupted ``append_log`` of the same thread; the worker never exited.)

So the handler here only counts the signal and puts its number on a
:class:`queue.SimpleQueue`, whose ``put`` is documented as reentrant ("can be safely
called from ... signal handlers"). A watcher thread started beforehand takes it off,
logs it and calls :meth:`Worker.request_stop` (hand the job back, stop at the next
checkpoint), while the job thread goes on until that checkpoint. A second signal exits at
once (``SystemExit(128 + signum)``).
"""

from __future__ import annotations

import logging
import queue
import signal
import threading
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Protocol

logger = logging.getLogger(__name__)

#: The signals that stop a worker gracefully.
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGTERM, signal.SIGINT)


class Stoppable(Protocol):
    """What the watcher needs of a worker."""

    worker_id: str

    def request_stop(self) -> None:
        """Stop claiming, hand the current job back and stop it at its next checkpoint."""


def stop_on_signals(
    worker: Stoppable, signums: Sequence[signal.Signals] = STOP_SIGNALS
) -> Callable[[], None]:
    """Make ``signums`` stop ``worker`` gracefully (call from the main thread).

    Parameters
    ----------
    worker
        The worker to stop (its :meth:`request_stop` runs in a watcher thread).
    signums
        The signals to handle (default SIGTERM and SIGINT).

    Returns
    -------
    callable
        Restores the previous handlers (the watcher thread, a daemon, stays idle).
    """
    pending: queue.SimpleQueue[int] = queue.SimpleQueue()
    received: list[int] = []

    def handler(signum: int, _frame: FrameType | None) -> None:
        # nothing here may take a lock: no logging, no store, no Event.set, no new thread.
        # Count first: a signal arriving inside this handler runs it again, nested, and
        # must see this one (or a second signal could be taken for a first).
        received.append(signum)
        if len(received) > 1:
            raise SystemExit(128 + signum)
        pending.put_nowait(signum)

    def watch() -> None:
        signum = pending.get()
        logger.warning(
            "worker %s: %s received; stopping after the current checkpoint",
            worker.worker_id,
            signal.Signals(signum).name,
        )
        worker.request_stop()

    threading.Thread(target=watch, name="signal-watch", daemon=True).start()
    previous = {signum: signal.signal(signum, handler) for signum in signums}

    def restore() -> None:
        for signum, old in previous.items():
            signal.signal(signum, old)

    return restore
