"""Tsky at given LSTs from its Fourier series in LST.

For a drift scan the beam-weighted sky is periodic in LST: the engines deliver its
harmonics ``coef[m]`` and :func:`synthesise` evaluates ``Re sum_m coef[m] exp(-i m L)`` at
any LSTs ``L`` (radians, :func:`lst_radians`): one inverse FFT for a regular LST grid, a
matrix product otherwise.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sp_fft


def lst_radians(lsts_hours: np.ndarray) -> np.ndarray:
    """Return LSTs given in hours as angles in ``[0, 2 pi)`` radians."""
    return np.mod(lsts_hours, 24.0) * (2 * np.pi / 24.0)


def _regular_grid(lst_rad: np.ndarray, mmax: int) -> tuple[int, np.ndarray] | None:
    """``(N, k)`` if every LST is ``lst[0] + k 2 pi / N`` (phase error < 1e-9 rad), else None."""
    if lst_rad.size < 2:
        return None
    diffs = np.diff(np.unique(lst_rad))
    if diffs.size == 0:
        return None
    n = round(float(2 * np.pi / diffs.min()))
    if n < 2 or n > (1 << 22):
        return None
    step = 2 * np.pi / n
    k = (lst_rad - lst_rad[0]) / step
    kr = np.round(k)
    if np.max(np.abs(k - kr)) * step * max(mmax, 1) > 1e-9:
        return None
    return n, np.mod(kr.astype(np.int64), n)


def synthesise(coef: np.ndarray, lst_rad: np.ndarray) -> np.ndarray:
    """``Re sum_m coef[m] exp(-i m L)`` for every LST: ``(M, K)`` -> ``(Nlst, K)``.

    LSTs on a regular grid of ``N`` points per day use one inverse real FFT of length
    ``N`` (or, with fewer than ``2 M`` points per day, a complex FFT of the harmonics
    folded modulo ``N``); other LSTs a matrix product with ``cos``/``sin``.
    """
    nm = coef.shape[0]
    grid = _regular_grid(lst_rad, nm - 1)
    if grid is not None and grid[0] * max(np.log2(grid[0]), 1.0) <= 4 * lst_rad.size * nm:
        n, k = grid
        shifted = coef * np.exp(-1j * np.arange(nm) * lst_rad[0])[:, None]
        if 2 * (nm - 1) < n:
            # irfft(X)_k = [X_0 + 2 Re sum_m X_m e^{2 pi i m k / N}] / N with X_m = conj
            half = np.zeros((n // 2 + 1, coef.shape[1]), dtype=np.complex128)
            half[0] = n * shifted[0].real
            half[1:nm] = (n / 2) * np.conj(shifted[1:])
            full = sp_fft.irfft(half, n=n, axis=0, workers=-1)
        else:  # fewer LSTs per day than harmonics: alias m onto m mod N
            folded = np.zeros((n, coef.shape[1]), dtype=np.complex128)
            np.add.at(folded, np.arange(nm) % n, shifted)
            full = sp_fft.fft(folded, axis=0, workers=-1).real
        if k.size == n and np.array_equal(k, np.arange(n)):
            return full
        return full[k]
    phase = np.outer(lst_rad, np.arange(nm))
    return np.cos(phase) @ coef.real + np.sin(phase) @ coef.imag
