"""Benchmark: a night's observations calibrated one by one, as the nightly service runs them.

``autocal nightly`` queues one job per observation and a worker runs them one after the
other in one process. Every observation has new LSTs, so while the Tsky cache held tables
(keyed by the LST grid) and the sky frame was each file's own time, every job computed its
Tsky afresh. Now the cache holds the LST-free harmonics and the frame is the night's
(:func:`autocal.core.coords.night_epoch`), so only a night's first job computes them.

This calibrates ``--files`` consecutive files of the night written by
``benchmarks/night.py`` in one process (as a worker does), each file twice, interleaved:

* ``computed``: ``AUTOCAL_CACHE_DIR=off``, the job computes its Tsky (what every job did
  before this change);
* ``cached``: one cache folder for the night's jobs, empty at the start: the first job
  computes and stores the harmonics, the others turn them into their table.

It reports each job's Tsky and total seconds (the run's ``summary.json`` timings) and checks
that the two solutions of every file are identical. A warm-up job (not counted) first loads
the libraries and compiles the fit kernel.

The price of the shared frame (``frame``): Tsky of the HERA beam and GSM2008 at nside 128,
64 channels over 100-200 MHz and 8640 LSTs over 24 h, with the frame of epochs 6 h and 12 h
after a HERA night's time, against that time's own frame (max and median |difference|).
Usage::

    python benchmarks/observations.py [--data /tmp/autocal-night] [--files 6] [--first 20]
        [--parts jobs,frame]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from night import compare_solutions, machine

from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig

ROOT = Path(__file__).resolve().parent
MODES = ("computed", "cached")


def calibrate(path: Path, out: Path, cache: str) -> dict:
    """Calibrate one file with the given cache folder; return its timings."""
    os.environ["AUTOCAL_CACHE_DIR"] = cache
    t0 = time.perf_counter()
    result = run_calibration(CalibrationConfig(inputs=[str(path)]), out)
    wall = time.perf_counter() - t0
    timings = result.summary["timings_s"]
    return {"tsky_s": timings["tsky_s"], "total_s": timings["total_s"], "wall_s": wall}


def frame_check() -> dict:
    """Tsky in frames 6 h and 12 h from the data's time against the data's own frame."""
    from autocal.tsky.compute import compute_tsky

    freqs = np.linspace(100e6, 200e6, 64, endpoint=False)
    lsts = np.arange(8640) * 24 / 8640
    jd = 2458098.30
    kwargs = dict(nside=128, pol="ee", cache=False, progress=False)
    own = compute_tsky("gsm2008", "hera", "hera", freqs, lsts, epoch=jd, **kwargs).tsky
    out = {}
    for hours in (6, 12):
        other = compute_tsky(
            "gsm2008", "hera", "hera", freqs, lsts, epoch=jd + hours / 24, **kwargs
        ).tsky
        diff = np.abs(other - own)
        out[f"{hours}h"] = {
            "max_abs_K": float(diff.max()),
            "median_abs_K": float(np.median(diff)),
            "max_rel": float((diff / own).max()),
        }
    return out


def run_jobs(files: list[Path]) -> dict:
    """Calibrate ``files`` one by one, cache off and on, interleaved; the per-job timings."""
    out: dict = {"files": [f.name for f in files], "jobs": []}
    with tempfile.TemporaryDirectory(prefix="autocal-obs-") as tmp:
        work, cache = Path(tmp), str(Path(tmp) / "tsky-cache")
        print("warm-up job ...", flush=True)
        calibrate(files[0], work / "warmup", "off")
        for i, path in enumerate(files):
            row: dict = {"file": path.name}
            for mode in MODES:
                row[mode] = calibrate(
                    path, work / f"{i}-{mode}", "off" if mode == "computed" else cache
                )
            same = compare_solutions(
                work / f"{i}-computed" / "solution.h5", work / f"{i}-cached" / "solution.h5"
            )
            row["identical"] = same["identical"]
            out["jobs"].append(row)
            print(json.dumps(row), flush=True)
        entries = list(Path(cache).glob("*.h5"))
        later = out["jobs"][1:]
        med = {
            f"{k}_{m}": statistics.median(r[m][key] for r in later)
            for k, key in (("tsky", "tsky_s"), ("job", "total_s"))
            for m in MODES
        }
        out["summary"] = {
            "tsky_computed_median_s": med["tsky_computed"],
            "tsky_cached_median_s": med["tsky_cached"],
            "job_computed_median_s": med["job_computed"],
            "job_cached_median_s": med["job_cached"],
            "job_speedup": med["job_computed"] / med["job_cached"],
            "cache_entries": len(entries),
            "cache_mb": sum(e.stat().st_size for e in entries) / 1e6,
        }
    return out


def markdown(report: dict) -> str:
    """The report as Markdown."""
    lines = ["# A night's observations, one job each (`python benchmarks/observations.py`)", ""]
    jobs = report.get("jobs_part")
    if jobs:
        m = jobs["machine"]
        lines += [
            f"Machine: {m['cpu']}, {m['cores']} cores; load average {m['load_avg_1_5_15']} at "
            f"the start, {jobs['load_after']} at the end. Files {jobs['files'][0]} ... "
            f"{jobs['files'][-1]} of the HERA-size night (350 antennas x 2 pols x 1536 "
            "channels x 192 integrations each), one process, after a warm-up job.",
            "",
            "| job | file | Tsky s, computed | Tsky s, cached | job s, computed "
            "| job s, cached | solutions identical |",
            "|---|---|---|---|---|---|---|",
        ]
        for i, row in enumerate(jobs["jobs"]):
            c, h = row["computed"], row["cached"]
            lines.append(
                f"| {i + 1} | {row['file']} | {c['tsky_s']:.2f} | {h['tsky_s']:.2f} | "
                f"{c['total_s']:.1f} | {h['total_s']:.1f} | {row['identical']} |"
            )
        s = jobs["summary"]
        lines += [
            "",
            f"Jobs after the night's first: Tsky median {s['tsky_computed_median_s']:.2f} s "
            f"computed against {s['tsky_cached_median_s']:.3f} s from the cache; job median "
            f"{s['job_computed_median_s']:.1f} s against {s['job_cached_median_s']:.1f} s "
            f"({s['job_speedup']:.2f}x). Cache entries: {s['cache_entries']} "
            f"({s['cache_mb']:.1f} MB).",
            "",
        ]
    frame = report.get("frame_part")
    if frame:
        lines += [
            "## The night's frame instead of the data's own time",
            "",
            "HERA `ee` beam, GSM2008, nside 128, 64 channels over 100-200 MHz, 8640 LSTs over "
            "24 h; Tsky in the frame of an epoch later than the data's time, against the "
            "data's own frame:",
            "",
            "| frame offset | max abs diff K | median abs diff K | max relative diff |",
            "|---|---|---|---|",
        ]
        for offset, row in frame["result"].items():
            lines.append(
                f"| {offset} | {row['max_abs_K']:.4f} | {row['median_abs_K']:.2e} | "
                f"{row['max_rel']:.1e} |"
            )
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("/tmp/autocal-night"))
    parser.add_argument("--files", type=int, default=6, help="observations (6)")
    parser.add_argument("--first", type=int, default=20, help="index of the first file (20)")
    parser.add_argument(
        "--parts", default="jobs,frame", help="jobs and/or frame (both); others are kept"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "results")
    args = parser.parse_args()
    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    if not parts or parts - {"jobs", "frame"}:
        raise SystemExit("--parts takes jobs, frame or both")
    path = args.out / "observations.json"
    report: dict = json.loads(path.read_text()) if path.is_file() else {}
    command = " ".join(["python", "benchmarks/observations.py", *sys.argv[1:]])
    if "jobs" in parts:
        files = sorted(args.data.glob("*.uvh5"))[args.first : args.first + args.files]
        if len(files) < 2:
            raise SystemExit(f"need at least 2 files from index {args.first} in {args.data}")
        info = machine()
        report["jobs_part"] = {"machine": info, **run_jobs(files), "command": command}
        report["jobs_part"]["load_after"] = [round(x, 2) for x in os.getloadavg()]
    if "frame" in parts:
        report["frame_part"] = {"result": frame_check(), "command": command}
    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")
    (args.out / "observations.md").write_text(markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
