"""Where the diagnosis's cable-reflection search stops finding true reflections.

Synthetic gains (numpy's generator, not autocal's simulator): a smooth bandpass over
110-190 MHz in 161 channels times ``1 + a cos(2 pi nu tau + phi)``, noise 1e-3, judged by
the search's own rule (:func:`autocal.diagnosis.candidate_fits.reflection_refusal` and the
``Delta BIC`` threshold of ``try_cable_reflection``). Four limits, each a count over fixed
seeds::

    python scripts/reflection_limits.py

1. faint reflections (a = 0.05-0.08 %, 8 delays x 12 seeds): of those over the threshold,
   how many are refused, and by which rule;
2. an amplitude changing across the band (1.67x and 2.08x from end to end; 0.5 %, 4 delays
   x 8 seeds): how many are refused;
3. beside shorter structure (a 0.15 % ripple at 75 ns, a 0.1 % reflection at 95-160 ns):
   taken or not, per delay;
4. beside a 1 % ripple at 55-70 ns, a 0.2 % reflection at 150 ns: found or not.

Prints one line per limit (the guide's numbers, ``docs/guide/diagnosis.md#fit``).
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from autocal.diagnosis.bandpass import fit_cable_reflection
from autocal.diagnosis.candidate_fits import reflection_refusal
from autocal.diagnosis.trials import BIC_THRESHOLD

FREQS = np.linspace(110e6, 190e6, 161)
X = (FREQS - 150e6) / 40e6
SMOOTH = 1.0 + 0.3 * X - 0.2 * X**2 + 0.05 * X**3
SIGMA = np.full(FREQS.size, 1e-3)


def verdict(g: np.ndarray) -> tuple[str, float]:
    """Return ``"below"`` (under the threshold), ``"taken"`` or the refusal's kind, and tau."""
    null, rip = fit_cable_reflection(FREQS, g, SIGMA)
    k = rip.nparam - null.nparam
    stat = (null.chi2 - rip.chi2) / max(1.0, rip.reduced_chi2) - k * np.log(null.nfreq)
    if stat <= BIC_THRESHOLD:
        return "below", rip.tau_ns
    refusal = reflection_refusal(FREQS, g, SIGMA, rip)
    if refusal is None:
        return "taken", rip.tau_ns
    for key in ("side lobe", "only one", "disagree", "below the range", "upper end"):
        if key in refusal:
            return key, rip.tau_ns
    return "refused", rip.tau_ns


def ripple(a: np.ndarray | float, tau_ns: float, phase: float) -> np.ndarray:
    return 1.0 + a * np.cos(2 * np.pi * FREQS * tau_ns * 1e-9 + phase)


def main() -> None:
    """Measure the four limits and print them."""
    faint: Counter[str] = Counter()
    for a in (5e-4, 6e-4, 7e-4, 8e-4):
        for tau in (95.0, 110.0, 130.0, 150.0, 200.0, 250.0, 300.0, 400.0):
            for seed in range(12):
                phase = np.random.default_rng(1000 + seed).uniform(-np.pi, np.pi)
                rng = np.random.default_rng(seed * 7919 + int(tau))
                g = SMOOTH * ripple(a, tau, phase) + rng.normal(0, 1e-3, FREQS.size)
                faint[verdict(g)[0]] += 1
    over = sum(n for k, n in faint.items() if k != "below")
    kinds = {k: n for k, n in faint.items() if k not in ("below", "taken")}
    print(
        f"1. faint (a 0.05-0.08 %): {over} over the threshold, {faint['taken']} taken, "
        f"refused {kinds}"
    )
    for change in (1.67, 2.08):
        slope = 2 * (change - 1) / (change + 1)  # (1 + s/2) / (1 - s/2) = change
        refused = 0
        for tau in (95.0, 150.0, 250.0, 400.0):
            for seed in range(8):
                rng = np.random.default_rng(seed * 31 + int(tau))
                g = SMOOTH * ripple(5e-3 * (1 + slope * X / 2), tau, 0.7)
                refused += verdict(g + rng.normal(0, 1e-3, FREQS.size))[0] != "taken"
        print(f"2. amplitude changing {change}x across the band: {refused} of 32 not taken")
    side = []
    for tau in (95.0, 100.0, 110.0, 120.0, 130.0, 140.0, 160.0):
        rng = np.random.default_rng(int(tau))
        g = SMOOTH * ripple(1.5e-3, 75.0, 0.3) * ripple(1e-3, tau, 0.7)
        v, best = verdict(g + rng.normal(0, 1e-3, FREQS.size))
        side.append(f"{tau:.0f} ns {v if v != 'taken' or abs(best - tau) < 5 else 'elsewhere'}")
    print("3. 0.1 % beside 0.15 % at 75 ns: " + ", ".join(side))
    near = []
    for shorter in (55.0, 60.0, 70.0):
        for seed in range(3):
            rng = np.random.default_rng(100 * int(shorter) + seed)
            g = SMOOTH * ripple(1e-2, shorter, 0.3) * ripple(2e-3, 150.0, 0.7)
            v, best = verdict(g + rng.normal(0, 1e-3, FREQS.size))
            near.append(v == "taken" and abs(best - 150.0) < 5)
    print(f"4. 0.2 % at 150 ns beside 1 % at 55-70 ns: found {sum(near)} of {len(near)}")


if __name__ == "__main__":
    main()
