"""Benchmark: the compiled solver's kernels side by side.

1. The general kernel of :mod:`autocal.fit.solve_kernel` against its unrolled
   two-parameter copy on the same 1.07 M synthetic two-parameter systems (a HERA file's
   350 antennas x 2 pols x 1536 channels of the constant model; sums of 50 integrations,
   fractional noise 1e-3).
2. The general kernel with and without the condition bound on 1.07 M four-parameter
   systems (the Legendre-1 model that the total uncertainty fits to every channel to
   weigh a drifting gain; the same sky, the drift's time shape ``s`` linear over the span).

Each through :func:`autocal.fit.threads.in_threads` (all cores), in turn, after one
unmeasured call each (numba's compilation). Prints the median of ``--repeats`` calls of
each, their ratio, and whether every output is bit-identical::

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


def drift_systems(n: int, ntime: int = 50, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Return the four-parameter ``(G, n, G d, n e)`` sums of the same fits, drift basis ``s``."""
    rng = np.random.default_rng(seed)
    sky = rng.uniform(100, 1000, (n, ntime))
    s = np.linspace(-1.0, 1.0, ntime)
    cols = np.stack([sky, np.ones_like(sky), sky * s, np.broadcast_to(s, sky.shape)], -1)
    y = 0.02 * (sky + 150) * (1 + 1e-3 * rng.standard_normal(sky.shape))
    ata = np.einsum("nti,ntj->nij", cols, cols)
    aty = np.einsum("nti,nt->ni", cols, y)
    return ata, aty, (y * y).sum(1), np.full(n, ntime)


def solve_with(kernel, ata, aty, yty, count, *extra) -> dict[str, np.ndarray]:  # type: ignore[no-untyped-def]
    """Solve every system with ``kernel`` as :func:`solve_kernel.solve_channels` does."""
    n, m = aty.shape
    out = {
        "coeffs": np.empty((n, m)),
        "cov": np.empty((n, m, m)),
        "chi2": np.empty(n),
        "flag_reason": np.zeros(n, np.int8),
    }
    args = (ata, aty, yty, count, 3, 2, 1e12, True, *out.values())
    in_threads(lambda c0, c1: kernel(*args, c0, c1, *extra), -(-n // solve_kernel._CHUNK))
    return out


def compare(title: str, runs: dict[str, tuple], data: tuple[np.ndarray, ...], repeats: int) -> None:
    """Time each ``(kernel, *extra)`` of ``runs`` on ``data`` in turn; print medians, ratio."""
    outputs = {name: solve_with(run[0], *data, *run[1:]) for name, run in runs.items()}
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            t0 = time.perf_counter()
            solve_with(run[0], *data, *run[1:])
            times[name].append(time.perf_counter() - t0)
    med = {name: statistics.median(t) for name, t in times.items()}
    first, second = list(runs)
    same = all(
        np.array_equal(outputs[first][k], outputs[second][k], equal_nan=True)
        for k in outputs[first]
    )
    print(f"{data[1].shape[0]} {title}, median of {repeats}:")
    for name, value in med.items():
        print(f"  {name:14s} {value:.3f} s")
    print(f"  {first} / {second} = {med[first] / med[second]:.2f}; bit-identical: {same}")


def main() -> None:
    """Run the comparison and print it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    n = 350 * 2 * 1536
    kernels = {"general": (solve_kernel._kernel,), "unrolled": (solve_kernel._kernel2,)}
    compare("two-parameter systems", kernels, systems(n), args.repeats)
    paths = {"eigenvalues": (solve_kernel._kernel, False), "bound": (solve_kernel._kernel, True)}
    compare("four-parameter systems", paths, drift_systems(n), args.repeats)


if __name__ == "__main__":
    main()
