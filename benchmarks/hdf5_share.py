"""Benchmark: the share of HDF5 reading and decoding in one night file's work (single thread).

Method: one process, every thread pool set to one thread (``NUMBA_NUM_THREADS``,
``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS`` = 1) and the block reader's stages run in the
calling thread (``iter_uvh5_blocks(prefetch=False)``), so that one profiled thread does all
the work. cProfile with a CPU-time clock (``time.process_time``: the process's CPU, which
with one thread is that thread's, and which other processes on a shared machine do not
inflate) and then with the wall clock measures, after one unmeasured run (page cache,
numba's compilation):

* ``compute_partial``: the per-file work of the pipeline (read block by block + normal
  sums), as ``benchmarks/night.py``'s profile and the README's "HDF5 68 %" figure;
* with ``--calibrate``, also the whole ``autocal.calibrate(file, out=..., products=["calh5",
  "hdf5"])`` of the file (scan, Tsky from the cache, sums, solve, total uncertainty, products).

"HDF5" is reported twice: the time inside h5py's dataset reads (``Dataset.read_direct`` and
``Dataset.__getitem__``: HDF5 reading and gzip decoding of the stored data, including the
filter pipeline) and the time inside :func:`autocal.io.uvh5_chunks.read_rows` (the reader's
stage 1, which also compares and copies repeated chunks of flags and nsamples)::

    python benchmarks/hdf5_share.py --file /tmp/autocal-night-350x1536x192/zen.*.uvh5

(``benchmarks/night.py generate --ntimes 192`` writes that file.) The report goes to
``benchmarks/results/hdf5_share.json``.
"""

from __future__ import annotations

import os

for _name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_name] = "1"  # before numpy and numba are imported

import argparse  # noqa: E402
import cProfile  # noqa: E402
import functools  # noqa: E402
import json  # noqa: E402
import pstats  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import autocal  # noqa: E402
import autocal.pipeline.partials as partials  # noqa: E402
from autocal.fit.model import FitModel  # noqa: E402
from autocal.io.uvh5_meta import scan_uvh5  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "hdf5_share.json"

#: (file suffix, function name) of the h5py calls that read and decode stored data.
H5PY_READS = (("h5py/_hl/dataset.py", "read_direct"), ("h5py/_hl/dataset.py", "__getitem__"))
READER_STAGE = ("autocal/io/uvh5_chunks.py", "read_rows")
#: Raw reads of stored chunks (no decoding): how repeated chunks are recognised.
H5PY_RAW = (("~", "<method 'read_direct_chunk' of 'h5py.h5d.DatasetID' objects>"),)


def _cumulative(stats: pstats.Stats, wanted: tuple[tuple[str, str], ...]) -> float:
    """Cumulative time of the wanted functions, outermost calls only (no double counting).

    cProfile's cumulative time of a function already excludes its recursive re-entries; the
    h5py functions do not call each other, so the sum over them is the time inside them.
    """
    total = 0.0
    for (file, _, name), (_, _, _, cumulative, _) in stats.stats.items():  # type: ignore[attr-defined]
        if any(file.endswith(f) and name == n for f, n in wanted):
            total += cumulative
    return total


def profiled(work: Callable[[], object], timer: Callable[[], float]) -> dict:
    """Profile one call of ``work`` with ``timer``: total and the HDF5 shares."""
    profile = cProfile.Profile(timer)
    start = timer()
    profile.enable()
    work()
    profile.disable()
    total = timer() - start
    stats = pstats.Stats(profile)
    h5py_s = _cumulative(stats, H5PY_READS)
    reader_s = _cumulative(stats, (READER_STAGE,))
    raw_s = _cumulative(stats, H5PY_RAW)
    return {
        "h5py_raw_chunk_reads_s": round(raw_s, 3),
        "total_s": round(total, 3),
        "h5py_reads_s": round(h5py_s, 3),
        "h5py_reads_share": round(h5py_s / total, 3),
        "read_rows_s": round(reader_s, 3),
        "read_rows_share": round(reader_s / total, 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--file", type=Path, required=True, help="one night file (UVH5)")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument(
        "--calibrate", action="store_true", help="also profile the whole autocal.calibrate call"
    )
    args = parser.parse_args()
    # the pipeline's reader (bound in autocal.pipeline.partials) with every stage in this thread
    partials.iter_uvh5_blocks = functools.partial(partials.iter_uvh5_blocks, prefetch=False)

    file = scan_uvh5([str(args.file)])[0]
    tsky = np.full((len(file.pols), file.lsts.size, file.freqs.size), 300.0)  # any values
    selection = {"antennas": None, "pols": None, "freq_range": None, "lst_range": None}
    spec = partials.PartialSpec(FitModel.for_lsts(file.lsts), "radiometer", selection, 2, 1)
    task = partials.FileTask(0, file, 0, file.lsts, tsky)
    out = Path(tempfile.mkdtemp(prefix="autocal-hdf5-share-"))

    def partial() -> object:
        return partials.compute_partial(spec, task)

    def calibrate() -> object:
        folder = out / f"run-{time.monotonic_ns()}"
        return autocal.calibrate(str(args.file), out=folder, products=["calh5", "hdf5"])

    partial()  # warm-up: page cache, numba's compilation
    report: dict = {"file": str(args.file), "load_start": os.getloadavg()}
    report["compute_partial"] = {"cpu": profiled(partial, time.process_time)}
    print(json.dumps(report), flush=True)
    report["compute_partial"]["wall"] = profiled(partial, time.perf_counter)
    print(json.dumps(report), flush=True)
    if args.calibrate:
        calibrate()  # warm-up: Tsky into the cache
        report["calibrate"] = {
            "cpu": profiled(calibrate, time.process_time),
            "wall": profiled(calibrate, time.perf_counter),
        }
    report["load_end"] = os.getloadavg()
    report["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
