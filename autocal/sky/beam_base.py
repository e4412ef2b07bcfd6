"""The beam interface: :class:`Beam`, :class:`BeamEvaluator` and their conventions.

Convention: a beam is evaluated at directions given by the azimuth ``az`` measured from
north through east (astropy's convention) and the zenith angle ``za`` in ``[0, pi]``,
both in radians, and returns the power pattern ``A(nu, az, za)`` (any normalisation:
Tsky divides by the beam integral). Directions with ``za > pi/2`` are below the horizon;
their beam weight sees the ground.

Polarisations: ``ee`` is the east-west dipole (the "XX" of older HERA papers), ``nn`` the
north-south one. An east-west dipole's pattern is wider along north-south (its H-plane).

A dish fed by a dipole behaves the other way round in its main lobe: the feed's narrower
E-plane pattern under-illuminates the dish along the dipole, so the HERA ``ee`` primary
beam is *wider* east-west near zenith (tested against the Fagnoni file).

The beams: analytic ones in :mod:`autocal.sky.analytic_beams`, beams read from files in
:mod:`autocal.sky.file_beams`; :func:`autocal.sky.beam_names.get_beam` resolves names and
paths to them.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from autocal.errors import AutocalError

#: Speed of light in m/s.
C_LIGHT = 299792458.0
#: The polarisations a beam can have.
POLS = ("ee", "nn")


class BeamError(AutocalError):
    """A beam cannot be built or evaluated as asked."""


class BeamEvaluator:
    """A beam bound to a fixed set of directions, evaluated frequency by frequency.

    Returned by :meth:`Beam.on`; file beams precompute their spatial interpolation here
    so that evaluating many frequency chunks costs one frequency interpolation each.
    """

    #: True if values can never be negative (NaN may still appear): the Tsky engine then
    #: skips its per-value sign check and relies on the beam integrals being finite.
    nonnegative: bool = False

    def __init__(self, beam: Beam, az: np.ndarray, za: np.ndarray) -> None:
        self.beam = beam
        self.az = np.asarray(az, dtype=np.float64)
        self.za = np.asarray(za, dtype=np.float64)

    def __call__(self, freqs: np.ndarray) -> np.ndarray:
        """Return ``(Nfreq, Ndir)`` beam values at ``freqs`` (Hz)."""
        return self.beam.power(freqs, self.az, self.za)

    def by_direction(self, freqs: np.ndarray, rows: slice | None = None) -> np.ndarray:
        """Return the values direction-major: C-contiguous ``(Nrows, Nfreq)``.

        Parameters
        ----------
        freqs
            Frequencies in Hz.
        rows
            The directions to evaluate (a slice of the bound ones; ``None``: all).

        Notes
        -----
        The Tsky engine evaluates the beam block by block of directions, with the
        frequencies as the fastest axis (it Fourier-transforms along HEALPix rings).
        Evaluators that can produce this layout directly override this method.
        It may be called from several threads at once.
        """
        rows = slice(None) if rows is None else rows
        return np.ascontiguousarray(self.beam.power(freqs, self.az[rows], self.za[rows]).T)


class Beam(ABC):
    """A frequency-dependent power beam."""

    name: str = "beam"
    pol: str = "ee"

    @property
    def freq_range(self) -> tuple[float, float] | None:
        """Range of valid frequencies in Hz, or ``None`` if unbounded."""
        return None

    def check_freqs(self, freqs: np.ndarray, in_range: bool = True) -> np.ndarray:
        """Validate a frequency array (Hz) against this beam, returning it as float64.

        With ``in_range=False`` only the grid itself is checked (not empty, finite,
        positive), not the beam's range: a beam read from a file then need not be read
        (a Tsky cache hit checks the range of nothing it computes).
        """
        freqs = np.atleast_1d(np.asarray(freqs, dtype=np.float64))
        if freqs.size == 0:
            raise BeamError("the frequency grid is empty: give at least one frequency")
        if not np.all(np.isfinite(freqs)) or np.any(freqs <= 0):
            raise BeamError("frequencies must be finite and positive (Hz)")
        rng = self.freq_range if in_range else None
        if rng is not None:
            lo, hi = rng
            tol = 1e-6 * hi
            if freqs.min() < lo - tol or freqs.max() > hi + tol:
                raise BeamError(
                    f"frequencies {freqs.min() / 1e6:.3f}-{freqs.max() / 1e6:.3f} MHz are "
                    f"outside the {self.name} beam's range {lo / 1e6:.3f}-{hi / 1e6:.3f} MHz"
                )
        return freqs

    @abstractmethod
    def power(self, freqs: np.ndarray, az: np.ndarray, za: np.ndarray) -> np.ndarray:
        """Return the power beam ``(Nfreq, Ndir)`` at ``freqs`` (Hz) and directions (rad)."""

    def on(self, az: np.ndarray, za: np.ndarray) -> BeamEvaluator:
        """Bind the beam to fixed directions (see :class:`BeamEvaluator`)."""
        return BeamEvaluator(self, az, za)

    @abstractmethod
    def describe(self) -> dict[str, Any]:
        """Return a JSON-serialisable description (provenance and cache keys)."""


def check_pol(pol: str) -> str:
    """Return ``pol`` in lower case, raising :class:`BeamError` unless it is one of :data:`POLS`."""
    pol = pol.lower()
    if pol not in POLS:
        raise BeamError(f"polarisation {pol!r} not supported: use one of {POLS}")
    return pol
