"""The janitor (autocal.service.janitor): leftovers of killed processes and failed jobs."""

from __future__ import annotations

import os
import time
from pathlib import Path

from autocal.service.janitor import sweep
from autocal.service.settings import Settings
from autocal.service.store import JobState, JobStore

AFTER_S = 600.0


def _age(path: Path, seconds: float) -> Path:
    """Set ``path``'s modification time ``seconds`` in the past."""
    then = time.time() - seconds
    os.utime(path, (then, then))
    return path


def _settings(tmp_path: Path) -> Settings:
    return Settings(
        state_dir=tmp_path / "state",
        database_url=f"sqlite:///{tmp_path / 'jobs.sqlite'}",
        janitor_after_s=AFTER_S,
    )


def _job(store: JobStore, name: str, state: JobState | None) -> str:
    """A job left in ``state`` after one attempt (queued: never claimed)."""
    job, _ = store.submit({"inputs": [f"/data/{name}.uvh5"]})
    if state is None:
        return job["id"]
    store.claim(name)
    if state != JobState.running:
        store.finish(job["id"], name, 1, state, error="x" if state != JobState.succeeded else None)
    return job["id"]


def test_sweep_removes_orphans_and_keeps_live_and_fresh_files(tmp_path: Path) -> None:
    settings = _settings(tmp_path)
    store = JobStore(settings.resolved_database_url())
    jobs = settings.products_dir
    failed = _job(store, "failed", JobState.failed)
    done = _job(store, "done", JobState.succeeded)
    running = _job(store, "running", JobState.running)

    # a failed job: an empty attempt folder holding an orphaned staging folder
    failed_attempt = jobs / failed / "attempt-1"
    (failed_attempt / ".staging-99-1").mkdir(parents=True)
    (failed_attempt / ".staging-99-1" / "solution.h5").write_bytes(b"half")
    _age(failed_attempt / ".staging-99-1", 2 * AFTER_S)
    # a succeeded job: its products, an old orphaned temporary, a fresh staging folder
    done_attempt = jobs / done / "attempt-1"
    done_attempt.mkdir(parents=True)
    (done_attempt / "solution.h5").write_bytes(b"product")
    _age(done_attempt / "solution.h5", 2 * AFTER_S)
    stale_part = done_attempt / ".summary.json.x1.part"
    stale_part.write_bytes(b"")
    _age(stale_part, 2 * AFTER_S)
    fresh_staging = done_attempt / ".staging-98-2"
    fresh_staging.mkdir()
    # a running job: its attempt folder is being written, old or not
    live_staging = jobs / running / "attempt-1" / ".staging-97-3"
    live_staging.mkdir(parents=True)
    _age(live_staging, 2 * AFTER_S)
    # a job folder the store does not know (its record deleted)
    unknown = jobs / ("f" * 32) / "attempt-2"
    unknown.mkdir(parents=True)
    # uploads: a stale and a fresh partial upload, a completed upload
    uploads = settings.uploads_dir
    for name in ("a" * 32, "b" * 32, "c" * 32):
        (uploads / name).mkdir(parents=True)
    stale_upload = uploads / ("a" * 32) / "big.uvh5.part"
    stale_upload.write_bytes(b"x")
    _age(stale_upload, 2 * AFTER_S)
    _age(uploads / ("a" * 32), 2 * AFTER_S)
    fresh_upload = uploads / ("b" * 32) / "big.uvh5.part"
    fresh_upload.write_bytes(b"x")
    complete = uploads / ("c" * 32) / "obs.uvh5"
    complete.write_bytes(b"x")
    _age(complete, 2 * AFTER_S)
    _age(uploads / ("c" * 32), 2 * AFTER_S)

    report = sweep(store, settings)

    assert not (jobs / failed).exists()  # staging, then the empty attempt and job folders
    assert report.staging == [failed_attempt / ".staging-99-1"]
    assert report.partial == [stale_part]
    assert (done_attempt / "solution.h5").is_file() and fresh_staging.is_dir()
    assert live_staging.is_dir()
    assert not unknown.exists() and not unknown.parent.exists()
    assert not stale_upload.exists() and not (uploads / ("a" * 32)).exists()
    assert fresh_upload.is_file() and complete.is_file()
    assert sweep(store, settings).total == 0  # nothing left to do
    store.engine.dispose()


def test_sweep_keeps_an_empty_folder_of_the_attempt_running_now(tmp_path: Path) -> None:
    settings = _settings(tmp_path)
    store = JobStore(settings.resolved_database_url())
    job = _job(store, "r", JobState.running)
    old = settings.products_dir / job / "attempt-0"  # an earlier, superseded attempt
    current = settings.products_dir / job / "attempt-1"
    old.mkdir(parents=True)
    current.mkdir(parents=True)
    report = sweep(store, settings)
    assert report.attempts == [old] and current.is_dir()
    store.engine.dispose()
