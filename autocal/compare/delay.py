"""Delay spectra of calibration products.

The delay spectrum of a product ``F(nu)`` (a gain, a receiver temperature, a gain ratio)
is the amplitude of its windowed Fourier transform along frequency, normalised to its
value at zero delay: ``D(tau) = |FT[w F](tau)| / |FT[w F](0)|``. Spectral structure on a
scale of ``1/tau`` (a cable reflection at delay ``tau``, a beam-sky chromatic mix) appears
as power at ``tau``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import get_window

from autocal.errors import AutocalError


class DelayError(AutocalError):
    """Invalid input for a delay spectrum."""


@dataclass(frozen=True)
class DelaySpectrum:
    """A delay spectrum.

    Attributes
    ----------
    delays
        ``(Ndelay,)`` non-negative delays in seconds.
    amplitude
        ``(..., Ndelay)`` amplitude normalised to 1 at zero delay.
    window
        Window name.
    """

    delays: np.ndarray
    amplitude: np.ndarray
    window: str

    @property
    def delays_ns(self) -> np.ndarray:
        """Delays in nanoseconds."""
        return self.delays * 1e9


def delay_spectrum(
    values: np.ndarray,
    freqs: np.ndarray,
    *,
    flags: np.ndarray | None = None,
    window: str = "blackmanharris",
    subtract_mean: bool = False,
) -> DelaySpectrum:
    """Return the normalised delay spectrum of ``values`` along its last axis.

    Parameters
    ----------
    values
        ``(..., Nfreq)`` real or complex product on a uniform frequency grid.
    freqs
        ``(Nfreq,)`` Hz, uniformly spaced.
    flags
        Like ``values``; flagged or non-finite channels get zero weight.
    window
        Any :func:`scipy.signal.get_window` name (``blackmanharris`` keeps the leakage
        of a smooth spectrum below 1e-4 beyond a few delay bins).
    subtract_mean
        Remove the (weighted) mean before transforming; the normalisation then uses the
        mean's own zero-delay amplitude, so ripples read as fractions of the mean.

    Returns
    -------
    DelaySpectrum
        Delays ``0 .. 1/(2 dnu)`` and amplitudes normalised to the zero-delay value.
    """
    values = np.asarray(values)
    freqs = np.asarray(freqs, dtype=np.float64)
    if values.shape[-1] != freqs.size:
        raise DelayError(f"{values.shape[-1]} values for {freqs.size} frequencies")
    if freqs.size < 4:
        raise DelayError("a delay spectrum needs at least 4 channels")
    steps = np.diff(freqs)
    if not np.allclose(steps, steps[0], rtol=1e-6, atol=0.0) or steps[0] <= 0:
        raise DelayError("frequencies must be uniformly spaced and increasing")
    mask = np.isfinite(values)
    if flags is not None:
        mask &= ~np.broadcast_to(np.asarray(flags, bool), values.shape)
    win = get_window(window, freqs.size, fftbins=False)
    weight = win * mask
    data = np.where(mask, values, 0.0)
    wsum = weight.sum(axis=-1, keepdims=True)
    if np.any(wsum == 0):
        raise DelayError("a spectrum has every channel flagged")
    mean = (weight * data).sum(axis=-1, keepdims=True) / wsum
    if subtract_mean:
        data = np.where(mask, data - mean, 0.0)
    spec = np.abs(np.fft.rfft(weight * data, axis=-1))
    ref = np.abs(mean[..., 0]) * wsum[..., 0] if subtract_mean else spec[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        amp = spec / ref[..., None]
    delays = np.fft.rfftfreq(freqs.size, d=steps[0])
    return DelaySpectrum(delays, amp, window)
