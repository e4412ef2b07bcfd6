"""Benchmark: one night file through the pipeline's per-file work, reader features on and off.

:func:`autocal.pipeline.partials.compute_partial` (read block by block, normal sums of every block)
on one file of the night written by ``benchmarks/night.py`` (in the page cache, so the
decoding is timed, not the disk), with the block reader's speed-ups switched on one after
the other, interleaved over the repeats (best and median of N):

1. ``plain``: every stage in the calling thread, fresh arrays per block, every chunk decoded;
2. ``+ prefetch``: HDF5 reads and conversion pipelined in background threads;
3. ``+ reused buffers``: blocks decoded into two alternating sets of arrays;
4. ``+ repeated chunks decoded once``: flags and nsamples chunks compared stored;
5. ``+ gzip inflated on threads``: chunks inflated outside HDF5
   (:mod:`autocal.io.uvh5_inflate`), the pipeline's default.

The normal sums are checked to be identical in every configuration. Usage::

    python benchmarks/reader.py [--data /tmp/autocal-night] [--file 10] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

import autocal.pipeline.partials as partials
from autocal.core.files import file_sha256 as _file_sha256
from autocal.fit.model import FitModel
from autocal.io.uvh5_meta import scan_uvh5
from autocal.pipeline.partials import FileTask, PartialSpec, compute_partial

_OFF = {"prefetch": False, "reuse_buffers": False, "decode_repeats_once": False, "inflate": False}
CONFIGS = {
    "plain": _OFF,
    "+ prefetch": {**_OFF, "prefetch": True},
    "+ reused buffers": {**_OFF, "prefetch": True, "reuse_buffers": True},
    "+ repeated chunks decoded once": {
        **_OFF,
        "prefetch": True,
        "reuse_buffers": True,
        "decode_repeats_once": True,
    },
    "+ gzip inflated on threads": {
        "prefetch": True,
        "reuse_buffers": True,
        "decode_repeats_once": True,
        "inflate": True,
    },
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("/tmp/autocal-night"))
    parser.add_argument("--file", type=int, default=10, help="index of the file (10)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    files = sorted(args.data.glob("*.uvh5"))
    if len(files) <= args.file:
        raise SystemExit(f"no file {args.file} in {args.data}: run benchmarks/night.py")
    path = files[args.file]
    path.read_bytes()  # into the page cache
    file = scan_uvh5([path])[0]
    tsky = np.full((len(file.pols), file.lsts.size, file.freqs.size), 300.0)
    selection = {"antennas": None, "pols": None, "freq_range": None, "lst_range": None}
    spec = PartialSpec(FitModel.for_lsts(file.lsts), "radiometer", selection, 2, 1)
    task = FileTask(0, file, 0, file.lsts, tsky)
    # the pipeline's reader is the name bound in autocal.pipeline.partials: patch it there
    real = partials.iter_uvh5_blocks
    seconds: dict[str, list[float]] = {name: [] for name in CONFIGS}
    reference = None
    try:
        for _ in range(args.repeats):
            for name, options in CONFIGS.items():
                # the pipeline asks for reuse_buffers=True: the options here take precedence
                partials.iter_uvh5_blocks = lambda *a, _o=options, **k: real(*a, **{**k, **_o})
                _file_sha256.cache_clear()  # every run hashes the file, as a fresh process
                t0 = time.perf_counter()
                sums = compute_partial(spec, task).sums
                seconds[name].append(time.perf_counter() - t0)
                if reference is None:
                    reference = sums
                elif not all(
                    np.array_equal(getattr(sums, k), getattr(reference, k))
                    for k in ("ata", "aty", "yty", "count", "nflagged")
                ):
                    raise SystemExit(f"{name}: the normal sums differ from the plain read's")
    finally:
        partials.iter_uvh5_blocks = real
    print(f"{path.name}, {args.repeats} interleaved repeats; normal sums identical in all")
    print("| reader | best [s] | median [s] |")
    print("|---|---|---|")
    for name, secs in seconds.items():
        print(f"| {name} | {min(secs):.2f} | {statistics.median(secs):.2f} |")


if __name__ == "__main__":
    main()
