"""Checks at submission of what a job would only find out later, in the worker.

Run after the options are validated and the paths resolved, before the job is queued:

- the same file named twice in a list (``inputs``, ``reference``), after resolution: a
  relative and an absolute path, or an upload id and its file, are the same input;
- a frequency range outside the band of the data: every UVH5 input whose header is
  readable is asked for its channels (``Header/freq_array`` only; no data is read), and a
  range holding no channel of some file is refused with that file's band;
- a sky that would flag every channel: a sky constant in time (``uniform:T``, or a power
  law of a uniform sky) leaves the receiver temperature and the gain inseparable, so every
  channel's normal matrix is singular, unless a receiver-temperature prior ties them.

Inputs that cannot be read here (not HDF5, Miriad folders, EDGES files) are left to the
worker, which reports them.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from autocal.errors import AutocalError

logger = logging.getLogger(__name__)


class SubmissionError(AutocalError):
    """An option that the job would fail (or flag everything) on; names the field.

    Parameters
    ----------
    field
        The request field at fault (``freq_range_mhz``, ``inputs``, ``sky``...).
    message
        What is wrong and what to do.
    """

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


def check_distinct(paths: Sequence[str | Path], field: str) -> None:
    """Refuse a list of resolved paths that names one file more than once.

    Parameters
    ----------
    paths
        Resolved paths, in the order given.
    field
        The request field they came from.

    Raises
    ------
    SubmissionError
        Naming the repeated file and the positions it was given at.
    """
    positions: dict[str, list[int]] = {}
    for index, path in enumerate(paths):
        positions.setdefault(str(path), []).append(index)
    repeated = {path: where for path, where in positions.items() if len(where) > 1}
    if repeated:
        path, where = next(iter(repeated.items()))
        raise SubmissionError(
            field,
            f"{field}: items {', '.join(str(i) for i in where)} are the same file "
            f"({Path(path).name}); list each file once",
        )


def header_freqs(path: Path) -> np.ndarray | None:
    """Return a UVH5 file's channel frequencies (Hz) from its header, or ``None``.

    Only ``Header/freq_array`` is read. ``None`` when the file is not readable HDF5 with
    that data set (the worker reports such a file).
    """
    try:
        if not path.is_file() or not h5py.is_hdf5(path):
            return None
        with h5py.File(path, "r") as h5:
            freqs = np.asarray(h5["Header/freq_array"][()], dtype=np.float64).ravel()
    except (OSError, KeyError, ValueError, TypeError):
        return None
    return freqs if freqs.size and np.all(np.isfinite(freqs)) else None


def check_band(paths: Sequence[Path], freq_range_mhz: Sequence[float] | None) -> None:
    """Refuse a frequency range that holds no channel of one of the inputs.

    Parameters
    ----------
    paths
        Resolved input files.
    freq_range_mhz
        ``(low, high)`` MHz, or ``None`` (nothing to check).

    Raises
    ------
    SubmissionError
        For ``freq_range_mhz``, naming the file and its band.
    """
    if freq_range_mhz is None:
        return
    lo, hi = sorted(float(f) * 1e6 for f in freq_range_mhz)
    for path in paths:
        freqs = header_freqs(Path(path))
        if freqs is None:
            continue
        if not np.any((freqs >= lo) & (freqs <= hi)):
            raise SubmissionError(
                "freq_range_mhz",
                f"freq_range_mhz {lo / 1e6:g}-{hi / 1e6:g} MHz holds no channel of "
                f"{Path(path).name}, whose band is {freqs.min() / 1e6:.6g}-"
                f"{freqs.max() / 1e6:.6g} MHz ({freqs.size} channels): give a range inside it",
            )


def check_sky_varies(sky: str | None, trxr_prior: object) -> None:
    """Refuse a sky constant in time when nothing else separates gain and receiver.

    Parameters
    ----------
    sky
        The sky specification (``None``: the default, a Galactic model).
    trxr_prior
        The receiver-temperature prior, if any (it makes the fit solvable).

    Raises
    ------
    SubmissionError
        For ``sky``.
    """
    from autocal.sky.models import PowerLawSky, UniformSky, get_sky

    if sky is None or trxr_prior is not None:
        return
    model = get_sky(str(sky))
    base = model.base if isinstance(model, PowerLawSky) else model
    if isinstance(base, UniformSky):
        raise SubmissionError(
            "sky",
            f"sky {sky!r} is the same in every direction, so the sky temperature seen by "
            "the beam does not change with LST: the gain and the receiver temperature "
            "cannot be told apart and every channel would be flagged (singular). Use a "
            "sky map (gsm2008, gsm2016, lfsm, haslam) or give trxr_prior",
        )
