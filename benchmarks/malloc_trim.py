"""Benchmark: a night file's calibration with and without Dask's MALLOC_TRIM_THRESHOLD_.

Dask's nanny starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536``, which also fixes
glibc's mmap threshold at 128 kB, so every array above that is mapped and faulted in
afresh. This runs :func:`autocal.pipeline.partials.compute_partial` on files of the night written
by ``benchmarks/night.py``, in two processes side by side (as two Dask workers on this
2-core machine), once with the variable and once without, and prints the seconds per file.
Usage::

    python benchmarks/malloc_trim.py [--data /tmp/autocal-night] [--files 2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from pathlib import Path

WORKER = """
import sys, time
import numpy as np
from autocal.fit import FitModel
from autocal.io.uvh5 import scan_uvh5
from autocal.pipeline.partials import FileTask, PartialSpec, compute_partial
for path in sys.argv[1:]:
    open(path, "rb").read()  # page cache: time the decoding, not the disk
    file = scan_uvh5([path])[0]
    tsky = np.full((len(file.pols), file.lsts.size, file.freqs.size), 300.0)
    sel = {"antennas": None, "pols": None, "freq_range": None, "lst_range": None}
    spec = PartialSpec(FitModel.for_lsts(file.lsts), "radiometer", sel, 2, 1)
    print(compute_partial(spec, FileTask(0, file, 0, file.lsts, tsky)).seconds, flush=True)
"""


def side_by_side(groups: list[list[str]], env: dict[str, str]) -> list[float]:
    """Seconds per file of one process per group, all started together."""
    procs = [
        subprocess.Popen([sys.executable, "-c", WORKER, *g], env=env, stdout=subprocess.PIPE)
        for g in groups
    ]
    seconds: list[float] = []
    for proc in procs:
        out, _ = proc.communicate()
        if proc.returncode:
            raise SystemExit(f"a worker failed (exit {proc.returncode})")
        seconds += [float(x) for x in out.split()]
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("/tmp/autocal-night"))
    parser.add_argument("--files", type=int, default=2, help="files per process (2)")
    args = parser.parse_args()
    files = sorted(str(p) for p in args.data.glob("*.uvh5"))
    if len(files) < 4 * args.files:
        raise SystemExit(f"need {4 * args.files} files in {args.data}: run benchmarks/night.py")
    base = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    base["OMP_NUM_THREADS"] = "1"  # as in a Dask worker
    n = args.files
    for label, env, first in (
        ("without MALLOC_TRIM_THRESHOLD_", base, 0),
        ("with MALLOC_TRIM_THRESHOLD_=65536", {**base, "MALLOC_TRIM_THRESHOLD_": "65536"}, 2 * n),
    ):
        groups = [files[first : first + n], files[first + n : first + 2 * n]]
        secs = side_by_side(groups, env)
        print(f"{label}: median {statistics.median(secs):.2f} s per file ({len(secs)} files)")


if __name__ == "__main__":
    main()
