"""Synthetic solutions' reference gains and drifts shared by the comparison tests."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import autocal  # noqa: F401
from autocal.io.calsol_read import ReferenceGains
from autocal.sky.analytic_beams import FunctionBeam

BEAM_FILE = "hera/beams/HERA_NF_dipole_power.beamfits"


def exp_beam(s: float) -> FunctionBeam:
    """``A = exp(-(1 - cos za) / s)``: ``Omega = 2 pi s (1 - exp(-2 / s))`` in closed form."""
    return FunctionBeam(
        func=lambda f, az, za: np.exp(-(1 - np.cos(za)) / s)[None, :] * np.ones((f.size, 1)),
        key=f"exp{s}",
    )


def reference_for(
    sol,
    factor: np.ndarray | float,
    *,
    ntime: int = 5,
    jds: np.ndarray | None = None,
    freqs: np.ndarray | None = None,
    scatter: float = 0.0,
    absolute: bool = True,
    gain_scale: str | None = "Jy",
    flags: np.ndarray | None = None,
    seed: int = 0,
) -> ReferenceGains:
    """Reference gains with |g_ref|(nu) = factor(nu) |g_auto|(nu), interpolated to ``freqs``."""
    rng = np.random.default_rng(seed)
    freqs = sol.freqs if freqs is None else freqs
    jds = np.linspace(sol.jds.min(), sol.jds.max(), ntime) if jds is None else jds
    g = np.sqrt(np.nan_to_num(sol.G, nan=1.0))
    amp = np.array([[np.interp(freqs, sol.freqs, row) for row in ant] for ant in g])
    amp = amp * np.broadcast_to(factor, amp.shape)
    gains = amp[:, :, None, :] * (
        1 + scatter * rng.standard_normal((*amp.shape[:2], jds.size, freqs.size))
    )
    gains = gains * np.exp(1j * rng.uniform(0, 2 * np.pi, gains.shape))
    return ReferenceGains(
        gains=gains,
        flags=np.zeros(gains.shape, bool) if flags is None else flags,
        freqs=freqs,
        jds=jds,
        lsts=None,
        antennas=sol.antennas.copy(),
        pols=sol.pols,
        gain_convention="divide",
        absolute=absolute,
        gain_scale=gain_scale if absolute else None,
        meta={"files": ["synthetic"]},
    )


def drifting(ref: ReferenceGains, rise: float) -> ReferenceGains:
    """Scale the reference so that |g|^2 rises linearly by ``rise`` over its times."""
    power = 1.0 + rise * np.linspace(0.0, 1.0, ref.ntime)
    return replace(ref, gains=ref.gains * np.sqrt(power)[None, None, :, None])


def end_change(rise: float, ntime: int, k: int) -> float:
    """The drift statistic of a linear |g|^2 ramp with ``k`` integrations per end."""
    power = 1.0 + rise * np.linspace(0.0, 1.0, ntime)
    return power[-k:].mean() / power[:k].mean() - 1.0
