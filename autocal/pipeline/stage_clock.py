"""Wall and CPU seconds of a run's stages, for ``summary.json``.

The CPU time is this process's, over all its threads (``time.process_time``): the block
reader's decoding threads and the fit's kernels are in it; reader processes
(``--readers``) and Dask workers in other processes are not (a local cluster's worker
threads, ``processes=False``, are). Where CPU exceeds wall, the stage ran on more
than one core; ``cpu / wall`` is the mean number of busy cores.
"""

from __future__ import annotations

import time


class StageClock:
    """Times a run's stages: wall (``perf_counter``) and this process's CPU.

    Usage: ``start = clock.now()`` before a stage, ``clock.lap("fit_s", start)`` after it;
    ``clock.lap("total_s", clock.started)`` at the end.
    """

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self.started = self.now()

    @staticmethod
    def now() -> tuple[float, float]:
        """Return the wall and CPU clocks now, ``(wall, cpu)`` seconds."""
        return time.perf_counter(), time.process_time()

    def lap(self, name: str, since: tuple[float, float]) -> None:
        """Record stage ``name`` as the time from ``since`` to now."""
        wall, cpu = self.now()
        self.wall[name] = wall - since[0]
        self.cpu[name] = cpu - since[1]

    def summary(self) -> dict[str, dict[str, float]]:
        """Return ``timings_s`` (wall) and ``cpu_s`` (CPU), rounded to milliseconds."""
        return {
            "timings_s": {k: round(v, 3) for k, v in self.wall.items()},
            "cpu_s": {k: round(v, 3) for k, v in self.cpu.items()},
        }
