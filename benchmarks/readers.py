"""Benchmark: a night on two cores without Dask (issue 25, item 2), side by side in one run.

Measures, on the files of a night written by ``benchmarks/night.py generate`` (default the
quarter night, ``--ntimes 2112``: 11 files in ``/tmp/autocal-night-q``):

- the **serial decode floor**: one fresh process reads every file's visibilities with h5py
  in the block reader's blocks (``read_direct`` into one reused buffer) and makes one numpy
  pass over each block, file after file;
- ``autocal calibrate ... --products hdf5`` (the ordinary command; ``--products`` to
  change) with ``--readers 1`` and ``--readers 2``, with and without ``--no-rfi-flagging``,
  each a fresh process tree. The default products are not the default here: with them the
  quarter night's calibrate process was killed by the kernel's OOM killer at 15.2 GB on the
  23.5 GB machine (by its size, the per-time ``solution.calh5``), whatever reads the files.

Every run starts with the night's files evicted from the page cache
(``posix_fadvise(DONTNEED)``: their first read comes from the disk), the Tsky table already
in the benchmark's cache (computed once before the runs). Wall time (``wait4``), CPU of the
tree, and the peak over time of the summed RSS and PSS of the whole process tree (the
command and its reader processes, sampled every 0.1 s from ``/proc``), plus ``uptime``'s
load before each run. ``--steps variants`` also maps the fit's per-file work over reader
processes with 1 or 2 kernel threads and the reader's read-ahead on or off, and times the
pool's start with ``spawn`` and ``forkserver`` (fresh processes).

    python benchmarks/readers.py                       # floor + the four runs, one round
    python benchmarks/readers.py --rounds 2 --steps floor,serial,readers,variants

Writes ``benchmarks/results/readers.json`` and ``readers.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT_DATA = Path("/tmp/autocal-night-q")

#: The calibrate runs: name -> extra arguments.
RUNS = {
    "calibrate --readers 1 --no-rfi-flagging": ["--readers", "1", "--no-rfi-flagging"],
    "calibrate --readers 2 --no-rfi-flagging": ["--readers", "2", "--no-rfi-flagging"],
    "calibrate --readers 1": ["--readers", "1"],
    "calibrate --readers 2": ["--readers", "2"],
}


def night_files(folder: Path, nfiles: int | None) -> list[Path]:
    files = sorted(folder.glob("zen.*.uvh5"))
    if not files:
        raise SystemExit(
            f"no night in {folder}: python benchmarks/night.py generate --ntimes 2112 "
            f"--data {folder}"
        )
    return files[:nfiles] if nfiles else files


def evict(files: list[Path]) -> None:
    """Drop the files' pages from the page cache (their next read comes from the disk)."""
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def _tree(pid: int) -> list[int]:
    """The pids of ``pid`` and all its descendants (from /proc)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


def _memory(pid: int) -> tuple[int, int]:
    """RSS and PSS of one process in bytes (0, 0 once it is gone)."""
    try:
        text = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return 0, 0
    values = {}
    for line in text.splitlines()[1:]:
        key, _, rest = line.partition(":")
        parts = rest.split()
        if parts and parts[0].isdigit():
            values[key] = int(parts[0]) * 1024
    return values.get("Rss", 0), values.get("Pss", 0)


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of one process so far (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class TreeSampler(threading.Thread):
    """Peak over time of the summed RSS and PSS of a process tree, sampled every 0.1 s."""

    def __init__(self, pid: int) -> None:
        super().__init__(daemon=True)
        self.pid = pid
        self.peak_rss = self.peak_pss = 0
        self.processes: set[int] = set()
        self.cpu: dict[int, float] = {}  # last seen CPU seconds of every process of the tree
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            pids = _tree(self.pid)
            self.processes.update(pids)
            rss = pss = 0
            for p in pids:
                r, s = _memory(p)
                rss, pss = rss + r, pss + s
                self.cpu[p] = max(self.cpu.get(p, 0.0), _cpu_seconds(p))
            self.peak_rss, self.peak_pss = max(self.peak_rss, rss), max(self.peak_pss, pss)
            self._halt.wait(0.1)

    def stop(self) -> None:
        self._halt.set()
        self.join()


def run_tree(argv: list[str], env: dict[str, str]) -> dict:
    """Run one command as a fresh process tree: wall, CPU, peak tree RSS / PSS, load."""
    load = os.getloadavg()
    start = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    sampler = TreeSampler(proc.pid)
    sampler.start()
    stdout, stderr = proc.communicate()  # reads the pipes; the status is collected below
    sampler.stop()
    wall = time.perf_counter() - start
    usage = proc.returncode
    if usage != 0:
        raise SystemExit(f"{' '.join(argv)}: exit {usage}\n{stderr.decode()[-3000:]}")
    cpu = _children_cpu()
    return {
        "wall_s": round(wall, 2),
        # the reader processes are the forkserver's children, not the command's: their CPU
        # is summed from /proc (each process's last sample, <= 0.1 s before it ended)
        "cpu_s": round(max(cpu, sum(sampler.cpu.values())), 1),
        "cpu_waited_s": round(cpu, 1),
        "peak_tree_rss_gb": round(sampler.peak_rss / 1e9, 3),
        "peak_tree_pss_gb": round(sampler.peak_pss / 1e9, 3),
        "processes": len(sampler.processes),
        "load_before": [round(x, 2) for x in load],
        "stdout_tail": stdout.decode()[-300:],
    }


_cpu_seen = [0.0]


def _children_cpu() -> float:
    """CPU seconds of the children collected since the last call (the tree's, waited for)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    total = usage.ru_utime + usage.ru_stime
    spent, _cpu_seen[0] = total - _cpu_seen[0], total
    return spent


def floor(files: list[str]) -> dict:
    """The serial decode floor (run in a fresh process): visdata in the reader's blocks."""
    import h5py

    from autocal.io.uvh5_blocks import BLOCK_SAMPLES

    start = time.perf_counter()
    cpu0 = time.process_time()
    total = 0.0
    nbytes = 0
    buffer = None
    for name in files:
        with h5py.File(name, "r") as h5:
            dset = h5["Data/visdata"]
            nants = int(h5["Header/Nants_data"][()])
            nblts = dset.shape[0]
            per_time = int(np.prod(dset.shape[1:])) * nants  # values of one integration
            rows = nants * max(1, BLOCK_SAMPLES // per_time)  # the reader's block
            for r0 in range(0, nblts, rows):
                r1 = min(nblts, r0 + rows)
                shape = (r1 - r0, *dset.shape[1:])
                if buffer is None or buffer.shape != shape:
                    buffer = np.empty(shape, dset.dtype)
                dset.read_direct(buffer, np.s_[r0:r1])
                total += float(np.sum(buffer.real))  # one numpy pass
                nbytes += buffer.nbytes
    return {
        "wall_s": round(time.perf_counter() - start, 2),
        "cpu_self_s": round(time.process_time() - cpu0, 1),
        "decoded_gb": round(nbytes / 1e9, 2),
        "checksum": total,
    }


def warm_tsky(files: list[Path], cache: Path) -> float:
    """Compute the night's Tsky into the benchmark's cache (as calibrate will ask for it)."""
    os.environ["AUTOCAL_CACHE_DIR"] = str(cache)
    from autocal.core.coords import night_epoch
    from autocal.pipeline.config import CalibrationConfig
    from autocal.pipeline.sources import open_source, tsky_per_pol

    start = time.perf_counter()
    config = CalibrationConfig(inputs=[str(f) for f in files])
    source = open_source(config)
    pols = tuple(p.lower() for p in source.pols)
    epoch = night_epoch(source.jds, source.site.lon_deg)
    tsky_per_pol(config.sky, config, source, pols, epoch)
    return time.perf_counter() - start


def compare(a: Path, b: Path) -> dict:
    """Bit-for-bit comparison of two runs' solution.h5 (``benchmarks/night.py``'s)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from night import compare_solutions

    return compare_solutions(a / "solution.h5", b / "solution.h5")


def variants(files: list[Path], cache: Path, nfiles: int) -> dict:
    """Per-file time of the fit's work in 2 reader processes: kernel threads x read-ahead."""
    code = f"""
import json, os, time, sys
os.environ["AUTOCAL_CACHE_DIR"] = {str(cache)!r}
from autocal.core.coords import night_epoch
from autocal.fit.model import FitModel
from autocal.pipeline.config import CalibrationConfig, read_selection
from autocal.pipeline.partials import PartialSpec, compute_partial
from autocal.pipeline.readers import process_readers
from autocal.pipeline.sources import open_source, tsky_per_pol
if __name__ == "__main__":
    threads, ahead, method = int(sys.argv[1]), sys.argv[2] == "1", sys.argv[3]
    config = CalibrationConfig(inputs={[str(f) for f in files[:nfiles]]!r})
    source = open_source(config)
    pols = tuple(p.lower() for p in source.pols)
    tsky, _ = tsky_per_pol(config.sky, config, source, pols,
                           night_epoch(source.jds, source.site.lon_deg))
    model = FitModel.for_lsts(source.lsts, "constant", 0)
    spec = PartialSpec(model, "radiometer", read_selection(config), 1, 1)
    tasks = source.tasks(tsky)
    t0 = time.perf_counter()
    with process_readers(2, start_method=method, threads=threads, read_ahead=ahead) as pool:
        startup = pool.startup_seconds()
        t1 = time.perf_counter()
        for _ in pool.map_ordered(compute_partial, spec, tasks):
            pass
        t2 = time.perf_counter()
    print(json.dumps({{"startup_s": startup, "files_s": t2 - t1, "total_s": t2 - t0}}))
"""
    out = {}
    env = dict(os.environ)
    for threads, ahead in ((1, 1), (1, 0), (2, 1)):
        evict(files[:nfiles])
        proc = subprocess.run(
            [sys.executable, "-c", code, str(threads), str(ahead), "forkserver"],
            env=env,
            capture_output=True,
            text=True,
            check=True,
            cwd=ROOT,
        )
        value = json.loads(proc.stdout.strip().splitlines()[-1])
        value["per_file_s"] = round(value["files_s"] / nfiles, 2)
        out[f"threads={threads} read_ahead={bool(ahead)}"] = value
        print(f"  variant threads={threads} read_ahead={bool(ahead)}: {value}", flush=True)
    start_code = """
import sys, time
t0 = time.perf_counter()
from autocal.pipeline.readers import process_readers
if __name__ == "__main__":
    with process_readers(2, start_method=sys.argv[1]) as pool:
        s = pool.startup_seconds()
    print(s)
"""
    for method in ("spawn", "forkserver"):
        times = []
        for _ in range(2):
            proc = subprocess.run(
                [sys.executable, "-c", start_code, method],
                env=env,
                capture_output=True,
                text=True,
                check=True,
                cwd=ROOT,
            )
            times.append(float(proc.stdout.strip().splitlines()[-1]))
        out[f"startup {method}"] = {"seconds": [round(t, 2) for t in times]}
        print(f"  start of 2 processes, {method}: {times}", flush=True)
    return out


def markdown(report: dict) -> str:
    lines = [
        "# A night on two cores without Dask (`benchmarks/readers.py`)",
        "",
        f"{report['nfiles']} files, {report['disk_gb']} GB on disk, {report['machine']}; "
        f"`--products {report['products']}`; page cache evicted before every run; Tsky "
        f"cached; {report['rounds']} round(s), "
        "median. Load (1 / 5 / 15 min) before each run in the JSON.",
        "",
        "| run | wall s | over floor | CPU s | peak tree RSS GB | peak tree PSS GB |",
        "|---|---|---|---|---|---|",
    ]
    base = report["floor"]["wall_s"]
    lines.append(f"| serial decode floor | {base} | 1.00 | {report['floor']['cpu_s']} | | |")
    for name, row in report["runs"].items():
        lines.append(
            f"| `{name}` | {row['wall_s']} | {row['wall_s'] / base:.2f} | {row['cpu_s']} | "
            f"{row['peak_tree_rss_gb']} | {row['peak_tree_pss_gb']} |"
        )
    lines += ["", "Solutions, --readers 2 against --readers 1:"]
    for name, same in report.get("identical", {}).items():
        lines.append(f"- {name}: identical {same}")
    if report.get("variants"):
        lines += ["", "Variants:", "", "```", json.dumps(report["variants"], indent=1), "```"]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the night's folder")
    parser.add_argument("--files", type=int, help="only the first N files")
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument(
        "--steps", default="floor,serial,readers", help="floor, serial, readers, variants"
    )
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--products", default="hdf5", help="calibrate's --products (hdf5)")
    parser.add_argument(
        "--flagging", choices=("both", "on", "off"), default="both", help="runs with flagging"
    )
    args = parser.parse_args()
    steps = set(args.steps.split(","))
    files = night_files(args.data, args.files)
    cache = args.data / "tsky-cache"
    env = {**os.environ, "AUTOCAL_CACHE_DIR": str(cache)}
    print(f"{len(files)} files; Tsky into {cache} ...", flush=True)
    print(f"  Tsky {warm_tsky(files, cache):.1f} s", flush=True)
    runs = {
        name: extra
        for name, extra in RUNS.items()
        if (
            ("serial" in steps and "--readers 1" in name)
            or ("readers" in steps and "--readers 2" in name)
        )
        and (args.flagging == "both" or (args.flagging == "off") == ("--no-rfi" in name))
    }
    results: dict[str, list[dict]] = {"floor": [], **{name: [] for name in runs}}
    with tempfile.TemporaryDirectory(dir=args.data) as tmp:
        for round_ in range(args.rounds):
            if "floor" in steps:
                evict(files)
                argv = [sys.executable, __file__, "_floor", *map(str, files)]
                _children_cpu()
                run = run_tree(argv, env)
                run.update(json.loads(run.pop("stdout_tail").strip().splitlines()[-1]))
                results["floor"].append(run)
                print(f"round {round_} floor: {run['wall_s']} s", flush=True)
            for name, extra in runs.items():
                out = Path(tmp) / f"{round_}-{name.replace(' ', '_')}"
                evict(files)
                argv = [sys.executable, "-m", "autocal", "calibrate", *map(str, files)]
                _children_cpu()
                argv += ["--products", args.products, "--out", str(out), *extra]
                run = run_tree(argv, env)
                summary = json.loads((out / "summary.json").read_text())
                run["timings_s"] = summary["timings_s"]
                run["execution"] = {
                    k: v for k, v in summary["execution"].items() if k != "file_seconds"
                }
                run["out"] = str(out)
                results[name].append(run)
                print(f"round {round_} {name}: {run['wall_s']} s", flush=True)
        identical = {}
        for flagging in ("", " --no-rfi-flagging"):
            one, two = f"calibrate --readers 1{flagging}", f"calibrate --readers 2{flagging}"
            if results.get(one) and results.get(two):
                same = compare(Path(results[one][-1]["out"]), Path(results[two][-1]["out"]))
                identical[f"flagging {'off' if flagging else 'on'}"] = same["identical"]
    report = {
        "nfiles": len(files),
        "disk_gb": round(sum(f.stat().st_size for f in files) / 1e9, 2),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "rounds": args.rounds,
        "products": args.products,
        "load_at_end": [round(x, 2) for x in os.getloadavg()],
        "all": results,
        "identical": identical,
    }
    if results["floor"]:
        report["floor"] = {
            "wall_s": statistics.median(r["wall_s"] for r in results["floor"]),
            "cpu_s": statistics.median(r["cpu_s"] for r in results["floor"]),
        }
    report["runs"] = {
        name: {
            key: statistics.median(r[key] for r in rows)
            for key in ("wall_s", "cpu_s", "peak_tree_rss_gb", "peak_tree_pss_gb")
        }
        for name, rows in results.items()
        if name != "floor" and rows
    }
    if "variants" in steps:
        report["variants"] = variants(files, cache, min(4, len(files)))
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "readers.json").write_text(json.dumps(report, indent=2, default=str))
    if "floor" in report:
        (args.results / "readers.md").write_text(markdown(report))
        print(markdown(report))
    else:
        print(json.dumps(report["runs"], indent=1))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "_floor":
        print(json.dumps(floor(sys.argv[2:])))
    else:
        main()
