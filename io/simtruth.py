"""HDF5 side-car files holding the truth behind a simulated observation.

Layout: datasets ``gain`` (Ntime, Nfreq), ``trxr`` (Nfreq; K), ``tsky`` (Npol, Ntime,
Nfreq; K), ``freqs`` (Hz), ``lsts`` (hours), ``jds``; root attributes ``format``
(``autocal-simtruth-1``), ``config`` (the simulation settings as JSON), ``pols`` (JSON)
and ``autocal_version``. Written atomically.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal import __version__
from autocal.core.files import atomic_path
from autocal.errors import AutocalError

FORMAT = "autocal-simtruth-1"


class SimTruthError(AutocalError):
    """A file that is not an autocal simulation truth file."""


def write_truth(path: str | Path, truth: Any, obs: Any) -> Path:
    """Write a :class:`autocal.simulate.mock.Truth` with the observation's axes."""
    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs["format"] = FORMAT
        h5.attrs["config"] = json.dumps(truth.config, sort_keys=True)
        h5.attrs["pols"] = json.dumps(list(obs.pols))
        h5.attrs["autocal_version"] = __version__
        for name, value in (
            ("gain", truth.gain),
            ("trxr", truth.trxr),
            ("tsky", truth.tsky),
            ("freqs", obs.freqs),
            ("lsts", obs.lsts),
            ("jds", obs.jds),
        ):
            h5.create_dataset(name, data=np.asarray(value))
    return path


def read_truth(path: str | Path) -> dict[str, Any]:
    """Read a truth file into a dictionary of arrays plus ``config`` and ``pols``."""
    with h5py.File(path, "r") as h5:
        if h5.attrs.get("format") != FORMAT:
            raise SimTruthError(f"{path} is not an autocal simulation truth file ({FORMAT})")
        out: dict[str, Any] = {k: h5[k][()] for k in h5}
        out["config"] = json.loads(h5.attrs["config"])
        out["pols"] = json.loads(h5.attrs["pols"])
    return out
