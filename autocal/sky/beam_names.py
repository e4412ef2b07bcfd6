"""Beams by name or path: :func:`get_beam`.

Names: ``dipole`` and ``airy`` (:mod:`autocal.sky.analytic_beams`), ``hera`` (the
Fagnoni beamfits) and the EDGES FEKO beams in the data folder; paths to UVBeam or FEKO
files (:mod:`autocal.sky.file_beams`).
"""

from __future__ import annotations

from pathlib import Path

from autocal.io.datasets import EDGES_BEAM_FILES, HERA_BEAM_FILE, data_file
from autocal.io.feko import BeamFileError
from autocal.sky.analytic_beams import AiryBeam, GaussianDipoleBeam
from autocal.sky.beam_base import Beam, BeamError, check_pol
from autocal.sky.file_beams import FekoFileBeam, HealpixFileBeam

_BEAM_HELP = (
    "beams: dipole, airy, hera (the Fagnoni beamfits in the data folder), edges-low, "
    "edges-low-45deg, edges-mid, edges-high (FEKO files in the data folder), or a path to a "
    "UVBeam file (.beamfits, .fits, .h5) or an EDGES FEKO .txt file"
)


def get_beam(spec: str | Beam, pol: str = "ee") -> Beam:
    """Resolve a beam specification.

    Parameters
    ----------
    spec
        A :class:`Beam`, a name (see ``_BEAM_HELP``) or a file path.
    pol
        ``"ee"`` or ``"nn"``.

    Returns
    -------
    Beam
        The beam.

    Raises
    ------
    BeamError
        For unknown names or unreadable files.
    """
    if isinstance(spec, Beam):
        return spec
    pol = check_pol(pol)
    key = str(spec).strip()
    low = key.lower()
    try:
        if low == "dipole":
            return GaussianDipoleBeam(pol=pol)
        if low == "airy":
            return AiryBeam(pol=pol)
        if low == "hera":
            return HealpixFileBeam(data_file(HERA_BEAM_FILE, "HERA Fagnoni beam"), pol)
        if low in EDGES_BEAM_FILES:
            return FekoFileBeam(data_file(EDGES_BEAM_FILES[low], f"EDGES {low} beam"), pol=pol)
        path = Path(key).expanduser()
        if path.suffix.lower() == ".txt":
            return FekoFileBeam(path, pol=pol)
        if path.suffix.lower() in {".beamfits", ".fits", ".h5", ".uvbeam"} or path.exists():
            return HealpixFileBeam(path, pol)
    except (BeamFileError, FileNotFoundError) as err:
        raise BeamError(str(err)) from err
    raise BeamError(f"unknown beam {spec!r}; {_BEAM_HELP}")
