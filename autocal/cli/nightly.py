"""``autocal nightly``: queue one calibration job per observation of a night or a folder.

Submission is idempotent (the same observation is not queued again unless ``--force``), so
the command can run from a timer or cron as often as wanted. ``--watch DIR`` keeps polling
a folder and submits observations as their files appear (once the folder has been quiet
for ``--settle`` seconds, so files still being written are not picked up half-way).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from autocal.cli.args import CliError
from autocal.cli.options import add_calibration_arguments, calibration_settings

logger = logging.getLogger(__name__)

#: An observation file: ``zen.<JD>.<fraction>.<suffix with uvh5>``, e.g.
#: ``zen.2458116.30448.HH.uvh5`` (the names :mod:`autocal.service.nightly` groups).
OBSERVATION_NAME = re.compile(r"^zen\.(?P<jd>[0-9]{7})\.[0-9]+\..*uvh5")
#: Smallest accepted night (JD 2400000 = 1858; catches MJDs and typos).
MIN_NIGHT = 2_400_000


def find_nights(folders: Iterable[Path]) -> list[int]:
    """Return the nights (integer JDs) of the observation files found under ``folders``.

    A night is read from the file name (``zen.<JD>.<fraction>.<...uvh5...>``, as nightly
    submission groups them); calibration products, reference gains and hidden folders
    are ignored.

    Parameters
    ----------
    folders
        Folders searched recursively.

    Returns
    -------
    list of int
        The nights, sorted.
    """
    nights: set[int] = set()
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            continue
        for _root, dirs, files in os.walk(folder):
            dirs[:] = [d for d in dirs if not d.startswith(".")]
            for name in files:
                match = OBSERVATION_NAME.match(name)
                if match:
                    nights.add(int(match.group("jd")))
    return sorted(nights)


def latest_night(folders: Iterable[Path]) -> int:
    """Return the most recent night found under ``folders``.

    Raises
    ------
    CliError
        When no observation named with a Julian date is found.
    """
    folders = list(folders)
    nights = find_nights(folders)
    if not nights:
        where = ", ".join(str(f) for f in folders) or "(no data roots configured)"
        raise CliError(
            f"--night last: no observation named with a Julian date (e.g. "
            f"zen.2458116.30448.HH.uvh5) under {where}; set AUTOCAL_DATA_ROOTS or --folder"
        )
    return nights[-1]


def _night(text: str) -> int | str:
    if text.strip().lower() == "last":
        return "last"
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give the integer Julian date of the night (e.g. 2458116) or 'last'"
        ) from err
    if value != int(value) or value < MIN_NIGHT:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give the integer Julian date of the night (e.g. 2458116), not an "
            "MJD or a fraction"
        )
    return int(value)


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "nightly",
        help="queue one calibration job per observation of a night or a watched folder",
        description="Group the files of a night (JD, searched under AUTOCAL_DATA_ROOTS or "
        "--folder) or of a folder into observations and queue one calibration job per "
        "observation. Idempotent: an observation already queued, running or calibrated is "
        "not submitted again unless --force. Jobs are run by `autocal worker` processes.",
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--night",
        type=_night,
        metavar="JD|last",
        help="integer Julian date of the night, or 'last' for the most recent night found",
    )
    what.add_argument(
        "--watch", type=Path, metavar="DIR", help="poll this folder and submit new observations"
    )
    p.add_argument("--folder", type=Path, help="with --night: only look in this folder")
    p.add_argument(
        "--force", action="store_true", help="submit again observations already calibrated"
    )
    p.add_argument("--interval", type=float, default=60.0, help="--watch: seconds between polls")
    p.add_argument(
        "--settle",
        type=float,
        default=60.0,
        help="--watch: submit once no file changed for this many seconds (60)",
    )
    p.add_argument("--once", action="store_true", help="--watch: one pass, then exit")
    p.add_argument("--json", action="store_true", help="print the submission result as JSON")
    p.add_argument(
        "--wait",
        type=float,
        default=None,
        metavar="SECONDS",
        help="with --night: wait up to this long for the night's jobs (run by workers) to "
        "finish, then print the night's outliers",
    )
    cal = p.add_argument_group("calibration options (default: those of autocal calibrate)")
    add_calibration_arguments(cal)
    p.set_defaults(func=run)


def _count(value: Any) -> int:
    return len(value) if isinstance(value, list | tuple | set | dict) else int(value or 0)


def _report(result: dict[str, Any], as_json: bool) -> None:
    if as_json:
        print(json.dumps(result, indent=2, default=str))
        return
    observations = result.get("observations") or []
    label = f"night {result['night']}" if result.get("night") is not None else "folder"
    refused = f", {_count(result.get('refused'))} refused" if result.get("refused") else ""
    print(
        f"{label}: {len(observations)} observation(s), {_count(result.get('created'))} "
        f"submitted, {_count(result.get('existing'))} already queued or calibrated{refused}"
    )
    for obs in observations:
        files = obs.get("files") or []
        first = Path(files[0]).name if files else "?"
        if obs.get("job_id") is None:
            print(f"  refused   {len(files)} file(s) from {first}: {obs.get('error')}")
            continue
        status = "submitted" if obs.get("created") else "exists   "
        print(f"  {status} job {obs.get('job_id')}  {len(files)} file(s) from {first}")


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Size and modification time of every file under ``folder`` (hidden ones skipped)."""
    snap: dict[str, tuple[int, int]] = {}
    for root, dirs, files in os.walk(folder):
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        for name in files:
            if name.startswith("."):
                continue
            path = Path(root) / name
            try:
                st = path.stat()
            except FileNotFoundError:  # removed while walking
                continue
            snap[str(path.relative_to(folder))] = (st.st_size, st.st_mtime_ns)
    return snap


def _shown_url(url: str) -> str:
    """Return a store URL without its password."""
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


def _submit(args: argparse.Namespace, **where: Any) -> dict[str, Any]:
    from autocal.service.nightly import submit_nightly  # written alongside the API
    from autocal.service.settings import get_settings
    from autocal.service.store import JobStore

    settings = get_settings()
    url = settings.resolved_database_url()
    store = JobStore(url)
    print(
        f"autocal nightly: job store {_shown_url(url)}, products under "
        f"{settings.products_dir} (AUTOCAL_DATABASE_URL, AUTOCAL_STATE_DIR change them)",
        file=sys.stderr,
    )
    try:
        return submit_nightly(
            store, settings, force=args.force, options=calibration_settings(args), **where
        )
    finally:
        store.engine.dispose()


def _watch(args: argparse.Namespace) -> int:
    folder = args.watch.expanduser().resolve()
    if not folder.is_dir():
        raise CliError(f"--watch {args.watch}: not a folder")
    calibration_settings(args)  # fail early on bad options
    submitted: dict[str, tuple[int, int]] | None = None
    while True:
        snap = _snapshot(folder)
        newest = max((mtime for _, mtime in snap.values()), default=0) / 1e9
        quiet_for = time.time() - newest
        if snap and snap != submitted and quiet_for >= args.settle:
            try:
                _report(_submit(args, folder=folder), args.json)
                submitted = snap
            except Exception as err:
                if args.once:
                    raise
                logger.error("nightly --watch %s: submission failed: %s", folder, err)
        elif snap and snap != submitted:
            wait = args.settle - quiet_for
            logger.info("files in %s changed %.0f s ago; waiting %.0f s", folder, quiet_for, wait)
            if args.once:
                time.sleep(max(wait, 0.1))
                continue
        elif args.once and not snap:
            logger.warning("nothing to submit: %s holds no files", folder)
        if args.once:
            return 0
        time.sleep(args.interval)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    if args.interval <= 0 or args.settle < 0:
        raise CliError("--interval must be positive and --settle not negative")
    if args.wait is not None and (args.wait < 0 or args.watch is not None):
        raise CliError("--wait goes with --night and takes a number of seconds >= 0")
    if args.watch is not None:
        if args.folder is not None:
            raise CliError("--folder goes with --night; --watch already names the folder")
        try:
            return _watch(args)
        except KeyboardInterrupt:
            return 130
    calibration_settings(args)  # fail early on bad options
    folder = args.folder.expanduser().resolve() if args.folder is not None else None
    if folder is not None and not folder.is_dir():
        raise CliError(f"--folder {args.folder}: not a folder")
    night = args.night
    if night == "last":
        from autocal.service.settings import get_settings

        roots = [folder] if folder is not None else get_settings().resolved_data_roots()
        night = latest_night(roots)
        logger.info("--night last: %d", night)
    result = _submit(args, night=night, folder=folder)
    _report(result, args.json)
    if result.get("night") is not None and not args.json:
        _report_outliers(int(result["night"]), result, args.wait)
    # an observation refused (listed above, with why): a timer or cron job must notice
    return 2 if result.get("refused") else 0  # 2: autocal.cli.main.EXIT_USER_ERROR


def _report_outliers(night: int, result: dict[str, Any], wait_s: float | None) -> None:
    """Print the night's outliers (after waiting for its jobs with ``--wait``)."""
    from autocal.service.monitoring import outliers_of_night
    from autocal.service.settings import get_settings
    from autocal.service.store import FINAL_STATES, JobStore

    store = JobStore(get_settings().resolved_database_url())
    try:
        ids = [o["job_id"] for o in result.get("observations") or [] if o.get("job_id")]
        deadline = time.monotonic() + (wait_s or 0.0)
        while True:
            jobs = [store.get(i) for i in ids]
            pending = [j for j in jobs if j is not None and j["state"] not in FINAL_STATES]
            if not pending or time.monotonic() >= deadline:
                break
            time.sleep(min(2.0, max(deadline - time.monotonic(), 0.0)))
        outliers = outliers_of_night(store, night)
    finally:
        store.engine.dispose()
    if pending:
        print(f"night {night}: {len(pending)} job(s) not finished yet; outliers so far:")
    failed = [j for j in jobs if j is not None and j["state"] == "failed"]
    for job in failed:
        print(f"  failed job {job['id']}: {job.get('error') or ''}")
    if not outliers:
        print(f"night {night}: no outlier antenna")
    for o in outliers:
        print(f"  outlier antenna {o['antenna']} {o['pol']} ({o['test']}): {o['reason']}")
