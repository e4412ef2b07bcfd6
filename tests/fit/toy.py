"""Toy data shared by the fit tests.

A day of sky (:func:`toy_tsky`, :func:`make_obs`, :func:`noisy`), a short span over which
the sky changes by ~1 % (:func:`short_sky`, :func:`short_obs`) and random chunks with every
kind of bad sample for the engines (:func:`random_chunk`).
"""

from __future__ import annotations

import numpy as np

from autocal.core.observation import Observation
from autocal.core.sites import HERA

NT, NF = 144, 40
LSTS = np.arange(NT) * 24.0 / NT
FREQS = np.linspace(110e6, 190e6, NF)
#: Channels and frequencies of the short span.
SHORT_NF = 24
SHORT_FREQS = np.linspace(110e6, 190e6, SHORT_NF)
#: Models the engines are checked with.
MODELS = [("constant", 0), ("legendre", 0), ("legendre", 1), ("legendre", 2), ("legendre", 4)]


def toy_tsky(nfreq: int = NF) -> np.ndarray:
    """A day of sky: bright peak near LST 17.5 h, falling with frequency."""
    f = np.linspace(110e6, 190e6, nfreq)
    shape = 1.0 + 3.0 * np.exp(-0.5 * ((LSTS - 17.5) / 3.0) ** 2)
    return 250.0 * shape[:, None] * (f / 150e6)[None, :] ** -2.5


def make_obs(data: np.ndarray, flags: np.ndarray | None = None, bt: float = 5e3) -> Observation:
    nant, npol, nt, nf = data.shape
    return Observation(
        data=data,
        freqs=np.linspace(110e6, 190e6, nf),
        lsts=LSTS[:nt],
        jds=2458098.0 + np.arange(nt) / 288.0,
        antennas=np.arange(nant),
        pols=("ee", "nn")[:npol],
        site=HERA,
        flags=flags,
        channel_width=bt,
        integration_time=1.0,
    )


def noisy(clean: np.ndarray, rng: np.random.Generator, bt: float = 5e3) -> np.ndarray:
    return clean * (1 + rng.standard_normal(clean.shape) / np.sqrt(bt))


def short_sky(nt: int, span_h: float = 0.5, lst0: float = 3.2) -> tuple[np.ndarray, np.ndarray]:
    """A sky that changes by ~1 % over half an hour, with some curvature (LSTs, Tsky)."""
    lsts = lst0 + np.linspace(0.0, span_h, nt)
    x = (lsts - lst0) / span_h
    shape = 1.0 + 0.02 * x + 0.01 * x**2
    return lsts, 250.0 * shape[:, None] * (SHORT_FREQS / 150e6)[None, :] ** -2.5


def short_obs(data: np.ndarray, lsts: np.ndarray, bt: float = 1e6) -> Observation:
    nant, npol, _, nf = data.shape
    return Observation(
        data=data,
        freqs=SHORT_FREQS[:nf],
        lsts=lsts,
        jds=2458116.0 + (lsts - lsts[0]) / 24.0,
        antennas=np.arange(nant),
        pols=("ee", "nn")[:npol],
        site=HERA,
        channel_width=bt,
        integration_time=1.0,
    )


def random_chunk(
    seed: int, nant: int = 3, ntime: int = 37, nfreq: int = 11
) -> dict[str, np.ndarray]:
    """Random data with flags, NaN, inf, zeros, and weights that are sometimes unusable."""
    rng = np.random.default_rng(seed)
    shape = (nant, 2, ntime, nfreq)
    data = rng.uniform(50.0, 6000.0, shape)
    data[rng.random(shape) < 0.03] = np.nan
    data[rng.random(shape) < 0.01] = np.inf
    data[rng.random(shape) < 0.01] = 0.0
    flags = rng.random(shape) < 0.1
    flags[0, 0, :, 1] = True  # a fully flagged channel
    bt = rng.uniform(1e3, 1e4, shape)
    bt[rng.random(shape) < 0.05] = 0.0
    reference = data * rng.uniform(0.9, 1.1, shape)
    reference[rng.random(shape) < 0.05] = -1.0
    user = rng.uniform(0.0, 3.0, shape)
    user[rng.random(shape) < 0.05] = 0.0
    user[~(np.isfinite(data) & ~flags) & (rng.random(shape) < 0.5)] = np.nan  # unusable anyway
    return {
        "data": data,
        "flags": flags,
        "tsky": rng.uniform(100.0, 5000.0, (2, ntime, nfreq)),
        "lsts": np.sort(rng.uniform(0.0, 24.0, ntime)),
        "bt": bt,
        "reference": reference,
        "user": user,
    }
