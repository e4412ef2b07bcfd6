"""``autocal worker``: one job-worker process (claims queued jobs and runs them)."""

from __future__ import annotations

import argparse
import logging
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from autocal.service.settings import Settings
    from autocal.service.store import JobStore

logger = logging.getLogger(__name__)


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "worker",
        help="run queued jobs from the job store (one process; start several for more)",
        description="Claim queued jobs from the job store (AUTOCAL_DATABASE_URL, default "
        "SQLite in AUTOCAL_STATE_DIR) and run them one at a time, writing products to "
        "AUTOCAL_STATE_DIR/jobs/<job id>/attempt-<n>. For parallelism start several worker "
        "processes (e.g. systemd autocal-worker@1, @2, ... or compose replicas); with many "
        "workers or machines use PostgreSQL. Jobs of crashed workers are re-queued after "
        "AUTOCAL_STALE_AFTER_S without heartbeat. SIGTERM/SIGINT: stop claiming, hand the "
        "current job back to the queue at once (the attempt is not counted), abort it at its "
        "next checkpoint and exit; a second signal exits at once.",
    )
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--once", action="store_true", help="run at most one job, then exit")
    mode.add_argument(
        "--drain", action="store_true", help="run jobs until the queue is empty, then exit"
    )
    p.add_argument(
        "--poll", type=float, default=2.0, help="seconds between looks at an empty queue (2)"
    )
    p.add_argument("--id", dest="worker_id", help="worker name (default host:pid:random)")
    p.set_defaults(func=run)


def _open_store(settings: Settings, tries: int = 10, wait_s: float = 3.0) -> JobStore:
    """Open the job store, retrying while the database starts or another process creates it."""
    from sqlalchemy.exc import DBAPIError

    from autocal.service.store import JobStore

    url = settings.resolved_database_url()
    for attempt in range(1, tries + 1):
        try:
            return JobStore(url)
        except DBAPIError as err:  # not ready, or tables being created
            if attempt == tries:
                raise
            logger.warning("job store not ready (%s); retrying in %.0f s", err, wait_s)
            time.sleep(wait_s)
    raise AssertionError("unreachable")  # pragma: no cover


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from autocal.cli.args import CliError
    from autocal.service.settings import get_settings
    from autocal.service.shutdown import stop_on_signals
    from autocal.service.worker import Worker

    if args.poll <= 0:
        raise CliError(f"--poll {args.poll}: give a positive number of seconds")
    if args.verbose == 0:
        logging.getLogger("autocal").setLevel(logging.INFO)  # a service logs what it does
    settings = get_settings()
    worker = Worker(store=_open_store(settings), settings=settings, worker_id=args.worker_id)

    stop_on_signals(worker)  # SIGTERM/SIGINT: hand the job back, stop at a checkpoint
    worker.maybe_recover(force=True)
    worker.maybe_sweep(force=True)  # the janitor: leftovers of killed processes
    if args.once:
        ran = worker.run_once()
        logger.info("worker %s: %s", worker.worker_id, "ran one job" if ran else "queue empty")
        return 0
    if args.drain:
        count = 0
        while worker.run_once():
            count += 1
            worker.maybe_recover()
        logger.info("worker %s: queue empty after %d job(s)", worker.worker_id, count)
        return 0
    worker.run_forever(poll_s=args.poll)
    return 0
