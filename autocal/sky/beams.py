"""Temporary re-exports for the layout merge."""

from autocal.sky.analytic_beams import (  # noqa: F401
    FunctionBeam,
    GaussianDipoleBeam,
    PerturbedBeam,
    s1_airy,
    s1_dipole,
)
from autocal.sky.beam_base import Beam, BeamError, BeamEvaluator  # noqa: F401
from autocal.sky.beam_names import get_beam  # noqa: F401
from autocal.sky.file_beams import HealpixFileBeam  # noqa: F401
