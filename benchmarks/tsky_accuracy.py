"""Tsky accuracy (issue 25, item 4): the engine against an independent, converged reference.

The reference is :func:`autocal.tsky.quadrature.tsky_quadrature`: direct quadrature on a
grid fixed to the ground (Gauss-Legendre in zenith angle with panels split at the edges of
the soft horizon, uniform azimuths ~``step`` apart), the beam evaluated exactly at every
node and the sky model's native Galactic maps interpolated at every node and LST. It
shares nothing with the engine's HEALPix grid. One command:

1. computes the reference at ``--steps`` (e.g. 0.2 and 0.1 degrees) on ``--nlst`` LSTs and
   at ``--conv-step`` (0.05 degrees) on ``--conv-lsts`` of them, and reports how far each
   coarser reference is from the finest (the reference's own error);
2. measures the engine (:func:`autocal.tsky.ringfft.tsky_fft`) at each ``--nsides``
   against the finest reference on all LSTs, for the sky given to it three ways: sampled
   at the pixel centres (``SkyModel.components``, what ``compute_tsky`` used before),
   averaged over each pixel (box window), and band-limited to ``lmax = 2 nside``
   (:mod:`autocal.tsky.bandlimit`, what ``compute_tsky`` uses now);
3. times, side by side, the sky preparation (point-sampled vs band-limited) and the
   engine at the production size (``--speed-nfreq`` channels, nside 64, HERA beam):
   the band limit changes only the one-off sky preparation, not the engine.

Reference tables are cached (``--cache-dir``, default a folder under the system temp
directory, never the repository), keyed by beam, step, channels, LSTs and the autocal
source of the quadrature module.

Usage::

    python benchmarks/tsky_accuracy.py           # ~10 min on 2 cores (cold cache)
    python benchmarks/tsky_accuracy.py --quick   # 8 LSTs, no 0.05-degree check

Writes ``benchmarks/results/tsky_accuracy.json`` and ``.md`` (``tsky_accuracy_quick.*``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import healpy as hp
import numpy as np

import autocal.tsky.quadrature as quadrature
from autocal.core.sites import HERA
from autocal.sky.beam_names import get_beam
from autocal.sky.models import SkyComponents, get_sky
from autocal.tsky.bandlimit import band_limited_components, fine_nside
from autocal.tsky.ringfft import tsky_fft

RESULTS = Path(__file__).resolve().parent / "results"
TARGET_MAX_K = 0.05


def reference(
    beam_name: str, freqs: np.ndarray, lsts: np.ndarray, step: float, cache: Path
) -> tuple[np.ndarray, float]:
    """Return the quadrature reference ``(Nlst, Nfreq)`` and its compute time (cached)."""
    source = Path(quadrature.__file__).read_bytes()
    key = hashlib.sha256(
        b"|".join([beam_name.encode(), str(step).encode(), freqs.tobytes(), lsts.tobytes(), source])
    ).hexdigest()[:16]
    path = cache / f"ref-{beam_name}-{step}-{key}.npz"
    if path.exists():
        with np.load(path) as f:
            return f["tsky"], float(f["seconds"])
    t0 = time.perf_counter()
    table = quadrature.tsky_quadrature(
        get_sky("gsm2008"), get_beam(beam_name), HERA, freqs, lsts, step_deg=step, progress=False
    ).tsky
    seconds = time.perf_counter() - t0
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, tsky=table, seconds=seconds)
    return table, seconds


def sky_variants(freqs: np.ndarray, nside: int) -> dict[str, SkyComponents]:
    """The sky at ``nside``: sampled at pixel centres, box-averaged, band-limited."""
    sky = get_sky("gsm2008")
    fine = sky.components(freqs, nside=fine_nside(nside))
    box = np.array([hp.ud_grade(m, nside) for m in fine.maps])
    return {
        "point (pixel centres, old)": sky.components(freqs, nside=nside),
        "box (pixel average)": replace(fine, maps=box, nside=nside),
        "band-limited lmax 2 nside (new)": band_limited_components(sky, freqs, nside),
    }


def stats(diff: np.ndarray, freqs: np.ndarray) -> dict[str, Any]:
    """Max, rms and per-channel max of ``|diff|`` (kelvin)."""
    return {
        "max_K": round(float(np.abs(diff).max()), 4),
        "rms_K": round(float(np.sqrt(np.mean(diff**2))), 4),
        "max_per_channel_K": {
            f"{f / 1e6:g} MHz": round(float(v), 4)
            for f, v in zip(freqs, np.abs(diff).max(0), strict=True)
        },
    }


def accuracy(args: argparse.Namespace, freqs: np.ndarray, lsts: np.ndarray) -> dict[str, Any]:
    """Convergence of the reference and the engine's error, per beam."""
    out: dict[str, Any] = {}
    conv_rows = np.unique(np.linspace(0, lsts.size, args.conv_lsts, endpoint=False).astype(int))
    for beam_name in args.beams:
        refs = {s: reference(beam_name, freqs, lsts, s, args.cache_dir) for s in args.steps}
        finest = min(args.steps)
        ref = refs[finest][0]
        conv = {
            f"{s} deg vs {finest} deg": stats(refs[s][0] - ref, freqs)
            for s in args.steps
            if s != finest
        }
        if args.conv_step:
            fine_ref, _ = reference(
                beam_name, freqs, lsts[conv_rows], args.conv_step, args.cache_dir
            )
            for s in args.steps:
                conv[f"{s} deg vs {args.conv_step} deg ({conv_rows.size} LSTs)"] = stats(
                    refs[s][0][conv_rows] - fine_ref, freqs
                )
        beam = get_beam(beam_name)
        engine = {}
        for nside in args.nsides:
            for label, comps in sky_variants(freqs, nside).items():
                table = tsky_fft(comps, beam, HERA, lsts, progress=False).tsky
                engine[f"nside {nside}, sky {label}"] = stats(table - ref, freqs)
                print(beam_name, nside, label, engine[f"nside {nside}, sky {label}"]["max_K"])
        out[beam_name] = {
            "reference_seconds": {str(s): round(refs[s][1], 1) for s in args.steps},
            "reference_convergence": conv,
            "engine_vs_reference": engine,
        }
    return out


def speed(nfreq: int, nside: int, repeat: int) -> dict[str, Any]:
    """Sky preparation (old vs new) and the engine, HERA beam, ``nfreq`` channels, 8640 LSTs."""
    beam = get_beam("hera")
    lo, hi = beam.freq_range
    freqs = np.linspace(max(lo, 100e6), min(hi, 200e6), nfreq)
    lsts = np.arange(8640) * (24.0 / 8640)
    sky = get_sky("gsm2008")
    tsky_fft(sky.components(freqs[:4], nside=nside), beam, HERA, lsts[:2], progress=False)  # warm
    prep: dict[str, list[float]] = {"point (old)": [], "band-limited (new)": []}
    engine: dict[str, list[float]] = {"point (old)": [], "band-limited (new)": []}
    for i in range(repeat):
        epoch = 2451545.0 + i  # a fresh epoch each round: no memoised sky
        for label in prep:
            t0 = time.perf_counter()
            if label.startswith("point"):
                comps = sky.components(freqs, nside=nside, epoch=epoch)
            else:
                comps = band_limited_components(sky, freqs, nside, epoch=epoch)
            prep[label].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            tsky_fft(comps, beam, HERA, lsts, progress=False)
            engine[label].append(time.perf_counter() - t0)
    return {
        "nfreq": nfreq,
        "nside": nside,
        "nlst": lsts.size,
        "sky_prep_best_s": {k: round(min(v), 2) for k, v in prep.items()},
        "engine_best_s": {k: round(min(v), 2) for k, v in engine.items()},
        "engine_median_s": {k: round(float(np.median(v)), 2) for k, v in engine.items()},
    }


def render(res: dict[str, Any]) -> str:
    """Markdown report."""
    cfg, lines = res["config"], []
    lines.append(f"# Tsky accuracy: engine vs independent quadrature (`{cfg['command']}`)\n")
    lines.append(
        f"GSM2008, HERA site, J2000, {cfg['nlst']} LSTs over 24 h, channels "
        f"{', '.join(f'{f:g}' for f in cfg['freqs_MHz'])} MHz, soft horizon 2 deg, Tgnd 300 K. "
        f"Machine: {res['machine']['cpu']}, load {res['machine']['load']}.\n"
    )
    for beam, r in res["accuracy"].items():
        lines.append(f"## {beam} beam\n")
        lines.append("Reference convergence (max / rms |difference|, K):\n")
        lines.append("| references | max | rms |\n|---|---|---|")
        for k, v in r["reference_convergence"].items():
            lines.append(f"| {k} | {v['max_K']} | {v['rms_K']} |")
        lines.append("\nEngine vs the finest reference on every LST (K):\n")
        lines.append("| engine | max | rms | max per channel |\n|---|---|---|---|")
        for k, v in r["engine_vs_reference"].items():
            per = ", ".join(f"{c}: {x}" for c, x in v["max_per_channel_K"].items())
            lines.append(f"| {k} | {v['max_K']} | {v['rms_K']} | {per} |")
        lines.append("")
    sp = res.get("speed")
    if sp:
        lines.append(
            f"## Cost at nside {sp['nside']}, {sp['nfreq']} channels x {sp['nlst']} LSTs "
            "(HERA beam, best of the repeats, side by side)\n"
        )
        lines.append("| sky | sky preparation (s) | engine (s) |\n|---|---|---|")
        for k in sp["sky_prep_best_s"]:
            lines.append(f"| {k} | {sp['sky_prep_best_s'][k]} | {sp['engine_best_s'][k]} |")
        lines.append("")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Run the benchmark and write the report."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--nlst", type=int, default=None, help="LSTs over 24 h (default 24)")
    parser.add_argument("--freqs-mhz", default="100,150,200")
    parser.add_argument("--beams", default="dipole,hera")
    parser.add_argument("--steps", default="0.2,0.1", help="reference steps, degrees")
    parser.add_argument("--conv-step", type=float, default=None, help="default 0.05 (0: skip)")
    parser.add_argument("--conv-lsts", type=int, default=4)
    parser.add_argument("--nsides", default="64,128")
    parser.add_argument("--speed-nfreq", type=int, default=1024, help="0 skips the timing")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument(
        "--cache-dir", type=Path, default=Path(tempfile.gettempdir()) / "autocal-tsky-reference"
    )
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    args.beams = args.beams.split(",")
    args.steps = [float(s) for s in args.steps.split(",")]
    args.nsides = [int(s) for s in args.nsides.split(",")]
    if args.conv_step is None:
        args.conv_step = 0.0 if args.quick else 0.05
    nlst = args.nlst or (8 if args.quick else 24)
    freqs = np.array([float(f) * 1e6 for f in args.freqs_mhz.split(",")])
    lsts = np.arange(nlst) * (24.0 / nlst)
    command = "python benchmarks/tsky_accuracy.py" + (" --quick" if args.quick else "")
    load0 = os.getloadavg()[0]
    res: dict[str, Any] = {
        "config": {
            "command": command,
            "nlst": nlst,
            "freqs_MHz": [f / 1e6 for f in freqs],
            "steps_deg": args.steps,
            "conv_step_deg": args.conv_step,
            "nsides": args.nsides,
            "target_max_K": TARGET_MAX_K,
        },
        "accuracy": accuracy(args, freqs, lsts),
    }
    if args.speed_nfreq:
        res["speed"] = speed(args.speed_nfreq, 64, args.repeat)
    cpu = "unknown"
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.lower().startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    res["machine"] = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "load": f"{load0:.1f} -> {os.getloadavg()[0]:.1f}",
    }
    markdown = render(res)
    print(markdown)
    out = args.out or RESULTS / ("tsky_accuracy_quick" if args.quick else "tsky_accuracy")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(res, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown)
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
