"""Benchmark: ring-FFT Tsky engine vs the per-LST brute-force reference, side by side.

Both run in the same process on the same low-rank sky (GSM2008 at the chosen nside) and
beam; the table reports wall times, their ratio and max |difference|. Usage::

    python benchmarks/tsky.py [--beam dipole] [--nfreq 32] [--nlst 144] [--nsides 64 128]
                              [--json benchmarks/results/tsky.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

import autocal
from autocal.beams import get_beam
from autocal.sites import HERA
from autocal.sky import get_sky
from autocal.tsky import tsky_brute, tsky_fft


def run(beam_name: str, nfreq: int, nlst: int, nside: int) -> dict:
    freqs = np.linspace(100e6, 200e6, nfreq)
    lsts = np.linspace(0, 24, nlst, endpoint=False)
    beam = get_beam(beam_name, "ee")
    sky = get_sky("gsm2008").components(freqs, nside=nside, epoch="2018-01-01")
    t0 = time.perf_counter()
    fast = tsky_fft(sky, beam, HERA, lsts, progress=False)
    t_fast = time.perf_counter() - t0
    t0 = time.perf_counter()
    slow = tsky_brute(sky, beam, HERA, lsts, progress=False)
    t_slow = time.perf_counter() - t0
    diff = np.abs(fast.tsky - slow.tsky)
    return {
        "beam": beam_name,
        "nside": nside,
        "nfreq": nfreq,
        "nlst": nlst,
        "fft_s": round(t_fast, 3),
        "brute_s": round(t_slow, 3),
        "speedup": round(t_slow / t_fast, 1),
        "max_abs_diff_K": float(f"{diff.max():.3g}"),
        "max_rel_diff": float(f"{(diff / slow.tsky).max():.3g}"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beam", default="dipole")
    parser.add_argument("--nfreq", type=int, default=32)
    parser.add_argument("--nlst", type=int, default=144)
    parser.add_argument("--nsides", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    rows = [run(args.beam, args.nfreq, args.nlst, n) for n in args.nsides]
    machine = (
        f"{platform.processor() or platform.machine()}, {platform.system()}, "
        f"python {platform.python_version()}, autocal {autocal.__version__}"
    )
    print(f"# Tsky engine vs brute force ({machine})")
    print(
        "| beam | nside | channels | LSTs | ring FFT [s] | brute force [s] | speed-up | "
        "max abs diff [K] | max rel diff |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['beam']} | {r['nside']} | {r['nfreq']} | {r['nlst']} | {r['fft_s']} | "
            f"{r['brute_s']} | {r['speedup']}x | {r['max_abs_diff_K']} | {r['max_rel_diff']} |"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"machine": machine, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
