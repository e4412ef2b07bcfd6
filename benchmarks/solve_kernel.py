"""Benchmark: the compiled solver's general kernel against its unrolled two-parameter copy.

Both kernels of :mod:`autocal.fit.solve_kernel` solve the same 1.07 M synthetic
two-parameter systems (a HERA file's 350 antennas x 2 pols x 1536 channels of the
constant model; sums of 50 integrations, fractional noise 1e-3) through
:func:`autocal.fit.threads.in_threads` (all cores), in turn, after one unmeasured call
each (numba's compilation). Prints the median of ``--repeats`` calls of each, their ratio,
and whether every output is bit-identical::

    python benchmarks/solve_kernel.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from autocal.fit import solve_kernel
from autocal.fit.threads import in_threads


def systems(n: int, ntime: int = 50, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Return ``(ata, aty, yty, count)`` of ``n`` fits of ``R = 0.02 (Tsky + 150 K)``."""
    rng = np.random.default_rng(seed)
    sky = rng.uniform(100, 1000, (n, ntime))
    ata = np.empty((n, 2, 2))
    ata[:, 0, 0] = (sky * sky).sum(1)
    ata[:, 0, 1] = ata[:, 1, 0] = sky.sum(1)
    ata[:, 1, 1] = ntime
    y = 0.02 * (sky + 150) * (1 + 1e-3 * rng.standard_normal(sky.shape))
    aty = np.stack([(sky * y).sum(1), y.sum(1)], -1)
    return ata, aty, (y * y).sum(1), np.full(n, ntime)


def solve_with(kernel, ata, aty, yty, count) -> dict[str, np.ndarray]:  # type: ignore[no-untyped-def]
    """Solve every system with ``kernel`` as :func:`solve_kernel.solve_channels` does."""
    n = aty.shape[0]
    out = {
        "coeffs": np.empty((n, 2)),
        "cov": np.empty((n, 2, 2)),
        "chi2": np.empty(n),
        "flag_reason": np.zeros(n, np.int8),
    }
    args = (ata, aty, yty, count, 3, 2, 1e12, True, *out.values())
    in_threads(lambda c0, c1: kernel(*args, c0, c1), -(-n // solve_kernel._CHUNK))
    return out


def main() -> None:
    """Run the comparison and print it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    data = systems(350 * 2 * 1536)
    kernels = {"general": solve_kernel._kernel, "unrolled": solve_kernel._kernel2}
    outputs = {name: solve_with(k, *data) for name, k in kernels.items()}  # compile
    times: dict[str, list[float]] = {name: [] for name in kernels}
    for _ in range(args.repeats):
        for name, kernel in kernels.items():
            t0 = time.perf_counter()
            solve_with(kernel, *data)
            times[name].append(time.perf_counter() - t0)
    med = {name: statistics.median(t) for name, t in times.items()}
    same = all(
        np.array_equal(outputs["general"][k], outputs["unrolled"][k], equal_nan=True)
        for k in outputs["general"]
    )
    print(f"{data[1].shape[0]} two-parameter systems, median of {args.repeats}:")
    for name, value in med.items():
        print(f"  {name:9s} {value:.3f} s")
    print(f"  general / unrolled = {med['general'] / med['unrolled']:.2f}; bit-identical: {same}")


if __name__ == "__main__":
    main()
