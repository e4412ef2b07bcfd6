"""Graceful shutdown on SIGTERM / SIGINT (autocal.service.shutdown).

The handler must not take any lock the interrupted main thread may hold: the signal
arrives while the job thread is inside the store (a transaction holding the job's row
lock) as often as not, right after a job starts. A clean-clone CI run once hung 180 s
there on PostgreSQL: the old handler's log line went through the job-log handler into
the store, whose ``SELECT ... FOR UPDATE`` waited for its own interrupted transaction.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from autocal.service.shutdown import stop_on_signals
from tests.service.test_service_store import BACKENDS, database_url


class _Recorder(logging.Handler):
    def __init__(self) -> None:
        super().__init__(level=logging.DEBUG)
        self.threads: list[int] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.threads.append(record.thread)


class _FakeWorker:
    worker_id = "fake"

    def __init__(self) -> None:
        self.stopped_in: list[int] = []
        self.called = threading.Event()

    def request_stop(self) -> None:
        self.stopped_in.append(threading.get_ident())
        self.called.set()


def test_the_handler_only_hands_the_signal_to_the_watcher() -> None:
    worker = _FakeWorker()
    recorder = _Recorder()
    root = logging.getLogger()
    root.addHandler(recorder)
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    restore = stop_on_signals(worker)
    main = threading.get_ident()
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        assert worker.called.wait(10), "request_stop was never called"
        assert worker.stopped_in and worker.stopped_in[0] != main
        assert recorder.threads and main not in recorder.threads  # logged by the watcher
        with pytest.raises(SystemExit) as second:  # a second signal exits at once
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)  # the handler runs between two bytecodes
        assert second.value.code == 128 + signal.SIGINT
        assert len(worker.stopped_in) == 1
    finally:
        restore()
        root.removeHandler(recorder)
    assert {s: signal.getsignal(s) for s in before} == before  # the handlers restored


SCENARIO = textwrap.dedent(
    """
    import logging, os, signal, sys, threading, time
    from autocal.service.settings import Settings
    from autocal.service.shutdown import stop_on_signals
    from autocal.service.store import Job, JobStore
    from autocal.service.worker import Worker, _JobLogHandler, _Run

    logging.basicConfig(level=logging.INFO)
    store = JobStore(sys.argv[1])
    store.submit({"inputs": []}, max_attempts=1)
    worker = Worker(store=store, settings=Settings(state_dir=sys.argv[2]), worker_id="w")
    run = _Run(worker, store.claim("w"))
    worker.current = run
    logging.getLogger().addHandler(_JobLogHandler(store, run.job_id, threading.get_ident()))
    stop_on_signals(worker)
    with store.session() as s:  # the job thread inside a store transaction...
        s.get(Job, run.job_id, with_for_update=not store.is_sqlite)
        os.kill(os.getpid(), signal.SIGTERM)  # ...when the signal arrives
        for _ in range(20):
            time.sleep(0.05)
    deadline = time.monotonic() + 30
    while not run.released and time.monotonic() < deadline:
        time.sleep(0.05)
    job = store.get(run.job_id)
    print("STATE", job["state"], job["releases"], run.released)
    """
)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_signal_inside_a_store_transaction_hands_the_job_back(
    backend: str, tmp_path: Path
) -> None:
    with database_url(backend, tmp_path / "db") as url:
        proc = subprocess.run(
            [sys.executable, "-c", SCENARIO, url, str(tmp_path / "state")],
            capture_output=True,
            text=True,
            timeout=90,  # the old handler never returned (a deadlock on PostgreSQL)
            cwd=Path(__file__).parents[2],
        )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "STATE queued 1 True" in proc.stdout, (proc.stdout, proc.stderr[-3000:])
    assert "SIGTERM received" in proc.stderr
