"""The janitor: remove what killed processes and failed jobs leave behind.

Products are written into a ``.staging-*`` folder and published by renames
(:func:`autocal.core.files.publish_staged`); uploads are received as ``<name>.part``
(:mod:`autocal.service.routers.uploads`); a single file is written through a
``.<name>.*.part`` temporary (:func:`autocal.core.files.atomic_path`). A process killed
at the wrong moment leaves these behind, and a failed attempt leaves an empty
``attempt-N`` folder. :func:`sweep`, run by every worker at start-up and every
``AUTOCAL_JANITOR_INTERVAL_S``, removes:

- ``.staging-*`` folders and ``*.part`` files under the products folder older than
  ``AUTOCAL_JANITOR_AFTER_S``, unless they belong to the attempt a worker is running now;
- empty ``attempt-N`` folders (and then empty job folders) of jobs that are failed,
  cancelled or unknown to the store, and of attempts that are not the job's current one;
- ``*.part`` uploads (and the upload folders they leave empty) older than
  ``AUTOCAL_JANITOR_AFTER_S``.

Age is the file's modification time against this host's clock (files live on this
host's file system, whose timestamps that clock wrote).
"""

from __future__ import annotations

import logging
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from autocal.service.paths import PARTIAL_SUFFIX
from autocal.service.settings import Settings
from autocal.service.store import JobState, JobStore

logger = logging.getLogger(__name__)

#: Prefix of a products staging folder.
STAGING_PREFIX = ".staging-"
_ATTEMPT = re.compile(r"attempt-(\d+)")


@dataclass
class SweepReport:
    """What one :func:`sweep` removed (paths)."""

    staging: list[Path] = field(default_factory=list)
    partial: list[Path] = field(default_factory=list)
    attempts: list[Path] = field(default_factory=list)
    uploads: list[Path] = field(default_factory=list)

    @property
    def total(self) -> int:
        """Number of paths removed."""
        return len(self.staging) + len(self.partial) + len(self.attempts) + len(self.uploads)


def _older(path: Path, after_s: float, now: float) -> bool:
    try:
        return now - path.lstat().st_mtime > after_s
    except OSError:
        return False


def _remove(path: Path) -> bool:
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    except FileNotFoundError:
        return False
    except OSError as err:
        logger.warning("janitor: cannot remove %s: %s", path, err)
        return False
    return True


def _rmdir_if_empty(path: Path) -> bool:
    try:
        path.rmdir()
    except OSError:  # not empty, gone, or busy
        return False
    return True


def _sweep_attempt(
    folder: Path, live: bool, after_s: float, now: float, report: SweepReport
) -> None:
    """Remove old leftovers inside one attempt folder (none while it is being written)."""
    if live:
        return
    for item in folder.iterdir():
        if not _older(item, after_s, now):
            continue
        if item.name.startswith(STAGING_PREFIX) and _remove(item):
            report.staging.append(item)
        elif item.name.endswith(PARTIAL_SUFFIX) and _remove(item):
            report.partial.append(item)


def _sweep_products(store: JobStore, settings: Settings, now: float, report: SweepReport) -> None:
    root = settings.products_dir
    if not root.is_dir():
        return
    after_s = settings.janitor_after_s
    for job_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        job = store.get(job_dir.name)
        state = job["state"] if job else None
        current = int(job["attempts"]) if job else None
        for folder in sorted(p for p in job_dir.iterdir() if p.is_dir()):
            match = _ATTEMPT.fullmatch(folder.name)
            if match is None:
                continue
            attempt = int(match.group(1))
            live = state in (JobState.running.value, JobState.queued.value) and attempt == current
            _sweep_attempt(folder, live, after_s, now, report)
            finished_badly = state not in (JobState.succeeded.value, None) and not live
            superseded = current is not None and attempt != current
            if (finished_badly or superseded or job is None) and _rmdir_if_empty(folder):
                report.attempts.append(folder)
        if (job is None or state in (JobState.failed.value, JobState.cancelled.value)) and (
            _rmdir_if_empty(job_dir)
        ):
            report.attempts.append(job_dir)


def _sweep_uploads(settings: Settings, now: float, report: SweepReport) -> None:
    root = settings.uploads_dir
    if not root.is_dir():
        return
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        # an upload folder is empty only after its partial file is removed, or if the
        # API was killed between making it and opening the file
        stale = _older(folder, settings.janitor_after_s, now)
        for item in folder.iterdir():
            if (
                item.name.endswith(PARTIAL_SUFFIX)
                and _older(item, settings.janitor_after_s, now)
                and _remove(item)
            ):
                report.uploads.append(item)
                stale = True
        if stale and _rmdir_if_empty(folder):
            report.uploads.append(folder)


def sweep(store: JobStore, settings: Settings, now: float | None = None) -> SweepReport:
    """Remove orphaned staging folders, temporaries, empty attempt folders, stale uploads.

    Parameters
    ----------
    store
        The job store (to tell finished, failed and running attempts apart).
    settings
        Service settings (``products_dir``, ``uploads_dir``, ``janitor_after_s``).
    now
        The current time (seconds since the epoch; default: this host's clock).

    Returns
    -------
    SweepReport
        What was removed.
    """
    now = time.time() if now is None else now
    report = SweepReport()
    _sweep_products(store, settings, now, report)
    _sweep_uploads(settings, now, report)
    if report.total:
        logger.info(
            "janitor: removed %d staging folder(s), %d temporary file(s), %d empty "
            "attempt/job folder(s), %d stale upload(s)",
            len(report.staging),
            len(report.partial),
            len(report.attempts),
            len(report.uploads),
        )
    return report
