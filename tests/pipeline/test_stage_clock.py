"""The stage clock: wall and this process's CPU per stage."""

from __future__ import annotations

import threading
import time

from autocal.pipeline.stage_clock import StageClock


def _spin(cpu_seconds: float) -> None:
    """Busy-loop until this thread has used ``cpu_seconds`` of CPU (however loaded)."""
    end = time.thread_time() + cpu_seconds
    while time.thread_time() < end:
        pass


def test_a_sleep_takes_wall_time_and_no_cpu() -> None:
    clock = StageClock()
    start = clock.now()
    time.sleep(0.5)
    clock.lap("sleep_s", start)
    assert clock.wall["sleep_s"] >= 0.5
    # the process's other threads (a BLAS pool left spinning by an earlier test) may
    # spend a little CPU meanwhile; the sleeping thread spends none
    assert clock.cpu["sleep_s"] < 0.25


def test_cpu_counts_every_thread_of_the_process() -> None:
    clock = StageClock()
    start = clock.now()
    workers = [threading.Thread(target=_spin, args=(0.15,)) for _ in range(2)]
    for w in workers:
        w.start()
    _spin(0.15)  # the calling thread too: three threads, 0.15 s of CPU each
    for w in workers:
        w.join()
    clock.lap("spin_s", start)
    assert clock.cpu["spin_s"] >= 0.45  # the calling thread's own CPU is a third of it
    clock.lap("total_s", clock.started)
    summary = clock.summary()
    assert set(summary) == {"timings_s", "cpu_s"}
    assert summary["timings_s"]["total_s"] >= summary["timings_s"]["spin_s"]
    assert summary["cpu_s"]["total_s"] >= summary["cpu_s"]["spin_s"]
