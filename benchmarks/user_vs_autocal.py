"""Benchmark: ``autocal calibrate`` against what a user would write (pyuvdata + numpy).

Target (issue 25, item 3): on the same file, autocal >= 3x faster than
``benchmarks/user_script.py`` (``UVData.read`` of the autos + a vectorised numpy least-squares
fit of ``autos = G (Tsky + Trxr)`` per antenna, pol and channel) at <= 1/5 of its peak memory.

Both get the same Tsky for free: it is computed once beforehand with autocal's own pipeline
functions into autocal's Tsky cache (``AUTOCAL_CACHE_DIR``, default ``/tmp/autocal-user-vs-
autocal-cache``), which ``autocal calibrate`` then reads, and written as the ``.npz`` the
user script loads. Each command runs as a fresh process (``python benchmarks/user_script.py
FILE ...`` and ``python -m autocal calibrate FILE --out DIR``, all products, and again with
``--products hdf5``, the nearest to the script's ``.npz``); wall time, CPU time and peak RSS
(``ru_maxrss`` of the child from ``wait4``; the driver itself stays small, since a child's
``ru_maxrss`` starts from its parent's RSS at the fork). One unmeasured run of each
first (page cache, numba's cache), then ``--repeats`` rounds with the commands
interleaved; the median is reported. The two fits are not the same estimator (autocal:
radiometer weights, flags and checks; the script: unweighted least squares), so their G are
compared only as a check that both solved the same problem (median ``|G_user / G_autocal - 1|``)::

    python benchmarks/user_vs_autocal.py                       # the real HERA file
    python benchmarks/user_vs_autocal.py --file /tmp/autocal-night-350x1536x192/zen.*.uvh5 \\
        --repeats 1 --label night-file
    # one file of the HERA-size night: python benchmarks/night.py generate --ntimes 192

Results are added to ``benchmarks/results/user_vs_autocal.json`` and ``.md`` under
``--label``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT_FILE = "hera/autos/zen.2458116.30448.HH.uvh5"
DEFAULT_CACHE = "/tmp/autocal-user-vs-autocal-cache"


def write_tsky(path: Path, out: Path) -> dict:
    """Tsky of the file's grid as autocal computes it (cached), written as the script's npz."""
    from autocal.core.coords import night_epoch
    from autocal.pipeline.config import CalibrationConfig
    from autocal.pipeline.sources import open_source, tsky_per_pol

    config = CalibrationConfig(inputs=[str(path)])
    source = open_source(config)
    pols = tuple(p.lower() for p in source.pols)
    epoch = night_epoch(source.jds, source.site.lon_deg)
    start = time.perf_counter()
    tsky, _ = tsky_per_pol(config.sky, config, source, pols, epoch)
    np.savez(out, tsky=tsky, jds=np.asarray(source.jds), pols=np.array(pols))
    return {"shape": list(tsky.shape), "pols": list(pols), "seconds": time.perf_counter() - start}


def run_child(argv: list[str], env: dict[str, str]) -> dict:
    """Run one command as a fresh process: wall time and peak RSS (``ru_maxrss``)."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    stdout, stderr = proc.stdout.read(), proc.stderr.read()  # type: ignore[union-attr]
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise SystemExit(f"{' '.join(argv)}: exit {code}\n{stderr.decode()[-2000:]}")
    return {
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_gb": usage.ru_maxrss * 1024 / 1e9,
        "stdout_tail": stdout.decode()[-200:],
    }


def commands(path: Path, tsky: Path, work: Path) -> dict[str, list[str]]:
    """The measured commands (fresh output paths each time they are asked for)."""
    stamp = f"{time.monotonic_ns()}"

    def calibrate(name: str, *options: str) -> list[str]:
        out = str(work / f"{name}-{stamp}")
        return [sys.executable, "-m", "autocal", "calibrate", str(path), "--out", out, *options]

    return {
        "user script (pyuvdata + numpy)": [
            sys.executable,
            str(ROOT / "benchmarks" / "user_script.py"),
            str(path),
            "--tsky",
            str(tsky),
            "--out",
            str(work / f"user-{stamp}.npz"),
        ],
        "autocal calibrate (calh5, hdf5, png)": calibrate("autocal"),
        "autocal calibrate --products hdf5": calibrate("autocal-hdf5", "--products", "hdf5"),
        "autocal calibrate --products hdf5 --no-rfi-flagging": calibrate(
            "autocal-bare", "--products", "hdf5", "--no-rfi-flagging"
        ),
    }


def agreement(work: Path) -> float:
    """Median ``|G_user / G_autocal - 1|`` over the channels both solved (last runs)."""
    import autocal

    user = np.load(sorted(work.glob("user-*.npz"))[-1])
    folder = sorted(p for p in work.glob("autocal-hdf5-*") if p.is_dir())[-1]
    summary = autocal.read_summary(folder)
    solution = autocal.read_solution(summary["products"]["hdf5"])
    gain_a = solution.coeffs[..., 0]  # (Nant, Npol, Nfreq): G of the constant model
    index = [list(user["antennas"]).index(a) for a in solution.antennas]
    order = [list(user["pols"]).index(p) for p in solution.pols]
    gain_u = user["gain"][index][:, order]
    ratio = np.abs(gain_u / gain_a - 1)
    return float(np.nanmedian(ratio[np.isfinite(ratio)]))


def measure(
    path: Path, repeats: int, env: dict[str, str], warmup: bool, variants: list[str]
) -> dict:
    """Tsky once, one unmeasured run of each command, then ``repeats`` interleaved rounds."""
    with tempfile.TemporaryDirectory(prefix="autocal-user-vs-") as tmp:
        work = Path(tmp)
        tsky_file = work / "tsky.npz"
        # in a child process: a child's ru_maxrss starts from its parent's RSS at the fork,
        # so the parent must stay small (no beam maps or sky in it)
        done = subprocess.run(
            [sys.executable, __file__, "_tsky", str(path), str(tsky_file)],
            env=env,
            check=True,
            capture_output=True,
            text=True,
        )
        tsky = json.loads(done.stdout.strip().splitlines()[-1])
        print(f"Tsky {tsky['shape']} in {tsky['seconds']:.1f} s", flush=True)
        for name, argv in commands(path, tsky_file, work).items():
            if warmup and name in variants:
                print(f"warm-up: {name}", flush=True)
                run_child(argv, env)
        runs: dict[str, list[dict]] = {}
        load = [os.getloadavg()[0]]
        for _ in range(repeats):
            for name, argv in commands(path, tsky_file, work).items():
                if name not in variants:
                    continue
                result = run_child(argv, env)
                runs.setdefault(name, []).append(result)
                print(
                    f"{name}: {result['wall_s']:.2f} s, {result['peak_rss_gb']:.2f} GB", flush=True
                )
                load.append(os.getloadavg()[0])
        median_g = agreement(work) if "autocal calibrate --products hdf5" in variants else None
        shutil.rmtree(work, ignore_errors=True)
    rows = {
        name: {
            "wall_s": statistics.median(r["wall_s"] for r in rs),
            "cpu_s": statistics.median(r["cpu_s"] for r in rs),
            "peak_rss_gb": statistics.median(r["peak_rss_gb"] for r in rs),
            "wall_all_s": [round(r["wall_s"], 2) for r in rs],
        }
        for name, rs in runs.items()
    }
    return {"tsky": tsky, "rows": rows, "load": load, "median_abs_g_ratio_minus_1": median_g}


def markdown(reports: dict[str, dict]) -> str:
    """Every label's table, with the ratios to the user script."""
    lines = [
        "# autocal calibrate vs a pyuvdata + numpy script (`benchmarks/user_vs_autocal.py`)",
        "",
    ]
    for label, rep in reports.items():
        user = rep["rows"]["user script (pyuvdata + numpy)"]
        lines += [
            f"## {label}: `{rep['file']}` ({rep['date']})",
            "",
            f"{rep['file_mb']:.1f} MB, Tsky {rep['tsky']['shape']} (pols {rep['tsky']['pols']}); "
            f"median of {rep['repeats']} run(s); load average {min(rep['load']):.1f}-"
            f"{max(rep['load']):.1f} during the runs on a {rep['machine']['cpus']}-core machine "
            "shared with other work.",
            "",
            "| command | wall s | CPU s | peak RSS GB | speed-up vs script | memory vs script |",
            "|---|---|---|---|---|---|",
        ]
        for name, row in rep["rows"].items():
            lines.append(
                f"| {name} | {row['wall_s']:.2f} | {row['cpu_s']:.2f} | {row['peak_rss_gb']:.2f} | "
                f"{user['wall_s'] / row['wall_s']:.2f}x | "
                f"{row['peak_rss_gb'] / user['peak_rss_gb']:.2f} |"
            )
        lines += [
            "",
            f"Median |G_script / G_autocal - 1| = {rep['median_abs_g_ratio_minus_1']:.2e} "
            "(different estimators: a check that both fit the same data, not an error)."
            if rep["median_abs_g_ratio_minus_1"] is not None
            else "",
            "",
        ]
    return "\n".join(lines)


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "_tsky":
        print(json.dumps(write_tsky(Path(sys.argv[2]), Path(sys.argv[3]))))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--file", type=Path, help=f"UVH5 file (default: data folder's {DEFAULT_FILE})"
    )
    parser.add_argument("--repeats", type=int, default=3, help="measured rounds (3)")
    parser.add_argument("--label", default="real HERA file", help="name of this measurement")
    parser.add_argument(
        "--no-warmup", action="store_true", help="no unmeasured run first (caches already warm)"
    )
    parser.add_argument(
        "--variants",
        default="user,autocal,autocal-hdf5",
        help=(
            "commands to run: user, autocal (all products), autocal-hdf5, autocal-bare "
            "(hdf5 without flagging: the work the script does) (default: the first three)"
        ),
    )
    parser.add_argument("--results", type=Path, default=RESULTS, help="folder of the reports")
    args = parser.parse_args()
    env = dict(os.environ)
    env.setdefault("AUTOCAL_CACHE_DIR", DEFAULT_CACHE)
    env.setdefault("MPLBACKEND", "Agg")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    os.environ.update({k: env[k] for k in ("AUTOCAL_CACHE_DIR", "MPLBACKEND")})
    path = args.file
    if path is None:
        from autocal.io.datasets import data_file

        path = Path(data_file(DEFAULT_FILE))
    names = {
        "user": "user script (pyuvdata + numpy)",
        "autocal": "autocal calibrate (calh5, hdf5, png)",
        "autocal-hdf5": "autocal calibrate --products hdf5",
        "autocal-bare": "autocal calibrate --products hdf5 --no-rfi-flagging",
    }
    variants = [names[v.strip()] for v in args.variants.split(",")]
    report = measure(path.resolve(), args.repeats, env, not args.no_warmup, variants)
    report.update(
        file=str(path),
        file_mb=path.stat().st_size / 1e6,
        repeats=args.repeats,
        warmup=not args.no_warmup,
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        machine={"cpus": os.cpu_count(), "python": platform.python_version()},
    )
    args.results.mkdir(parents=True, exist_ok=True)
    json_path = args.results / "user_vs_autocal.json"
    reports = json.loads(json_path.read_text()) if json_path.exists() else {}
    reports[args.label] = report
    json_path.write_text(json.dumps(reports, indent=2))
    text = markdown(reports)
    (args.results / "user_vs_autocal.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
