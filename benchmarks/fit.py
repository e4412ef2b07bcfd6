"""Benchmark: normal-equation accumulation vs numpy's own streaming reductions, side by side.

One chunk as the pipeline sees it per HERA file (default 350 antennas x 2 pols x 96
integrations x 1536 channels, float64 data as :class:`autocal.core.observation.Observation`
holds it, boolean flags, ``dnu dt N``) is reduced, in the same process and interleaved
round-robin over the repeats, by

- ``data.sum()`` (numpy's flat pairwise sum, single-threaded) and
  ``np.add.reduce(data, axis=2)`` (the same time-axis reduction shape as the fit);
- :func:`autocal.fit.sums.accumulate` for the constant and Legendre order-1/2 models with
  radiometer weights (``dnu dt N`` as the pipeline passes it for uniform ``nsamples``: one
  ``(Ntime, Nfreq)`` array, which the kernel reads as one ``(Nfreq,)`` row since the
  integration time is uniform too; and ``radiometer-nsamples``: a full per-sample array, as
  for LST-binned data) and identity weights, with 1 thread and with all threads, per engine,
  adding into one running set of sums (``into=``, as the pipeline's blocks do); and with
  fresh output arrays (1 thread, the first block of every file);
- the previous design-matrix implementation on a few antennas (the "before" rate);
- a floor (:func:`floor_kernel`): a compiled loop computing only the data moments, the
  per-sample work left even if every weight moment were shared between antennas;

and :func:`autocal.fit.solve.solve_sums` is timed separately. Rates are samples (data elements)
per second from the best-of-N wall time; the ratios to the plain sum and to the time-axis
reduction are the targets (>= 0.5). Usage (one command; writes JSON and markdown)::

    python benchmarks/fit.py [--nant 350] [--ntime 96] [--nfreq 1536] [--repeats 7]
                             [--threads 1 2] [--engines numba numpy] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

# '1 thread' means one core: keep BLAS (the numpy engine's matrix products) single-threaded
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

import autocal  # noqa: E402
from autocal.fit.model import FitModel, check_tsky, design, weights_for  # noqa: E402
from autocal.fit.solve import solve_sums  # noqa: E402
from autocal.fit.sums import NormalSums, accumulate  # noqa: E402

MODELS = (("constant", 0), ("legendre", 1), ("legendre", 2))
WEIGHTS = ("radiometer", "radiometer-nsamples", "identity")


# inputs -----------------------------------------------------------------------------------


def make_chunk(nant: int, npol: int, ntime: int, nfreq: int, seed: int = 0) -> dict[str, Any]:
    """A realistic chunk: G (Tsky + Trxr) with radiometer noise, ~2 % flags, RFI channels."""
    rng = np.random.default_rng(seed)
    freqs = np.linspace(100e6, 200e6, nfreq)
    lsts = 3.0 + np.arange(ntime) * 10.7 / 3600.0  # HERA 10.7 s integrations
    shape_t = 1.0 + 0.3 * np.sin(2 * np.pi * (lsts - 3.0) / 24.0)
    tsky = 300.0 * (freqs / 150e6)[None, None, :] ** -2.5 * shape_t[None, :, None]
    tsky = np.ascontiguousarray(np.broadcast_to(tsky, (npol, ntime, nfreq)))
    gain = rng.uniform(0.5, 2.0, (nant, npol, 1, nfreq))
    trxr = rng.uniform(80.0, 200.0, (nant, npol, 1, nfreq))
    channel_width = np.full(nfreq, freqs[1] - freqs[0])
    integration_time = np.full(ntime, 10.7)
    bt = channel_width[None, None, None, :] * integration_time[None, None, :, None]
    data = np.empty((nant, npol, ntime, nfreq))
    for a in range(nant):  # antenna by antenna to bound temporaries
        clean = gain[a] * (tsky + trxr[a])
        data[a] = clean * (1.0 + rng.standard_normal(clean.shape) / np.sqrt(bt[0]))
    flags = rng.random(data.shape) < 0.02
    flags[..., rng.choice(nfreq, nfreq // 20, replace=False)] = True  # RFI channels
    nsamples = np.ones(data.shape)
    bandwidth_time = bt * nsamples  # what Observation.bandwidth_time() returns
    return {
        "data": data,
        "flags": flags,
        "bandwidth_time": bandwidth_time,
        "tsky": tsky,
        "lsts": lsts,
    }


def reference_accumulate(
    model: FitModel,
    data: np.ndarray,
    tsky: np.ndarray,
    lsts: np.ndarray,
    *,
    flags: np.ndarray,
    weights: str,
    bandwidth_time: np.ndarray | None,
) -> NormalSums:
    """The previous implementation (full design matrix, batched tiny matmuls), for 'before'."""
    nant, npol, ntime, nfreq = data.shape
    tsky = check_tsky(tsky, npol, ntime, nfreq)
    usable = np.isfinite(data) & ~flags
    w = weights_for(weights, data, usable, bandwidth_time)
    used = w > 0
    y = np.where(used, data, 0.0)
    a = design(model, tsky, lsts)
    m = model.nparam
    wt = np.swapaxes(w, 2, 3)
    wy = wt * np.swapaxes(y, 2, 3)
    aty = (wy[..., None, :] @ a)[..., 0, :]
    iu, ju = np.triu_indices(m)
    upper = (wt[..., None, :] @ (a[..., iu] * a[..., ju]))[..., 0, :]
    ata = np.empty((nant, npol, nfreq, m, m))
    ata[..., iu, ju] = upper
    ata[..., ju, iu] = upper
    yty = np.einsum("apft,apft->apf", wy, np.swapaxes(y, 2, 3))
    count = np.swapaxes(used, 2, 3).sum(axis=-1)
    return NormalSums(model, ata, aty, yty, count, ntime - count)


def weight_kwargs(weights: str, bt: np.ndarray) -> dict[str, Any]:
    """``accumulate`` keywords of a weight case (``bt``: the full per-sample dnu dt N)."""
    if weights == "identity":
        return {"weights": "identity", "bandwidth_time": None}
    if weights == "radiometer":  # uniform nsamples: what the pipeline passes
        return {"weights": "radiometer", "bandwidth_time": bt[0, 0]}
    return {"weights": "radiometer", "bandwidth_time": bt}


# the floor: data moments only ----------------------------------------------------------------


def floor_kernel(order: int, flagged: bool = False) -> Callable[..., None]:
    """Compile a loop doing only the per-sample work no moment-based fit can avoid.

    For every (antenna, pol, channel): ``sum_t y P_k`` and ``sum_t y T P_k`` (``k <= p``)
    and ``sum_t y^2``, the data moments, with unit weights and no flag or finiteness
    checks. The weight moments (``sum_t w T^e P_r``) are left out: with unit weights and
    flags shared by all antennas they could be computed once per polarisation, so this
    is what even that design would still do per sample. Same loop structure as the fit
    kernel (channels vectorised, 4 integrations per pass, 512-channel blocks; a trailing
    ``Ntime mod 4`` integrations are skipped, which only makes it faster). ``flagged``: also
    read the flags and zero flagged samples (one more byte per sample and a select).
    """
    import numba

    nb, tu, fb = order + 1, 4, 512
    names = ["yy"] + [f"q{e}_{k}" for e in range(2) for k in range(nb)]
    src = [
        "def kernel(data, flags, tsky, coef, a0, a1, out):",
        "    npol, ntime, nfreq = data.shape[1], data.shape[2], data.shape[3]",
        f"    acc = np.empty({len(names)} * {fb + 8})",
        "    for a in range(a0, a1):",
        "        for p in range(npol):",
        f"            for f0 in range(0, nfreq, {fb}):",
        f"                nf = min({fb}, nfreq - f0)",
        "                acc[:] = 0.0",
        f"                for t0 in range(0, ntime - {tu} + 1, {tu}):",
    ]
    ind = " " * 20
    for u in range(tu):
        src += [
            f"{ind}d{u} = data[a, p, t0 + {u}, f0:f0 + nf]",
            f"{ind}s{u} = tsky[p, t0 + {u}, f0:f0 + nf]",
            f"{ind}g{u} = flags[a, p, t0 + {u}, f0:f0 + nf]",
        ]
        src += [f"{ind}c{u}_{k} = coef[{k}, t0 + {u}]" for k in range(1, nb)]
    src.append(f"{ind}for j in range(nf):")
    ind = " " * 24
    src += [f"{ind}{n} = acc[{i * (fb + 8)} + j]" for i, n in enumerate(names)]
    for u in range(tu):
        src.append(f"{ind}y = d{u}[j] if g{u}[j] == 0 else 0.0" if flagged else f"{ind}y = d{u}[j]")
        src += [f"{ind}x = y * s{u}[j]", f"{ind}yy += y * y"]
        src += [f"{ind}q0_0 += y", f"{ind}q1_0 += x"]
        src += [f"{ind}q0_{k} += c{u}_{k} * y" for k in range(1, nb)]
        src += [f"{ind}q1_{k} += c{u}_{k} * x" for k in range(1, nb)]
    src += [f"{ind}acc[{i * (fb + 8)} + j] = {n}" for i, n in enumerate(names)]
    src += [
        f"                for i in range({len(names)}):",
        f"                    out[a, p, i, f0:f0 + nf] += acc[i * {fb + 8}:i * {fb + 8} + nf]",
    ]
    namespace: dict[str, Any] = {"np": np}
    exec("\n".join(src) + "\n", namespace)
    return numba.njit(nogil=True, fastmath={"contract"}, boundscheck=False, error_model="numpy")(
        namespace["kernel"]
    )


def floor_case(
    order: int,
    data: np.ndarray,
    tsky: np.ndarray,
    lsts: np.ndarray,
    threads: int,
    flags: np.ndarray | None = None,
) -> Callable[[], Any]:
    """Time-able call of :func:`floor_kernel` over antenna blocks, like ``accumulate``."""
    from concurrent.futures import ThreadPoolExecutor

    from autocal.fit.moments import offset_copy, time_functions
    from autocal.fit.sums import antenna_blocks

    kernel = floor_kernel(order, flagged=flags is not None)
    flag_bytes = (
        np.zeros((1, 1, 1, 1), np.uint8)
        if flags is None
        else np.ascontiguousarray(flags, dtype=bool).view(np.uint8)
    )
    coef, _ = time_functions(FitModel.for_lsts(lsts, "legendre", max(order, 1)), lsts)
    tsky = offset_copy(np.ascontiguousarray(tsky), data)
    nant = data.shape[0]
    out = np.zeros((nant, data.shape[1], 2 * order + 3, data.shape[3]))
    blocks = antenna_blocks(nant, nant if threads == 1 else -(-nant // (4 * threads)))

    def run() -> None:
        if threads == 1:
            kernel(data, flag_bytes, tsky, coef, 0, nant, out)
            return
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(lambda ab: kernel(data, flag_bytes, tsky, coef, *ab, out), blocks))

    return run


# timing -----------------------------------------------------------------------------------


def run_round_robin(
    cases: dict[str, Callable[[], Any]], repeats: int
) -> dict[str, dict[str, float]]:
    """Time every case ``repeats`` times, interleaved, so machine noise hits all alike."""
    walls: dict[str, list[float]] = {k: [] for k in cases}
    cpus: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            c0, t0 = time.process_time(), time.perf_counter()
            fn()
            walls[name].append(time.perf_counter() - t0)
            cpus[name].append(time.process_time() - c0)
    return {
        k: {
            "best_s": min(walls[k]),
            "median_s": statistics.median(walls[k]),
            "cpu_best_s": min(cpus[k]),
        }
        for k in cases
    }


def fma_peak() -> float:
    """Single-core multiply-add peak (FMA lanes per second) from a BLAS dgemm."""
    n = 1024
    a, b = np.random.default_rng(1).random((2, n, n))
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return n**3 / best


def ceilings(order: int, weights: str, sum_rate: float, fma_rate: float) -> dict[str, float]:
    """Upper bounds of the ratio to the plain sum from bytes and multiply-adds per sample.

    Memory: the sum reads 8 B per sample; accumulate reads data (8 B), flags (1 B) and, for
    per-sample radiometer weights, dnu dt N (8 B). Compute: 8p + 6 multiply-adds per sample
    (the 3 (2p + 1) weighted moments of Tsky^e P_r, 2 (p + 1) of the data, y^2) and 4
    multiplies.
    """
    nbytes = 8 + 1 + (8 if weights == "radiometer-nsamples" else 0)
    flops = 8 * order + 6 + 4
    return {"memory": 8.0 / nbytes, "compute": fma_rate / flops / sum_rate}


def machine_info() -> dict[str, Any]:
    """CPU model, cores, RAM, numpy/BLAS/numba versions, load average."""
    info: dict[str, Any] = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "autocal": autocal.__version__,
        "cpus": os.cpu_count(),
        "usable_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
    }
    try:
        text = Path("/proc/cpuinfo").read_text()
        info["cpu"] = next(
            line.split(":", 1)[1].strip() for line in text.splitlines() if "model name" in line
        )
        flags = next(line for line in text.splitlines() if line.startswith("flags"))
        info["simd"] = " ".join(f for f in ("avx2", "fma", "avx512f") if f" {f}" in flags)
    except (OSError, StopIteration):
        info["cpu"] = platform.processor() or platform.machine()
    try:
        kb = next(
            int(line.split()[1])
            for line in Path("/proc/meminfo").read_text().splitlines()
            if line.startswith("MemTotal")
        )
        info["ram_gb"] = round(kb / 2**20, 1)
    except (OSError, StopIteration):
        info["ram_gb"] = None
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        info["blas"] = f"{blas.get('name')} {blas.get('version')}"
    except Exception:  # informational only
        info["blas"] = "unknown"
    try:
        import numba

        info["numba"] = numba.__version__
    except ImportError:
        info["numba"] = None
    return info


# main -------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nant", type=int, default=350)
    parser.add_argument("--npol", type=int, default=2)
    parser.add_argument("--ntime", type=int, default=96)
    parser.add_argument("--nfreq", type=int, default=1536)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument(
        "--threads", type=int, nargs="+", default=sorted({1, len(os.sched_getaffinity(0))})
    )
    parser.add_argument("--engines", nargs="+", default=["numba", "numpy"])
    parser.add_argument("--before-antennas", type=int, default=16)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()

    info = machine_info()
    info["load_average_start"] = [round(x, 2) for x in os.getloadavg()]
    info["fma_peak_per_s"] = fma_peak()
    chunk = make_chunk(args.nant, args.npol, args.ntime, args.nfreq)
    data, flags, bt = chunk["data"], chunk["flags"], chunk["bandwidth_time"]
    tsky, lsts = chunk["tsky"], chunk["lsts"]
    nsamp = data.size
    print(
        f"chunk {data.shape} float64: data {data.nbytes / 2**20:.0f} MiB, "
        f"dnu dt N {bt.nbytes / 2**20:.0f} MiB, flags {flags.nbytes / 2**20:.0f} MiB",
        flush=True,
    )

    def acc_case(
        model: FitModel, weights: str, engine: str, threads: int, reuse: bool = True
    ) -> Callable[[], Any]:
        kw = weight_kwargs(weights, bt)
        running: list[NormalSums] = []

        def run() -> NormalSums:
            sums = accumulate(
                model,
                data,
                tsky,
                lsts,
                flags=flags,
                engine=engine,  # type: ignore[arg-type]
                threads=threads,
                into=running[0] if running else None,
                **kw,
            )
            if reuse and not running:
                running.append(sums)
            return sums

        return run

    cases: dict[str, Callable[[], Any]] = {
        "sum": lambda: data.sum(),
        "reduce_time": lambda: np.add.reduce(data, axis=2),
    }
    labels: dict[str, dict[str, Any]] = {}
    compile_s: dict[str, float] = {}
    for kind, order in MODELS:
        model = FitModel.for_lsts(lsts, kind, order)
        for weights in WEIGHTS:
            for engine in args.engines:
                variants = [(t, True) for t in (args.threads if engine == "numba" else [1])]
                if engine == "numba":
                    variants.append((1, False))
                for threads, reuse in variants:
                    key = f"{kind}{order}-{weights}-{engine}-{threads}t"
                    key += "" if reuse else "-fresh"
                    fn = acc_case(model, weights, engine, threads, reuse)
                    t0 = time.perf_counter()
                    fn()  # compile (numba) / warm up / allocate the reused output
                    compile_s[key] = time.perf_counter() - t0
                    cases[key] = fn
                    labels[key] = {
                        "model": "constant" if kind == "constant" else f"Legendre {order}",
                        "weights": weights,
                        "engine": engine,
                        "threads": threads,
                        "output": "reused" if reuse else "fresh",
                    }
    for order in (0, 2):
        for threads in args.threads:
            for with_flags in (False, True):
                fn = floor_case(order, data, tsky, lsts, threads, flags if with_flags else None)
                fn()  # compile
                cases[f"floor{order}-{threads}t" + ("-flags" if with_flags else "")] = fn
    print(f"timing {len(cases)} cases x {args.repeats} repeats, round robin", flush=True)
    timings = run_round_robin(cases, args.repeats)

    # correctness against the previous implementation, and its speed, on a few antennas
    nb = min(args.before_antennas, args.nant)
    before: dict[str, Any] = {}
    for kind, order in MODELS:
        model = FitModel.for_lsts(lsts, kind, order)
        for weights in WEIGHTS:
            kw = weight_kwargs(weights, bt[:nb])
            t0 = time.perf_counter()
            old = reference_accumulate(
                model,
                data[:nb],
                tsky,
                lsts,
                flags=flags[:nb],
                weights=kw["weights"],
                bandwidth_time=kw["bandwidth_time"],
            )
            t_old = time.perf_counter() - t0
            new = accumulate(model, data[:nb], tsky, lsts, flags=flags[:nb], **kw)
            scale = np.abs(old.ata).max(axis=(-2, -1), keepdims=True)
            rel = float(np.max(np.abs(new.ata - old.ata) / np.where(scale > 0, scale, 1.0)))
            key = f"{kind}{order}-{weights}"
            before[key] = {
                "rate": nb * data[0].size / t_old,
                "max_rel_diff_ata": rel,
                "counts_equal": bool(np.array_equal(new.count, old.count)),
            }

    # solve_sums separately
    solve: dict[str, float] = {}
    for kind, order in MODELS:
        model = FitModel.for_lsts(lsts, kind, order)
        sums = accumulate(model, data, tsky, lsts, flags=flags, bandwidth_time=bt)
        best = np.inf
        for _ in range(max(1, args.repeats // 2)):
            t0 = time.perf_counter()
            solve_sums(sums)
            best = min(best, time.perf_counter() - t0)
        solve[f"{kind}{order}"] = best
    info["load_average_end"] = [round(x, 2) for x in os.getloadavg()]

    t_sum, t_red = timings["sum"]["best_s"], timings["reduce_time"]["best_s"]
    rows = []
    for key, lab in labels.items():
        t = timings[key]
        kind_order = key.split("-")[0]
        rows.append(
            {
                **lab,
                "best_s": round(t["best_s"], 4),
                "median_s": round(t["median_s"], 4),
                "cpu_best_s": round(t["cpu_best_s"], 4),
                "rate_samples_per_s": nsamp / t["best_s"],
                "ratio_to_sum": t_sum / t["best_s"],
                "ratio_to_reduce_time": t_red / t["best_s"],
                "ratio_to_sum_median": timings["sum"]["median_s"] / t["median_s"],
                # per-core efficiency (CPU time; robust to a shared machine, 1 thread only)
                "ratio_to_sum_cpu": (
                    timings["sum"]["cpu_best_s"] / t["cpu_best_s"] if lab["threads"] == 1 else None
                ),
                "first_call_s": round(compile_s[key], 3),
                "before_rate_samples_per_s": before[f"{kind_order}-{lab['weights']}"]["rate"],
                "ceiling_ratio_to_sum": ceilings(
                    int(kind_order[-1]), lab["weights"], nsamp / t_sum, info["fma_peak_per_s"]
                ),
            }
        )
    result = {
        "machine": info,
        "shape": list(data.shape),
        "samples": nsamp,
        "repeats": args.repeats,
        "baselines": {
            "sum": {**timings["sum"], "rate_samples_per_s": nsamp / t_sum},
            "reduce_time": {**timings["reduce_time"], "rate_samples_per_s": nsamp / t_red},
        },
        "accumulate": rows,
        "before": {"antennas": nb, **before},
        "solve_sums_s": solve,
        "floor": {
            key: {
                "order": int(key[5]),
                "threads": int(key.split("-")[1][:-1]),
                "flags": key.endswith("-flags"),
                "best_s": round(t["best_s"], 4),
                "ratio_to_sum": t_sum / t["best_s"],
                "ratio_to_reduce_time": t_red / t["best_s"],
            }
            for key, t in timings.items()
            if key.startswith("floor")
        },
    }
    md = render_markdown(result)
    print(md)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fit.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "fit.md").write_text(md)


def render_markdown(r: dict[str, Any]) -> str:
    """The result as a markdown report."""
    m = r["machine"]
    gs = 1e9
    base = r["baselines"]
    rows = r["accumulate"]
    lines = [
        "# Fit accumulation vs numpy streaming reductions",
        "",
        f"Machine: {m.get('cpu')} ({m.get('simd')}), {m.get('usable_cpus')} usable cores, "
        f"{m.get('ram_gb')} GB RAM; python {m['python']}, numpy {m['numpy']} "
        f"(BLAS {m['blas']}), numba {m['numba']}, autocal {m['autocal']}. Load average "
        f"{m['load_average_start']} at the start, {m['load_average_end']} at the end; on a "
        "shared machine compare the ratios (measured side by side, interleaved) rather than "
        "the absolute rates.",
        "",
        f"Chunk {tuple(r['shape'])} (antennas, pols, integrations, channels), float64 data "
        f"(what `Observation` holds), bool flags, `dnu dt N` as one (Ntime, Nfreq) array "
        "('radiometer', uniform nsamples, what the pipeline passes for raw files; uniform in "
        "time, so the kernel reads it as one (Nfreq,) row) or per "
        "sample ('radiometer-nsamples') = "
        f"{r['samples'] / 1e6:.1f} M samples; best of {r['repeats']} wall times. The "
        "chunk's sums are added into one running set of sums (`into=`), as the pipeline "
        "does for the blocks of a file ('fresh' = new arrays on every call, the first "
        "block of a file).",
        "",
        "| baseline (numpy, 1 thread) | best [s] | median [s] | rate [G samples/s] | [GB/s] |",
        "|---|---|---|---|---|",
    ]
    for name, label in (
        ("sum", "`data.sum()` (flat pairwise sum)"),
        ("reduce_time", "`np.add.reduce(data, axis=2)` (over time, as the fit)"),
    ):
        b = base[name]
        rate = b["rate_samples_per_s"]
        lines.append(
            f"| {label} | {b['best_s']:.4f} | {b['median_s']:.4f} | {rate / gs:.3f} | "
            f"{rate * 8 / gs:.1f} |"
        )
    # headline: best numba rate per model and weights, 1 thread and all threads
    lines += [
        "",
        "Headline (numba engine; target: ratio to the plain sum >= 0.5):",
        "",
        "| model | weights | 1 thread: ratio to sum (wall / CPU) | ratio to reduce-over-time | "
        "N threads: ratio to sum | ratio to reduce-over-time | speed-up vs before (1 thread) | "
        "1 thread, fresh output: ratio to sum | "
        "1-core ceiling of the ratio to sum (memory / compute) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for model in dict.fromkeys(row["model"] for row in rows):
        for weights in dict.fromkeys(row["weights"] for row in rows):
            sel = [
                x
                for x in rows
                if x["model"] == model and x["weights"] == weights and x["engine"] == "numba"
            ]
            fresh = [x for x in sel if x["output"] == "fresh"]
            sel = [x for x in sel if x["output"] == "reused"]
            one = [x for x in sel if x["threads"] == 1]
            many = [x for x in sel if x["threads"] > 1]
            if not one:
                continue
            o = one[0]
            cells = [
                f"{o['ratio_to_sum']:.2f} / {o['ratio_to_sum_cpu']:.2f}",
                f"{o['ratio_to_reduce_time']:.2f}",
            ]
            if many:
                t = max(many, key=lambda x: x["threads"])
                cells += [
                    f"{t['ratio_to_sum']:.2f} ({t['threads']} threads)",
                    f"{t['ratio_to_reduce_time']:.2f}",
                ]
            else:
                cells += ["-", "-"]
            cells.append(f"{o['rate_samples_per_s'] / o['before_rate_samples_per_s']:.0f}x")
            cells.append(f"{fresh[0]['ratio_to_sum']:.2f}" if fresh else "-")
            ceil = o["ceiling_ratio_to_sum"]
            cells.append(f"{ceil['memory']:.2f} / {ceil['compute']:.2f}")
            lines.append(f"| {model} | {weights} | " + " | ".join(cells) + " |")
    floor = r.get("floor", {})
    if floor:
        lines += [
            "",
            "Floor: the data moments alone (`floor_kernel`: sum_t y P_k, sum_t y T P_k, "
            "sum_t y^2 per channel, unit weights, no finiteness checks; what a fit would "
            "still do per sample if every weight moment were shared between antennas; "
            "'flags applied': flagged samples zeroed, as any fit must):",
            "",
            "| model | flags applied | threads | best [s] | ratio to sum | "
            "ratio to reduce-over-time |",
            "|---|---|---|---|---|---|",
        ]
        for v in floor.values():
            model = "constant" if v["order"] == 0 else f"Legendre {v['order']}"
            lines.append(
                f"| {model} | {'yes' if v.get('flags') else 'no'} | {v['threads']} | "
                f"{v['best_s']:.4f} | {v['ratio_to_sum']:.2f} | "
                f"{v['ratio_to_reduce_time']:.2f} |"
            )
    lines += [
        "",
        "All cases:",
        "",
        "| model | weights | engine | threads | output | best [s] | median [s] | "
        "rate [G samples/s] | ratio to sum | ratio to sum, CPU time | "
        "ratio to reduce-over-time | before [G samples/s] | first call [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        cpu = row["ratio_to_sum_cpu"]
        lines.append(
            f"| {row['model']} | {row['weights']} | {row['engine']} | {row['threads']} | "
            f"{row['output']} | {row['best_s']:.4f} | {row['median_s']:.4f} | "
            f"{row['rate_samples_per_s'] / gs:.3f} | {row['ratio_to_sum']:.2f} | "
            f"{'-' if cpu is None else f'{cpu:.2f}'} | {row['ratio_to_reduce_time']:.2f} | "
            f"{row['before_rate_samples_per_s'] / gs:.4f} | {row['first_call_s']:.2f} |"
        )
    before = r["before"]
    diffs = {k: v for k, v in before.items() if isinstance(v, dict)}
    lines += [
        "",
        "'ratio to sum, CPU time' = CPU time of `data.sum()` / CPU time of the case (1 thread "
        "only; less sensitive to other processes). 'first call' = first call in the process "
        "(numba: kernel compilation, or loading it from the on-disk cache).",
        "",
        "Ceilings (one core): memory = 8 B per sample for the sum / bytes read per sample by "
        "accumulate (data 8 + flags 1 + dnu dt N 8 for per-sample radiometer weights); "
        "compute = "
        f"single-core multiply-add peak ({m['fma_peak_per_s'] / gs:.1f} G/s, 1024^3 dgemm) "
        "/ (8p + 10) multiply-adds per sample (3 (2p + 1) weighted moments of Tsky^e P_r, "
        "2 (p + 1) of the data, y^2, 4 feature products) / the sum's rate. The plain sum does "
        "one add per sample.",
        "",
        f"'before' = the previous design-matrix implementation, timed on {before['antennas']} "
        "antennas (its rate per sample does not depend on the antenna count). Agreement with "
        "it there: max |diff| / max |ata| per channel = "
        + ", ".join(f"{k} {v['max_rel_diff_ata']:.1e}" for k, v in diffs.items())
        + "; counts equal: "
        + str(all(v["counts_equal"] for v in diffs.values()))
        + ".",
        "",
        "`solve_sums` (all channels of the chunk, radiometer sums), best wall time: "
        + ", ".join(f"{k} {v:.3f} s" for k, v in r["solve_sums_s"].items())
        + ".",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
