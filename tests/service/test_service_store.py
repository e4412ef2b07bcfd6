"""The job store (autocal.service.store) on SQLite and, when available, PostgreSQL.

Every test runs on a fresh SQLite file and, when ``AUTOCAL_TEST_POSTGRES_URL`` names a
PostgreSQL database, on a fresh schema of it (dropped afterwards). Under ``CI=true`` a
missing PostgreSQL URL is a failure, not a skip (``.ci/run`` starts a server).
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timedelta
from pathlib import Path

import pytest

from autocal.service.store import LOG_LINES, JobState, JobStore, StoreError

POSTGRES_ENV = "AUTOCAL_TEST_POSTGRES_URL"
BACKENDS = ["sqlite", "postgresql"]


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in {"1", "true", "yes"}


def postgres_base_url() -> str:
    """The PostgreSQL URL for tests; skip (fail under CI=true) when it is not set."""
    url = os.environ.get(POSTGRES_ENV, "").strip()
    if not url:
        message = f"PostgreSQL tests need {POSTGRES_ENV} (postgresql+psycopg://user:pw@host/db)"
        if _in_ci():
            pytest.fail(message + " (required under CI=true; .ci/run starts a server)")
        pytest.skip(message)
    return url


@contextmanager
def postgres_schema(base_url: str) -> Iterator[str]:
    """Yield a URL whose connections use a fresh, empty schema (dropped on exit)."""
    from sqlalchemy import create_engine, text

    schema = f"test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(base_url, future=True)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    sep = "&" if "?" in base_url else "?"
    try:
        yield f"{base_url}{sep}options=-csearch_path%3D{schema}"
    finally:
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
        admin.dispose()


@contextmanager
def database_url(backend: str, folder: Path) -> Iterator[str]:
    """Yield a fresh, empty database URL for ``backend`` (``sqlite`` or ``postgresql``)."""
    if backend == "sqlite":
        folder.mkdir(parents=True, exist_ok=True)
        yield f"sqlite:///{folder / 'jobs.sqlite'}"
    else:
        with postgres_schema(postgres_base_url()) as url:
            yield url


@pytest.fixture(params=BACKENDS)
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    with database_url(request.param, tmp_path / "db") as url:
        yield url


@pytest.fixture
def store(db_url: str) -> Iterator[JobStore]:
    s = JobStore(db_url)
    yield s
    s.engine.dispose()


def _config(name: str = "a") -> dict:
    return {"inputs": [f"/data/{name}.uvh5"], "beam": "dipole"}


# submission and queries ---------------------------------------------------------------------


def test_submit_get_and_list_filters(store: JobStore) -> None:
    assert store.ping()
    a, created = store.submit(_config("a"), night=2458116, antennas=[23])
    assert created and a["state"] == "queued" and a["attempts"] == 0 and a["completions"] == 0
    time.sleep(0.002)
    b, _ = store.submit(_config("b"), night=2458116, antennas=[24, 25])
    time.sleep(0.002)
    c, _ = store.submit(_config("c"), night=2458117, kind="diagnose", max_attempts=5)
    time.sleep(0.002)
    d, _ = store.submit(_config("d"))  # all antennas

    got = store.get(a["id"])
    assert got is not None and got["config"] == _config("a") and got["antennas"] == [23]
    assert got["night"] == 2458116 and got["kind"] == "calibrate" and got["max_attempts"] == 3
    assert store.get("no-such-job") is None
    assert store.get(c["id"])["max_attempts"] == 5

    ids = lambda jobs: [j["id"] for j in jobs]  # noqa: E731
    assert ids(store.list()) == [d["id"], c["id"], b["id"], a["id"]]  # newest first
    assert ids(store.list(night=2458116)) == [b["id"], a["id"]]
    assert ids(store.list(kind="diagnose")) == [c["id"]]
    assert set(ids(store.list(antenna=24))) == {b["id"], c["id"], d["id"]}  # None = all
    assert ids(store.list(limit=2)) == [d["id"], c["id"]]
    assert ids(store.list(limit=2, offset=2)) == [b["id"], a["id"]]
    assert store.count() == 4 and store.count("queued") == 4 and store.count("running") == 0

    claimed = store.claim("w1")
    assert claimed is not None and claimed["id"] == a["id"]  # oldest first
    assert ids(store.list(state="running")) == [a["id"]]
    assert store.count("running") == 1 and store.count("queued") == 3


def test_dedupe_and_force(store: JobStore) -> None:
    first, created = store.submit(_config(), dedupe_key="obs-1")
    assert created
    again, created = store.submit(_config(), dedupe_key="obs-1")
    assert not created and again["id"] == first["id"]
    forced, created = store.submit(_config(), dedupe_key="obs-1", force=True)
    assert created and forced["id"] != first["id"]
    other, created = store.submit(_config(), dedupe_key="obs-2")
    assert created

    # a succeeded job still deduplicates; a failed or cancelled one does not
    job = store.claim("w")
    assert job is not None and job["id"] == first["id"]
    assert store.finish(job["id"], "w", 1, JobState.succeeded, result={"ok": True})
    _, created = store.submit(_config(), dedupe_key="obs-1")
    assert not created
    store.request_cancel(other["id"])
    resubmitted, created = store.submit(_config(), dedupe_key="obs-2")
    assert created and resubmitted["id"] != other["id"]


def test_concurrent_identical_submissions_create_one_job(db_url: str) -> None:
    nthreads = 8
    barrier = threading.Barrier(nthreads)
    results: list[tuple[str, bool]] = []
    errors: list[BaseException] = []

    def submitter() -> None:
        store = JobStore(db_url)
        try:
            barrier.wait()
            job, created = store.submit(_config(), dedupe_key="same-observation")
            results.append((job["id"], created))
        except BaseException as err:
            errors.append(err)
        finally:
            store.engine.dispose()

    JobStore(db_url).engine.dispose()  # tables exist before the race
    threads = [threading.Thread(target=submitter) for _ in range(nthreads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, errors
    assert len(results) == nthreads
    assert len({job_id for job_id, _ in results}) == 1
    assert sum(created for _, created in results) == 1


# claiming ---------------------------------------------------------------------------------


def test_claim_is_atomic_under_concurrency(db_url: str) -> None:
    njobs, nthreads = 60, 8
    setup = JobStore(db_url)
    submitted = {setup.submit(_config(str(i)))[0]["id"] for i in range(njobs)}
    claims: dict[str, list[str]] = {}
    errors: list[BaseException] = []
    barrier = threading.Barrier(nthreads)

    def claimer(name: str) -> None:
        store = JobStore(db_url)  # one store per thread, as separate processes would have
        got: list[str] = []
        try:
            barrier.wait()
            while (job := store.claim(name)) is not None:
                assert job["worker"] == name and job["state"] == "running"
                got.append(job["id"])
        except BaseException as err:
            errors.append(err)
        finally:
            claims[name] = got
            store.engine.dispose()

    threads = [threading.Thread(target=claimer, args=(f"w{i}",)) for i in range(nthreads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    everything = [job_id for got in claims.values() for job_id in got]
    assert len(everything) == njobs == len(set(everything))  # each claimed exactly once
    assert set(everything) == submitted
    assert setup.count("queued") == 0 and setup.count("running") == njobs
    for name, got in claims.items():
        for job_id in got:
            job = setup.get(job_id)
            assert job["worker"] == name and job["attempts"] == 1
    assert setup.claim("late") is None
    setup.engine.dispose()


def test_claim_kinds_and_empty_queue(store: JobStore) -> None:
    assert store.claim("w") is None
    diag, _ = store.submit(_config(), kind="diagnose")
    cal, _ = store.submit(_config(), kind="calibrate")
    job = store.claim("w", kinds=["calibrate"])
    assert job is not None and job["id"] == cal["id"]
    assert store.claim("w", kinds=["calibrate"]) is None
    assert store.claim("w")["id"] == diag["id"]


# ownership ---------------------------------------------------------------------------------


def test_heartbeat_requires_ownership(store: JobStore) -> None:
    queued, _ = store.submit(_config())
    assert not store.heartbeat(queued["id"], "w1", 0)  # not running yet
    job = store.claim("w1")
    assert job is not None and job["attempts"] == 1
    before = store.get(job["id"])["heartbeat_at"]
    time.sleep(0.01)
    assert store.heartbeat(job["id"], "w1", 1, progress=0.4, message="fitting")
    now = store.get(job["id"])
    assert now["progress"] == pytest.approx(0.4) and now["message"] == "fitting"
    assert now["heartbeat_at"] > before
    assert not store.heartbeat(job["id"], "w2", 1)  # another worker
    assert not store.heartbeat(job["id"], "w1", 2)  # another attempt
    assert not store.heartbeat("no-such-job", "w1", 1)
    assert store.heartbeat(job["id"], "w1", 1, progress=7.0)
    assert store.get(job["id"])["progress"] == 1.0  # clamped


def test_finish_only_by_owner_and_attempt(store: JobStore) -> None:
    store.submit(_config())
    job = store.claim("w1")
    jid = job["id"]
    with pytest.raises(StoreError, match="not a final state"):
        store.finish(jid, "w1", 1, JobState.running)
    assert not store.finish(jid, "w2", 1, JobState.succeeded)
    assert not store.finish(jid, "w1", 2, JobState.succeeded)
    assert store.get(jid)["state"] == "running"
    products = {"hdf5": "/x/solution.h5"}
    assert store.finish(
        jid, "w1", 1, JobState.succeeded, result={"n": 1}, products=products, provenance={"v": 1}
    )
    done = store.get(jid)
    assert done["state"] == "succeeded" and done["completions"] == 1 and done["progress"] == 1.0
    assert done["result"] == {"n": 1} and done["products"] == products
    assert done["provenance"] == {"v": 1} and done["finished_at"] is not None
    assert not store.finish(jid, "w1", 1, JobState.succeeded)  # never twice
    assert not store.finish(jid, "w1", 1, JobState.failed, error="late")
    assert store.get(jid)["completions"] == 1 and store.get(jid)["error"] is None

    store.submit(_config("b"))
    failed = store.claim("w1")
    assert store.finish(failed["id"], "w1", 1, JobState.failed, error="ValueError: bad input")
    rec = store.get(failed["id"])
    assert rec["state"] == "failed" and rec["error"] == "ValueError: bad input"
    assert rec["completions"] == 0


# cancellation ------------------------------------------------------------------------------


def test_cancel_queued_and_running(store: JobStore) -> None:
    queued, _ = store.submit(_config("q"))
    running, _ = store.submit(_config("r"))
    cancelled = store.request_cancel(queued["id"])
    assert cancelled["state"] == "cancelled" and cancelled["finished_at"] is not None
    job = store.claim("w1")
    assert job["id"] == running["id"]  # the cancelled job is never claimed
    assert store.claim("w2") is None

    asked = store.request_cancel(running["id"])
    assert asked["state"] == "running" and asked["cancel_requested"]
    assert not store.heartbeat(running["id"], "w1", 1)  # the worker is told to stop
    assert store.finish(running["id"], "w1", 1, JobState.cancelled, error="cancelled on request")
    assert store.get(running["id"])["state"] == "cancelled"

    with pytest.raises(StoreError, match="already cancelled"):
        store.request_cancel(running["id"])
    with pytest.raises(StoreError, match="no job"):
        store.request_cancel("no-such-job")


# recovery ------------------------------------------------------------------------------------


def test_recover_stale_requeues_then_fails_after_max_attempts(store: JobStore) -> None:
    job, _ = store.submit(_config(), max_attempts=2)
    jid = job["id"]
    first = store.claim("w1")
    assert first["attempts"] == 1
    assert store.recover_stale(3600) == []  # fresh heartbeat: left alone
    time.sleep(0.05)
    changed = store.recover_stale(0.01)
    assert [c["id"] for c in changed] == [jid]
    rec = store.get(jid)
    assert rec["state"] == "queued" and rec["worker"] is None
    assert "stopped sending heartbeats" in rec["message"] and "heartbeats" in rec["log"]
    # the presumed-dead worker can no longer report for its attempt
    assert not store.heartbeat(jid, "w1", 1)
    assert not store.finish(jid, "w1", 1, JobState.succeeded)

    second = store.claim("w2")
    assert second["id"] == jid and second["attempts"] == 2
    assert not store.finish(jid, "w1", 1, JobState.succeeded)  # old attempt, even same id
    time.sleep(0.05)
    store.recover_stale(0.01)
    rec = store.get(jid)
    assert rec["state"] == "failed" and rec["attempts"] == 2 and rec["completions"] == 0
    assert "stopped sending heartbeats" in rec["error"] and "attempt 2" in rec["error"]
    assert store.claim("w3") is None
    assert not store.finish(jid, "w2", 2, JobState.succeeded)


def test_recover_stale_cancels_when_cancellation_was_requested(store: JobStore) -> None:
    store.submit(_config())
    job = store.claim("w1")
    store.request_cancel(job["id"])
    time.sleep(0.05)
    store.recover_stale(0.01)
    rec = store.get(job["id"])
    assert rec["state"] == "cancelled" and rec["finished_at"] is not None


def test_log_tail_is_bounded(store: JobStore) -> None:
    job, _ = store.submit(_config())
    for i in range(LOG_LINES + 25):
        store.append_log(job["id"], f"line {i}\n")
    store.append_log("no-such-job", "ignored")
    lines = store.get(job["id"])["log"].splitlines()
    assert len(lines) == LOG_LINES
    assert lines[0] == "line 25" and lines[-1] == f"line {LOG_LINES + 24}"


# graceful release, the database clock, the time limit (issue 24: D2, D10) -------------------


def test_release_hands_the_job_back_without_counting_an_attempt(store: JobStore) -> None:
    job, _ = store.submit(_config(), max_attempts=1)
    jid = job["id"]
    for attempt in (1, 2, 3):  # three graceful restarts of the worker running it
        claimed = store.claim(f"w{attempt}")
        assert claimed["id"] == jid and claimed["attempts"] == attempt
        assert store.release(jid, f"w{attempt}", attempt, "worker shut down")
        rec = store.get(jid)
        assert rec["state"] == "queued" and rec["worker"] is None
        assert rec["releases"] == attempt and "handed back" in rec["log"]
        # the released attempt can no longer report, nor be released twice
        assert not store.finish(jid, f"w{attempt}", attempt, JobState.succeeded)
        assert not store.heartbeat(jid, f"w{attempt}", attempt)
        assert not store.release(jid, f"w{attempt}", attempt, "again")
    claimed = store.claim("w4")
    assert claimed["attempts"] == 4
    time.sleep(0.05)
    store.recover_stale(0.01)  # a crash now: 1 counted attempt of 1 -> failed
    rec = store.get(jid)
    assert rec["state"] == "failed" and rec["completions"] == 0

    other, _ = store.submit(_config("b"), max_attempts=1)
    store.claim("w5")
    store.release(other["id"], "w5", 1, "worker shut down")
    claimed = store.claim("w6")
    assert store.finish(other["id"], "w6", 2, JobState.succeeded)
    assert store.get(other["id"])["completions"] == 1


def test_release_of_a_job_being_cancelled_cancels_it(store: JobStore) -> None:
    job, _ = store.submit(_config())
    store.claim("w1")
    store.request_cancel(job["id"])
    assert store.release(job["id"], "w1", 1, "worker shut down")
    rec = store.get(job["id"])
    assert rec["state"] == "cancelled" and rec["finished_at"] is not None


def _skewed_clock(monkeypatch: pytest.MonkeyPatch, offset_s: float) -> None:
    """Make this process's clock (as the store module reads it) run ``offset_s`` off."""
    import autocal.service.store as store_module

    real = store_module._now
    monkeypatch.setattr(store_module, "_now", lambda: real() + timedelta(seconds=offset_s))


def test_heartbeats_and_staleness_use_the_database_clock(
    store: JobStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    job, _ = store.submit(_config())
    store.claim("slow-clock")
    with monkeypatch.context() as patch:  # a worker whose clock is 10 minutes behind
        _skewed_clock(patch, -600)
        assert store.heartbeat(job["id"], "slow-clock", 1)
    assert store.recover_stale(60) == []  # its heartbeat is fresh by the database clock
    with monkeypatch.context() as patch:  # a recovering worker 10 minutes ahead
        _skewed_clock(patch, +600)
        assert store.recover_stale(60) == []
    assert store.get(job["id"])["state"] == "running"
    beat = datetime.fromisoformat(store.get(job["id"])["heartbeat_at"])
    assert abs((store.db_now() - beat).total_seconds()) < 60


def test_time_limit_fails_a_job_that_still_beats(store: JobStore) -> None:
    job, _ = store.submit(_config(), max_attempts=3)
    store.claim("hung")
    time.sleep(0.3)
    assert store.heartbeat(job["id"], "hung", 1)  # its heartbeat thread is alive
    assert store.recover_stale(3600, job_timeout_s=3600) == []
    changed = store.recover_stale(3600, job_timeout_s=0.2)
    assert [c["id"] for c in changed] == [job["id"]]
    rec = store.get(job["id"])
    assert rec["state"] == "failed" and rec["completions"] == 0
    assert "time limit" in rec["error"] and "AUTOCAL_JOB_TIMEOUT_S=0.2" in rec["error"]
    assert not store.heartbeat(job["id"], "hung", 1)  # the worker is told to stop
    assert store.recover_stale(3600, job_timeout_s=0) == []  # 0: no limit
