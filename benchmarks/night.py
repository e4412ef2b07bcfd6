"""Benchmark: calibrating a HERA-size night (issue 7, "Performance and scale").

One command generates the night if it is absent, calibrates 1/4, 1/2 and the whole night
serially, each in a fresh subprocess (wall time, peak RSS, bytes read, throughput),
calibrates the night again through a Dask LocalCluster of 2 workers, compares the two
solutions bit for bit, and writes ``night.json`` and ``night.md``::

    .venv/bin/python benchmarks/night.py                        # the full HERA night
    .venv/bin/python benchmarks/night.py --ants 20 --ntimes 1152  # a quick small night

The night (defaults): 350 antennas x pols ee/nn (UVH5 codes -5/-6, x = east) x 1536
channels over 100-200 MHz (65.1 kHz: the band of the HERA beam model) x 8640
integrations of 10/3 sidereal s (3.324 s) = 8 sidereal hours of LST from 2 h, in 45
files of 192 integrations (10.6 min each), autos only, HERA telescope metadata. Data:
``d = G_a(nu) (Tsky(nu, t) + Trxr_a(nu)) (1 + n / sqrt(dnu dt))`` with Tsky = GSM2008
through the HERA (Fagnoni CST) beam incl. CMB and 300 K ground, G_a = per-antenna scale
x H1C bandpass (floored at the band edges) x a cable-reflection ripple, Trxr_a 100-200 K
with a slope, n ~ N(0, 1) (radiometer noise, dnu dt = 2.2e5). Stored as complex64 with
HDF5 byte-shuffle + gzip level 1 (chunks: one integration x 256 channels x 1 pol;
flags and nsamples the same filter): see ``--dtype``/``--compression``. Subcommands:
``generate`` (only the files) and ``run`` (the default, everything).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import math
import os
import platform
import resource
import shutil
import subprocess
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT_DATA = Path("/tmp/autocal-night")
SIDEREAL_DAY = 0.9972695663


@dataclass(frozen=True)
class Night:
    """How the night is generated (recorded in the folder's ``night.json``)."""

    ants: int = 350
    nfreq: int = 1536
    ntimes: int = 8640
    per_file: int = 192
    freq_start_mhz: float = 100.0
    freq_stop_mhz: float = 200.0
    cadence_sidereal_s: float = 10.0 / 3.0
    lst_start_h: float = 2.0
    jd_start: float = 2458098.0
    seed: int = 2026
    dtype: str = "c8"
    compression: str = "gzip"
    part: int = 8  # integrations generated and written at once

    @property
    def is_full(self) -> bool:
        return (self.ants, self.nfreq, self.ntimes) == (350, 1536, 8640)

    @property
    def nfiles(self) -> int:
        return math.ceil(self.ntimes / self.per_file)

    @property
    def channel_width(self) -> float:
        return (self.freq_stop_mhz - self.freq_start_mhz) * 1e6 / self.nfreq

    @property
    def integration_time(self) -> float:
        return self.cadence_sidereal_s * SIDEREAL_DAY

    def freqs(self) -> np.ndarray:
        return self.freq_start_mhz * 1e6 + self.channel_width * np.arange(self.nfreq)

    def lsts(self) -> np.ndarray:
        return (self.lst_start_h + np.arange(self.ntimes) * self.cadence_sidereal_s / 3600) % 24


# generation ----------------------------------------------------------------------------

#: Integrations whose Tsky ``truth.h5`` keeps (:func:`tsky_mismatch`) and the largest
#: relative difference from a recomputation that still counts as the same Tsky.
TSKY_CHECK_TIMES = 4
TSKY_CHECK_RTOL = 1e-9


def _bandpass(freqs: np.ndarray) -> np.ndarray:
    """H1C bandpass G(nu) (hera_sim polynomial), 1 at 150 MHz, floored at the band edges."""
    from autocal.io.datasets import data_file

    coeffs = np.load(data_file("hera/instrument/HERA_H1C_BANDPASS.npy"))
    amp = np.polyval(coeffs, freqs / 1e9) / np.polyval(coeffs, 0.15)
    return np.maximum(amp, 0.0) ** 2 + 0.05**2


def _truth(night: Night) -> dict[str, np.ndarray]:
    """Per-antenna gains G (A, P, F) in raw units per K and Trxr (A, P, F) in K."""
    rng = np.random.default_rng([night.seed, 0])
    freqs = night.freqs()
    shape = (night.ants, 2, 1)
    x = (freqs - 150e6) / 50e6
    scale = rng.uniform(0.015, 0.025, shape)  # raw correlator units per kelvin
    ripple = 1 + rng.uniform(0.0, 0.02, shape) * np.cos(
        2 * np.pi * freqs * rng.uniform(100e-9, 1000e-9, shape) + rng.uniform(0, 2 * np.pi, shape)
    )
    gain = scale * _bandpass(freqs) * ripple
    trxr = rng.uniform(100.0, 200.0, shape) * (1 + rng.uniform(-0.2, 0.2, shape) * x)
    return {"gain": gain, "trxr": trxr}


def _write_file(args: tuple) -> dict:
    """Write one file of the night in parts (runs in a pool process)."""
    from autocal.core.sites import get_site
    from autocal.io.uvh5_writer import UVH5AutosWriter

    night, index, path, jds, lsts, tsky, gain, trxr = args
    bt = night.channel_width * night.integration_time
    rng = np.random.default_rng([night.seed, 1, index])
    start = time.perf_counter()
    with UVH5AutosWriter(
        path,
        freqs=night.freqs(),
        channel_width=night.channel_width,
        jds=jds,
        lsts=lsts,
        integration_time=night.integration_time,
        antennas=np.arange(night.ants),
        pols=("ee", "nn"),
        site=get_site("hera"),
        telescope_name="HERA",
        history=f"autocal benchmarks/night.py: simulated HERA night, file {index}",
        extra_keywords={"autocal_sim": "night", "noise_dnu_dt": bt},
        dtype=night.dtype,
        compression=night.compression,
        overwrite=True,
    ) as writer:
        for s in range(0, lsts.size, night.part):
            t = tsky[:, s : s + night.part]  # (P, t, F)
            data = gain[:, :, None, :] * (t[None] + trxr[:, :, None, :])
            noise = rng.standard_normal(data.shape, dtype=np.float32)
            noise *= np.float32(1 / math.sqrt(bt))
            noise += np.float32(1)
            data *= noise
            del noise
            writer.write(s, data)
            del data
    return {"file": str(path), "bytes": path.stat().st_size, "seconds": time.perf_counter() - start}


def generate(night: Night, folder: Path, jobs: int) -> dict:
    """Write the night's UVH5 files, ``truth.h5`` and ``night.json`` into ``folder``."""
    import h5py

    from autocal.core.sites import get_site
    from autocal.simulate.mock import lsts_to_jds
    from autocal.tsky.compute import compute_tsky

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "night.json").unlink(missing_ok=True)
    for old in folder.glob("zen.*.uvh5"):
        old.unlink()
    t0 = time.perf_counter()
    site = get_site("hera")
    lsts = night.lsts()
    jds = lsts_to_jds(lsts, site, night.jd_start)
    freqs = night.freqs()
    print(f"generating {night.nfiles} files into {folder}: Tsky first", flush=True)
    tsky = np.empty((2, night.ntimes, night.nfreq))
    for ip, pol in enumerate(("ee", "nn")):
        tsky[ip] = compute_tsky(
            "gsm2008",
            "hera",
            site,
            freqs,
            lsts,
            nside=64,
            epoch=float(jds.mean()),
            pol=pol,
            cache=False,  # today's engine, never a cached result (tsky_mismatch)
        ).tsky
    t_tsky = time.perf_counter() - t0
    truth = _truth(night)
    with h5py.File(folder / "truth.h5", "w") as h5:
        h5["gain"] = truth["gain"]
        h5["trxr"] = truth["trxr"]
        h5["freqs"] = freqs
        h5["antennas"] = np.arange(night.ants)
        h5.attrs["pols"] = "ee,nn"
        h5.attrs["night"] = json.dumps(asdict(night))
        # the Tsky the data were made with, at the first integrations: tells stale data
        # (an older Tsky engine) from current ones (:func:`tsky_mismatch`)
        h5["tsky_check"] = tsky[:, :TSKY_CHECK_TIMES]
        h5.attrs["tsky_epoch"] = float(jds.mean())
    tasks = []
    for i in range(night.nfiles):
        w = slice(i * night.per_file, min((i + 1) * night.per_file, night.ntimes))
        path = folder / f"zen.{jds[w][0]:.5f}.HH.autos.uvh5"
        tasks.append((night, i, path, jds[w], lsts[w], tsky[:, w].copy(), *truth.values()))
    files = []
    with ProcessPoolExecutor(max_workers=max(1, jobs)) as pool:
        for done in pool.map(_write_file, tasks):
            files.append(done)
            print(
                f"  {len(files)}/{night.nfiles} {Path(done['file']).name} "
                f"{done['bytes'] / 1e6:.0f} MB {done['seconds']:.1f} s",
                flush=True,
            )
    manifest = {
        "night": asdict(night),
        "files": [f["file"] for f in files],
        "bytes": [f["bytes"] for f in files],
        "total_bytes": sum(f["bytes"] for f in files),
        "complex64_bytes": night.ants * 2 * night.nfreq * night.ntimes * 8,
        "generate_s": round(time.perf_counter() - t0, 1),
        "tsky_s": round(t_tsky, 1),
        "jobs": jobs,
    }
    (folder / "night.json").write_text(json.dumps(manifest, indent=2))
    return manifest


def tsky_mismatch(folder: Path) -> str | None:
    """Say why the night in ``folder`` was not made with the current Tsky engine, or ``None``.

    ``truth.h5`` keeps the Tsky of the first :data:`TSKY_CHECK_TIMES` integrations the
    data were made with; they are computed again here (a few seconds; without the cache,
    as :func:`generate` computes them). A night simulated by
    an older engine is a model error of its own: the first file of a night made before
    the sky's band limit (commit 6f99f8e) differs from today's model by 2-6e-5 of the
    total power, drifting over the file, which a whole-file diagnosis rightly detects
    (a "gain drift" at 7 sigma on 206 M samples).
    """
    import h5py

    from autocal.core.sites import get_site
    from autocal.tsky.compute import compute_tsky

    if not (folder / "truth.h5").exists():
        return "made without its truth.h5"
    with h5py.File(folder / "truth.h5", "r") as h5:
        if "tsky_check" not in h5:
            return "made before its Tsky was recorded (truth.h5 has no tsky_check)"
        stored = h5["tsky_check"][()]
        epoch = float(h5.attrs["tsky_epoch"])
        night = Night(**json.loads(h5.attrs["night"]))
    lsts = night.lsts()[: stored.shape[1]]
    worst = 0.0
    for ip, pol in enumerate(("ee", "nn")):
        now = compute_tsky(
            "gsm2008",
            "hera",
            get_site("hera"),
            night.freqs(),
            lsts,
            nside=64,
            epoch=epoch,
            pol=pol,
            cache=False,
        ).tsky
        diff = np.abs(now / stored[ip] - 1)
        worst = max(worst, float(np.max(diff)) if np.all(np.isfinite(diff)) else np.inf)
    if not worst <= TSKY_CHECK_RTOL:
        return f"made with another Tsky (max relative difference {worst:.1e} from today's)"
    return None


def load_or_generate(night: Night, folder: Path, jobs: int, regenerate: bool) -> dict:
    """Return the folder's manifest, generating the night when absent, different or stale."""
    path = folder / "night.json"
    if path.exists() and not regenerate:
        manifest = json.loads(path.read_text())
        if manifest["night"] == asdict(night) and all(Path(f).exists() for f in manifest["files"]):
            stale = tsky_mismatch(folder)
            if stale is None:
                print(f"night found in {folder} ({manifest['total_bytes'] / 1e9:.2f} GB)")
                return manifest
            print(f"the night in {folder} was {stale}: regenerating")
        else:
            print(f"{folder} holds another night: regenerating")
    return generate(night, folder, jobs)


# one measured calibration (in a fresh subprocess) ----------------------------------------


def _proc_io() -> dict[str, int]:
    try:
        text = Path("/proc/self/io").read_text()
    except OSError:
        return {}
    return {k: int(v) for k, v in (line.split(": ") for line in text.splitlines())}


class _TreeSampler(threading.Thread):
    """Sample the summed RSS of this process and its children (psutil) every 0.2 s."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.peak = 0
        self._halt = threading.Event()

    def run(self) -> None:
        import psutil

        me = psutil.Process()
        while not self._halt.is_set():
            total = 0
            for proc in [me, *me.children(recursive=True)]:
                with contextlib.suppress(psutil.Error):
                    total += proc.memory_info().rss
            self.peak = max(self.peak, total)
            self._halt.wait(0.2)

    def stop(self) -> int:
        self._halt.set()
        self.join()
        return self.peak


def calibrate_child(spec: dict) -> None:
    """Run one calibration and write its measurements (the subprocess side)."""
    from autocal.pipeline.calibrate import run_calibration
    from autocal.pipeline.config import CalibrationConfig

    os.environ["AUTOCAL_CACHE_DIR"] = spec["cache"]
    files = [Path(f) for f in spec["files"]]
    for f in files:  # evict our files from the page cache: read_bytes then counts disk reads
        fd = os.open(f, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)
    from autocal.pipeline.scaleout import peak_rss_bytes

    sampler = _TreeSampler()
    sampler.start()
    io0 = _proc_io()
    phase_peaks: dict[str, int] = {}

    def progress(fraction: float, message: str) -> None:
        # Entering the streamed fit: record the peak so far (scan + Tsky) and reset the
        # high-water mark (Linux clear_refs 5), so the fit's own peak is measured too.
        if fraction >= 0.1 and "before_fit" not in phase_peaks:
            phase_peaks["before_fit"] = peak_rss_bytes()
            with contextlib.suppress(OSError):
                Path("/proc/self/clear_refs").write_text("5")

    t0 = time.perf_counter()
    config = CalibrationConfig(
        inputs=[str(f) for f in files],
        products=["calh5", "hdf5", "png"],
        model=spec.get("model", "constant"),
        order=spec.get("order", 1),
    )
    result = run_calibration(
        config,
        spec["out"],
        progress=progress,
        dask_scheduler=spec.get("dask"),
        dask_workers=spec.get("dask_workers"),
    )
    wall = time.perf_counter() - t0
    io1 = _proc_io()
    tree_peak = sampler.stop()
    fit_peak = peak_rss_bytes()
    out = {
        "wall_s": wall,
        "timings_s": result.timings,
        "execution": result.summary["execution"],
        "passes": result.summary["provenance"]["passes"],
        "peak_rss_self_bytes": max(fit_peak, phase_peaks.get("before_fit", 0)),
        "peak_rss_before_fit_bytes": phase_peaks.get("before_fit", 0),
        "peak_rss_fit_and_products_bytes": fit_peak,
        "ru_maxrss_children_bytes": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024,
        "peak_rss_tree_bytes": tree_peak,
        "proc_io": {k: io1.get(k, 0) - io0.get(k, 0) for k in io1},
        "solution": result.summary["solution"],
    }
    Path(spec["result"]).write_text(json.dumps(out, indent=2, default=str))


def measure(
    name: str,
    files: list[str],
    folder: Path,
    dask: str | None,
    workers: int,
    fit_model: dict | None = None,
) -> dict:
    """Calibrate ``files`` in a fresh subprocess and return its measurements.

    ``fit_model``: ``{"model": ..., "order": ...}`` (default: the pipeline's constant model).
    """
    out = folder / "runs" / name
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    spec = {
        "files": files,
        "out": str(out),
        "cache": str(folder / "tsky-cache"),
        "result": str(out / "measurements.json"),
        "dask": dask,
        "dask_workers": workers if dask else None,
        **(fit_model or {}),
    }
    print(f"calibrating {name}: {len(files)} files{' on Dask' if dask else ''} ...", flush=True)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, __file__, "_calibrate", json.dumps(spec)], check=True, cwd=ROOT)
    result = json.loads(Path(spec["result"]).read_text())
    result["subprocess_s"] = time.perf_counter() - t0
    result["out"] = str(out)
    print(f"  done in {result['wall_s']:.1f} s", flush=True)
    return result


# comparison and report -----------------------------------------------------------------


def compare_solutions(a_path: Path, b_path: Path) -> dict:
    """Bit-for-bit comparison of two solution.h5 files (coeffs, cov, chi2, dof, counts)."""
    from autocal.io.products import read_solution

    a, b = read_solution(a_path), read_solution(b_path)
    out: dict = {"identical": True, "max_rel_diff": 0.0}
    for name in ("coeffs", "cov", "chi2", "dof", "count", "nflagged", "flag_reason"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        same = bool(np.array_equal(x, y, equal_nan=x.dtype.kind == "f"))
        out["identical"] &= same
        if x.dtype.kind == "f":
            ok = np.isfinite(x) & np.isfinite(y) & (x != 0)
            if np.any(ok):
                rel = float(np.max(np.abs(y[ok] / x[ok] - 1)))
                out["max_rel_diff"] = max(out["max_rel_diff"], rel)
        out[name] = same
    return out


def truth_check(solution_path: Path, folder: Path) -> dict:
    """How well the full-night solution recovers the simulated G and Trxr."""
    import h5py

    from autocal.io.products import read_solution

    sol = read_solution(solution_path)
    if not (folder / "truth.h5").exists():
        return "made without its truth.h5"
    with h5py.File(folder / "truth.h5", "r") as h5:
        gain, trxr = h5["gain"][()], h5["trxr"][()]
    ok = ~sol.flags
    g_err = np.abs(sol.G / gain - 1)[ok]
    t_err = np.abs(sol.Trxr - trxr)[ok]
    pull = ((sol.G - gain) / sol.sigma_G)[ok]
    return {
        "median_abs_G_rel_err": float(np.median(g_err)),
        "median_abs_Trxr_err_K": float(np.median(t_err)),
        "rms_G_pull": float(np.sqrt(np.mean(pull[np.isfinite(pull)] ** 2))),
        "flagged_channels": int(sol.flags.sum()),
    }


def profile_file(path: str) -> dict:
    """Profile the per-block path on one file (pyinstrument): where the time goes.

    The profile runs the reader's stages in the calling thread (``prefetch=False``); the
    file's time as the pipeline runs it (reading and decoding pipelined in background
    threads) is reported beside it.
    """
    from pyinstrument import Profiler

    import autocal.pipeline.partials as partials
    from autocal.fit.model import FitModel
    from autocal.io.uvh5_meta import scan_uvh5
    from autocal.pipeline.partials import FileTask, PartialSpec, compute_partial

    file = scan_uvh5([path])[0]
    tsky = np.full((len(file.pols), file.lsts.size, file.freqs.size), 300.0)  # any values
    selection = {"antennas": None, "pols": None, "freq_range": None, "lst_range": None}
    spec = PartialSpec(FitModel.for_lsts(file.lsts), "radiometer", selection, 2, 1)
    task = FileTask(0, file, 0, file.lsts, tsky)
    pipelined = compute_partial(spec, task).seconds  # as the pipeline runs (warms the cache)
    # pyinstrument samples the calling thread: run every stage there (no prefetch threads)
    real = partials.iter_uvh5_blocks  # the name the pipeline calls is bound there
    partials.iter_uvh5_blocks = functools.partial(real, prefetch=False)
    try:
        profiler = Profiler(interval=0.005)
        profiler.start()
        partial = compute_partial(spec, task)
        profiler.stop()
    finally:
        partials.iter_uvh5_blocks = real
    parts = {
        "read_rows": "HDF5 reads + decompression",
        "iter_uvh5_blocks": "block reader total (incl. HDF5)",
        "file_checksum": "SHA-256 of the file",
        "accumulate": "autocal.fit.sums.accumulate (normal sums)",
        "bandwidth_time": "dnu dt N per sample",
        "_add_waterfall": "waterfall sums (2 antennas)",
        "_add_into": "adding block sums",
        "__post_init__": "Observation checks",
    }
    found = dict.fromkeys(parts, 0.0)

    def walk(frame, inside: frozenset) -> None:
        name = frame.function
        if name in found and name not in inside:
            found[name] += frame.time
            inside = inside | {name}
        for child in frame.children:
            walk(child, inside)

    walk(profiler.last_session.root_frame(), frozenset())
    total = partial.seconds
    return {
        "file": Path(path).name,
        "seconds": round(total, 2),
        "pipelined_seconds": round(pipelined, 2),
        "values": partial.stats["samples"],
        "blocks": partial.stats["blocks"],
        "parts_s": {parts[k]: round(v, 2) for k, v in found.items()},
        "text": profiler.output_text(unicode=False, color=False),
    }


def machine() -> dict:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = 0
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem = int(line.split()[1]) * 1024
    except OSError:
        pass
    disk = shutil.disk_usage("/tmp")
    import dask
    import h5py
    import pyuvdata

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "ram_gb": round(mem / 1e9, 1),
        "disk_free_gb": round(disk.free / 1e9, 1),
        "disk_total_gb": round(disk.total / 1e9, 1),
        "load_avg_1_5_15": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
        "numpy": np.__version__,
        "h5py": h5py.__version__,
        "pyuvdata": pyuvdata.__version__,
        "dask": dask.__version__,
    }


def _row(label: str, nfiles: int, run: dict, manifest: dict, night: Night) -> dict:
    ex = run["execution"]
    io = ex["io"]
    ntime = sum(min(night.per_file, night.ntimes - i * night.per_file) for i in range(nfiles))
    disk = ex["bytes_on_disk"]
    samples = ex["samples_per_pass"] * run["passes"]
    startup = ex.get("dask", {}).get("startup_s", 0.0)  # before the scan, not in fit_s
    fit = run["timings_s"]["fit_s"]
    worker_peak = max(ex.get("dask", {}).get("worker_peak_rss_bytes", {}).values(), default=0)
    return {
        "run": label,
        "files": nfiles,
        "integrations": ntime,
        "hours_lst": round(ntime * night.cadence_sidereal_s / 3600, 2),
        "samples": samples,
        "disk_gb": round(disk / 1e9, 2),
        "wall_s": round(run["wall_s"], 1),
        "tsky_s": round(run["timings_s"]["tsky_s"], 1),
        "fit_s": round(fit, 1),
        "dask_startup_s": round(startup, 1),
        "products_s": round(run["timings_s"]["products_s"], 1),
        "passes": run["passes"],
        "peak_rss_gb": round(run["peak_rss_self_bytes"] / 1e9, 2),
        "peak_rss_before_fit_gb": round(run["peak_rss_before_fit_bytes"] / 1e9, 2),
        "peak_rss_fit_gb": round(run["peak_rss_fit_and_products_bytes"] / 1e9, 2),
        "worker_peak_rss_gb": round(worker_peak / 1e9, 2),
        "tree_peak_rss_gb": round(run["peak_rss_tree_bytes"] / 1e9, 2),
        "hdf5_read_over_disk": round(io.get("bytes_read", 0) / disk, 3) if disk else None,
        "checksum_read_over_disk": round(io.get("checksum_bytes", 0) / disk, 3) if disk else None,
        "process_rchar_over_disk": round(run["proc_io"].get("rchar", 0) / disk, 3)
        if disk
        else None,
        "process_disk_reads_over_disk": round(run["proc_io"].get("read_bytes", 0) / disk, 3)
        if disk
        else None,
        "largest_array_mb": round(io.get("largest_array", 0) / 1e6, 1),
        "blocks": io.get("blocks", 0),
        "msamples_per_s_fit": round(samples / fit / 1e6, 1),
        "msamples_per_s_wall": round(samples / run["wall_s"] / 1e6, 1),
        "disk_mb_per_s_fit": round(disk * run["passes"] / fit / 1e6, 1),
        "c8_mb_per_s_fit": round(samples * 8 / fit / 1e6, 1),
    }


def _model_text(fit_model: dict | None) -> str:
    if not fit_model or fit_model.get("model", "constant") == "constant":
        return "constant G, Trxr (the default)"
    return f"Legendre order {fit_model['order']} in LST (`--model legendre --order N`)"


def markdown(report: dict) -> str:
    m, night, manifest = report["machine"], report["night"], report["storage"]
    lines = [
        "# A HERA-size night: calibration benchmark",
        "",
        f"Command: `{report['command']}` (total {report['total_s'] / 60:.1f} min, "
        f"generation {'included' if report['generated'] else 'skipped: files found'}).",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, {m['ram_gb']} GB RAM, "
        f"/tmp {m['disk_free_gb']} GB free of {m['disk_total_gb']} GB; load average "
        f"{m['load_avg_1_5_15']} at the start (the machine was shared: timings are noisy). "
        f"Python {m['python']}, numpy {m['numpy']}, h5py {m['h5py']}, pyuvdata "
        f"{m['pyuvdata']}, dask {m['dask']}.",
        "",
        "## The night",
        "",
        f"{night['ants']} antennas x 2 pols (ee, nn) x {night['nfreq']} channels "
        f"({night['freq_start_mhz']:.0f}-{night['freq_stop_mhz']:.0f} MHz, "
        f"{report['channel_width_khz']:.2f} kHz) x {night['ntimes']} integrations of "
        f"{night['cadence_sidereal_s']:.4f} sidereal s ({report['integration_time_s']:.4f} s), "
        f"LST {night['lst_start_h']:.1f} h + {report['hours_lst']:.2f} h, "
        f"in {len(manifest['bytes'])} files of {night['per_file']} integrations; autos only; "
        f"dnu dt = {report['dnu_dt']:.3g} (data-weight bias 2/(dnu dt) = "
        f"{2 / report['dnu_dt']:.2g} < 1e-5: one pass).",
        "",
        f"Storage: {night['dtype']} visdata with HDF5 byte shuffle + {night['compression']}"
        f"{' (level 1)' if night['compression'] == 'gzip' else ''}, chunks of one "
        "integration x 256 channels x 1 pol; flags and nsamples with the same filter. "
        f"Per file {np.mean(manifest['bytes']) / 1e6:.0f} MB, total "
        f"{manifest['total_bytes'] / 1e9:.2f} GB (uncompressed complex64 would be "
        f"{manifest['complex64_bytes'] / 1e9:.1f} GB: "
        f"{manifest['total_bytes'] / manifest['complex64_bytes']:.3f}x, "
        f"{manifest['total_bytes'] / (manifest['complex64_bytes'] / 8):.2f} bytes per value). "
        f"Generated in {manifest['generate_s']:.0f} s with {manifest['jobs']} processes.",
        "",
        "## Calibration (`autocal calibrate`, each run in a fresh process, Tsky computed "
        f"once per run and cached; fit model: {_model_text(report.get('fit_model'))})",
        "",
        "| run | files | integrations (LST h) | values | disk GB | wall s | Tsky s | fit s | "
        "passes | peak RSS GB: all (scan+Tsky / fit+products) | workers' peak GB | "
        "HDF5 read / disk | SHA-256 read / disk | disk reads / disk | largest array MB | "
        "Mvalues/s | disk MB/s | complex64 MB/s |",
        "|" + "---|" * 18,
    ]
    for r in report["rows"]:
        lines.append(
            f"| {r['run']} | {r['files']} | {r['integrations']} ({r['hours_lst']}) | "
            f"{r['samples'] / 1e9:.2f} G | {r['disk_gb']} | {r['wall_s']} | {r['tsky_s']} | "
            f"{r['fit_s']} | {r['passes']} | {r['peak_rss_gb']} "
            f"({r['peak_rss_before_fit_gb']} / {r['peak_rss_fit_gb']}) | "
            f"{r['worker_peak_rss_gb'] or '-'} | {r['hdf5_read_over_disk']} | "
            f"{r['checksum_read_over_disk']} | {r['process_disk_reads_over_disk']} | "
            f"{r['largest_array_mb']} | {r['msamples_per_s_fit']} | {r['disk_mb_per_s_fit']} | "
            f"{r['c8_mb_per_s_fit']} |"
        )
    startup = next((r["dask_startup_s"] for r in report["rows"] if r["dask_startup_s"]), None)
    lines += [
        "",
        "Columns: *values* = antennas x pols x integrations x channels per pass; *fit s* = "
        "the streamed pass over the files"
        + (
            f" (the Dask cluster is started before the scan: {startup} s, in wall s)"
            if startup
            else ""
        )
        + "; throughputs are per fit second; *peak RSS* = the high-water mark (VmHWM) of "
        "the calibrating process, overall and split into scan + Tsky and the streamed "
        "fit + products (for Dask: the client; the workers' own peaks are the next "
        "column); *HDF5 read / disk* = bytes the HDF5 library read through the reader's "
        "counting file object over the files' size (1.0 = read once); *SHA-256 read / "
        "disk* = the sequential provenance checksum read just before each file's data "
        "(served again from the page cache); *disk reads / disk* = /proc/self/io "
        "read_bytes of the process after evicting the files from the page cache "
        "(physical reads; the Dask workers read in their own processes).",
        "",
    ]
    if not report.get("complete"):
        lines += ["**Partial report: the benchmark has not finished (yet).**", ""]
    cmp_ = report.get("dask_vs_serial")
    if cmp_ is not None:
        lines += [
            f"Dask ({report['dask_night']} night, LocalCluster of {report['dask_workers']} "
            "worker processes, 1 thread each) vs the serial run of the same files: "
            f"{'bit-identical' if cmp_['identical'] else 'NOT bit-identical'} "
            f"(max relative difference {cmp_['max_rel_diff']:.3g}).",
            "",
        ]
    truth = report.get("truth")
    if truth is not None:
        lines += [
            "Full-night solution vs the simulated truth: median |G/G_true - 1| = "
            f"{truth['median_abs_G_rel_err']:.2e}, median |Trxr - Trxr_true| = "
            f"{truth['median_abs_Trxr_err_K']:.3f} K, rms pull of G = "
            f"{truth['rms_G_pull']:.2f}, {truth['flagged_channels']} channels flagged.",
            "",
        ]
    prof = report.get("profile")
    if prof is not None:
        lines += [
            "## Where the time goes (pyinstrument, one file, in the benchmark process)",
            "",
            f"{prof['file']}: {prof['values'] / 1e6:.0f} M values in {prof['blocks']} "
            f"blocks, {prof['seconds']} s ({prof['values'] / prof['seconds'] / 1e6:.1f} M "
            "values/s) with every stage in one thread (profiled); as the pipeline runs it, "
            "HDF5 reads and decoding in background threads, pipelined: "
            f"{prof.get('pipelined_seconds', '-')} s:",
            "",
            "| part | s | share |",
            "|---|---|---|",
            *[
                f"| {k} | {v} | {100 * v / prof['seconds']:.0f} % |"
                for k, v in prof["parts_s"].items()
            ],
            "",
        ]
    lines += [
        "## Pointing the calibration at a Dask cluster",
        "",
        "```bash",
        "# on the scheduler node",
        "dask scheduler --port 8786",
        "# on each worker node (autocal installed, the data at the same paths); without",
        "# the nanny's MALLOC_TRIM_THRESHOLD_ (every large array faulted in afresh, 1.3-1.7x",
        "# slower): either no nanny, or a Dask config that unsets it",
        "dask worker tcp://SCHEDULER:8786 --nthreads 1 --no-nanny",
        "mkdir -p ~/.config/dask && printf 'distributed:\\n  nanny:\\n    pre-spawn-environ:\\n"
        "      MALLOC_TRIM_THRESHOLD_: null\\n' > ~/.config/dask/autocal.yaml",
        "dask worker tcp://SCHEDULER:8786 --nthreads 1 --nworkers 2",
        "# then",
        "autocal calibrate /data/2458098/zen.*.uvh5 --dask tcp://SCHEDULER:8786 --out cal",
        "autocal calibrate /data/2458098/zen.*.uvh5 --dask local --dask-workers 2 --out cal",
        "```",
        "",
        "From Python (e.g. the service worker with `AUTOCAL_DASK_SCHEDULER`): "
        "`run_calibration(config, out, progress=..., should_stop=..., "
        "dask_scheduler=settings.dask_scheduler or None)`. Each file is one task "
        "(`autocal.pipeline.partials.compute_partial`: the file read block by block); at most two "
        "files per worker are in flight and the partial sums come back and are added in "
        "file order, so the result is the same as the in-process run, bit for bit. An "
        "unreachable scheduler fails after 10 s with a message, a scheduler without "
        "workers after 30 s.",
        "",
    ]
    return "\n".join(lines)


def run_all(args: argparse.Namespace, night: Night) -> None:
    """Generate if needed, measure the runs, compare, profile; save after every step."""
    t0 = time.perf_counter()
    fit_model = {"model": args.model, "order": args.order if args.model == "legendre" else 0}
    # runs and results of another fit model go beside the default's, not over them
    suffix = "" if args.model == "constant" else f"-legendre{args.order}"
    folder = args.data
    generated = not (folder / "night.json").exists() or args.regenerate
    report: dict = {
        "command": " ".join(["python", "benchmarks/night.py", *sys.argv[1:]]),
        "machine": machine(),
        "night": asdict(night),
        "channel_width_khz": night.channel_width / 1e3,
        "integration_time_s": night.integration_time,
        "hours_lst": night.ntimes * night.cadence_sidereal_s / 3600,
        "dnu_dt": night.channel_width * night.integration_time,
        "dask_night": args.dask_night,
        "dask_workers": args.dask_workers,
        "fit_model": fit_model,
        "rows": [],
        "runs": {},
        "complete": False,
    }
    results = args.results or (RESULTS if night.is_full else folder / "results")
    results.mkdir(parents=True, exist_ok=True)
    stem = "night" if suffix == "" else f"night{suffix}"

    def save() -> None:
        report["total_s"] = time.perf_counter() - t0
        (results / f"{stem}.json").write_text(json.dumps(report, indent=2, default=str))
        (results / f"{stem}.md").write_text(markdown(report))

    manifest = load_or_generate(night, folder, args.jobs, args.regenerate)
    report["storage"] = manifest
    report["generated"] = generated
    files = manifest["files"]
    n = len(files)
    parts = {"quarter": max(1, n // 4), "half": max(1, n // 2), "full": n}
    wanted = args.runs.split(",")
    runs = report["runs"]
    for label in ("quarter", "half", "full"):
        if label in wanted:
            runs[label] = measure(label + suffix, files[: parts[label]], folder, None, 0, fit_model)
            report["rows"].append(_row(label, parts[label], runs[label], manifest, night))
            save()
    dask_label = args.dask_night
    if "dask" in wanted:
        runs["dask"] = measure(
            f"dask-{dask_label}{suffix}",
            files[: parts[dask_label]],
            folder,
            "local",
            args.dask_workers,
            fit_model,
        )
        report["rows"].append(
            _row(
                f"dask {dask_label} ({args.dask_workers} workers)",
                parts[dask_label],
                runs["dask"],
                manifest,
                night,
            )
        )
        serial = folder / "runs" / (dask_label + suffix) / "solution.h5"
        if serial.exists():
            report["dask_vs_serial"] = compare_solutions(
                serial, Path(runs["dask"]["out"]) / "solution.h5"
            )
        save()
    if "full" in runs:
        report["truth"] = truth_check(Path(runs["full"]["out"]) / "solution.h5", folder)
    if "profile" in wanted:
        print("profiling one file ...", flush=True)
        report["profile"] = profile_file(files[n // 2])
    report["complete"] = True
    save()
    print(markdown(report))
    print(f"wrote {results / (stem + '.json')} and {results / (stem + '.md')}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", nargs="?", default="run", choices=["run", "generate"])
    parser.add_argument("--ants", type=int, default=350, help="antennas (350)")
    parser.add_argument("--nfreq", type=int, default=1536, help="channels (1536)")
    parser.add_argument("--ntimes", type=int, default=8640, help="integrations (8640)")
    parser.add_argument("--per-file", type=int, default=192, help="integrations per file (192)")
    parser.add_argument("--dtype", default="c8", choices=["c8", "c16", "int32"])
    parser.add_argument(
        "--compression", default="gzip", choices=["lzf", "gzip"], help="(gzip, level 1)"
    )
    parser.add_argument(
        "--data", type=Path, help="night folder (default /tmp/autocal-night[-AxFxT])"
    )
    parser.add_argument("--results", type=Path, help="where night.json/md go")
    parser.add_argument("--jobs", type=int, default=2, help="generation processes (2)")
    parser.add_argument("--regenerate", action="store_true", help="rewrite the night")
    parser.add_argument("--dask-workers", type=int, default=2)
    parser.add_argument(
        "--model",
        default="constant",
        choices=["constant", "legendre"],
        help="fit model (constant, the pipeline's default); other models write "
        "night-legendre<order>.json/md and runs/<run>-legendre<order>",
    )
    parser.add_argument("--order", type=int, default=2, help="Legendre order (2)")
    parser.add_argument(
        "--runs",
        default="quarter,half,full,dask,profile",
        help="comma-separated steps to run (default quarter,half,full,dask,profile)",
    )
    parser.add_argument(
        "--dask-night",
        default="full",
        choices=["quarter", "half", "full"],
        help="which night the Dask run calibrates (full)",
    )
    if len(sys.argv) > 2 and sys.argv[1] == "_calibrate":
        calibrate_child(json.loads(sys.argv[2]))
        return
    args = parser.parse_args()
    night = Night(
        ants=args.ants,
        nfreq=args.nfreq,
        ntimes=args.ntimes,
        per_file=args.per_file,
        dtype=args.dtype,
        compression=args.compression,
    )
    if args.data is None:
        args.data = (
            DEFAULT_DATA
            if night.is_full
            else Path(f"{DEFAULT_DATA}-{night.ants}x{night.nfreq}x{night.ntimes}")
        )
    if night.ants > 350:
        parser.error("HERA has 350 antennas")
    if args.command == "generate":
        manifest = load_or_generate(night, args.data, args.jobs, args.regenerate)
        print(json.dumps({k: v for k, v in manifest.items() if k != "files"}, indent=2))
        return
    run_all(args, night)


if __name__ == "__main__":
    main()
