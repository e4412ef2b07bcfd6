"""How the diagnosis streams an observation: chunks of antennas, usable weights.

Each channel's ``(G, n)`` belongs to one antenna, and the extended fit's global normal
equations and chi^2 are sums over antennas, so every pass over an observation (the fit, its
model and residuals, the outlier flagging) takes a chunk of antennas at a time
(:func:`antenna_chunks`). The weights of a large observation (:data:`LARGE_SAMPLES`) are
kept in float32 (:func:`weights_dtype`).
"""

from __future__ import annotations

import math

import numpy as np

from autocal.diagnosis.errors import DiagnoseError

#: Samples (antenna x pol x integration x channel) in one chunk of antennas of the extended
#: fit and of every pass over its model or residuals. Each channel's ``(G, n)`` belongs to
#: one antenna and the global normal equations and chi^2 are sums over antennas, so the fit
#: streams antennas through its sums; working arrays are a chunk's size, not the
#: observation's, and elementwise work on a chunk of a few MB stays in the processor's
#: caches (one HERA antenna, 0.6 M samples: ~6x faster per sample than 16 antennas at once,
#: ``benchmarks/diagnose_scale.py``).
CHUNK_SAMPLES = 1 << 20
#: Observations with more samples than this are "large": their weights are kept in float32
#: (:func:`autocal.diagnosis.extended_fit.radiometer_weights`) and the search screens its
#: candidates by their score before fitting them
#: (:func:`autocal.diagnosis.screening.screen_candidates`). Smaller ones are diagnosed
#: exactly as before.
LARGE_SAMPLES = 1 << 24


def antenna_chunks(shape: tuple[int, ...], chunk_antennas: int | None = None) -> list[slice]:
    """Return the slices of antennas processed together (:data:`CHUNK_SAMPLES`).

    Parameters
    ----------
    shape
        ``(Nant, Npol, Ntime, Nfreq)``.
    chunk_antennas
        Antennas per chunk (default: as many as :data:`CHUNK_SAMPLES` allows, at least one).
    """
    per_antenna = max(1, math.prod(shape[1:]))
    n = max(1, CHUNK_SAMPLES // per_antenna) if chunk_antennas is None else int(chunk_antennas)
    if n < 1:
        raise DiagnoseError(f"chunks need at least one antenna, got {chunk_antennas}")
    return [slice(i, min(i + n, shape[0])) for i in range(0, shape[0], n)]


def is_large(shape: tuple[int, ...]) -> bool:
    """Return whether an observation of this shape is large (:data:`LARGE_SAMPLES`)."""
    return math.prod(shape) > LARGE_SAMPLES


def weights_dtype(shape: tuple[int, ...]) -> type:
    """Float64 weights, float32 for a large observation (:data:`LARGE_SAMPLES`).

    The weights are held fixed while fits are compared, so their rounding to float32 (a
    relative 6e-8) changes every compared chi^2 alike; every sum is accumulated in float64.
    """
    return np.float32 if is_large(shape) else np.float64


def usable_weights(weights: np.ndarray, chan_ok: np.ndarray | None = None) -> np.ndarray:
    """Return a chunk's weights ``(a, P, T, F)`` as float64, zero where unusable.

    Unusable: not finite, not positive, or in a channel without a ``(G, n)`` solution
    (``chan_ok`` ``(a, P, F)`` false).
    """
    w = np.asarray(weights, np.float64)
    ok = np.isfinite(w) & (w > 0)
    if chan_ok is not None:
        ok &= chan_ok[:, :, None, :]
    return np.where(ok, w, 0.0)
