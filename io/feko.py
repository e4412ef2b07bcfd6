"""EDGES FEKO beam text files (``edges/beams/*/*.txt``).

Format (as written by the EDGES collaboration's FEKO post-processing): for each
frequency, a line ``#FREQUENCY <f> MHz ...``, a header line of elevation indices, then
360 lines ``az <k> g_0 ... g_90`` giving the gain in dB at azimuth ``k`` degrees and
elevations 0..90 degrees. Azimuth is measured in the antenna frame from the excitation
axis; edges-analysis rotates it by ``rotation_from_north`` (90 deg by default) to true
azimuth east of north.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from autocal.errors import AutocalError

logger = logging.getLogger(__name__)

_FREQ_RE = re.compile(r"^#FREQUENCY\s+([0-9.eE+-]+)\s*MHz")


class BeamFileError(AutocalError):
    """A beam file cannot be read or is inconsistent."""


@dataclass(frozen=True)
class FekoBeamData:
    """Contents of a FEKO beam file.

    Attributes
    ----------
    freqs
        ``(Nfreq,)`` frequencies in Hz.
    az_deg
        ``(Naz,)`` azimuths in degrees, antenna frame.
    el_deg
        ``(Nel,)`` elevations in degrees.
    gain
        ``(Nfreq, Naz, Nel)`` linear power gain.
    """

    freqs: np.ndarray
    az_deg: np.ndarray
    el_deg: np.ndarray
    gain: np.ndarray


def read_feko_beam(path: str | Path) -> FekoBeamData:
    """Read an EDGES FEKO beam text file.

    Parameters
    ----------
    path
        The file.

    Returns
    -------
    FekoBeamData
        Frequencies, grids and linear gain.

    Raises
    ------
    BeamFileError
        If the file is missing, truncated or not in the expected format.
    """
    path = Path(path)
    if not path.is_file():
        raise BeamFileError(f"beam file {path} does not exist")
    stat = path.stat()
    return _read_cached(str(path.resolve()), stat.st_mtime_ns, stat.st_size)


@lru_cache(maxsize=8)
def _read_cached(path: str, _mtime: int, _size: int) -> FekoBeamData:
    freqs: list[float] = []
    rows: list[str] = []
    with open(path, encoding="ascii", errors="replace") as handle:
        for line in handle:
            if line.startswith("#"):
                match = _FREQ_RE.match(line)
                if match:
                    freqs.append(float(match.group(1)) * 1e6)
                continue
            if line.strip():
                rows.append(line)
    if not freqs or not rows:
        raise BeamFileError(f"{path} is not a FEKO beam text file (no '#FREQUENCY' blocks)")
    try:
        table = np.loadtxt(rows, usecols=range(1, 93), dtype=np.float64)
    except ValueError as err:
        raise BeamFileError(f"{path}: malformed beam rows ({err})") from err
    nfreq = len(freqs)
    if table.shape[0] != nfreq * 360:
        raise BeamFileError(
            f"{path}: expected {nfreq} x 360 azimuth rows, found {table.shape[0]} (truncated file?)"
        )
    az = table[:360, 0]
    if not np.array_equal(az, np.arange(360.0)):
        raise BeamFileError(f"{path}: azimuth column is not 0..359 degrees")
    gain_db = table[:, 1:].reshape(nfreq, 360, 91)
    if not np.all(np.isfinite(gain_db)):
        raise BeamFileError(f"{path}: non-finite gain values")
    freq_arr = np.asarray(freqs)
    if np.any(np.diff(freq_arr) <= 0):
        raise BeamFileError(f"{path}: frequencies are not increasing")
    logger.info(
        "read FEKO beam %s: %d frequencies %.0f-%.0f MHz",
        path,
        nfreq,
        freq_arr[0] / 1e6,
        freq_arr[-1] / 1e6,
    )
    return FekoBeamData(
        freqs=freq_arr, az_deg=az, el_deg=np.arange(91.0), gain=10.0 ** (gain_db / 10.0)
    )
