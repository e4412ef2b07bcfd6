"""HDF5 Tsky tables.

Layout: datasets ``tsky`` (Nlst, Nfreq; kelvin), ``freqs`` (Hz), ``lsts`` (hours),
``f_above`` and ``f_below`` (Nfreq; beam fractions above/below the horizon); root
attributes ``sky``, ``beam``, ``site`` (JSON), ``tgnd_K``, ``nside``, ``epoch_jd``,
``method``, ``engine_version``, ``cmb``, ``frame``, ``azimuth_convention``,
``autocal_version``. Files are written atomically (temporary file, then rename).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np

FORMAT = "autocal-tsky-1"


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: The process umask, read once at import (``os.umask`` can only be read by setting it).
_UMASK = _current_umask()


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp makes the file private (0600); give the product the usual permissions
        # so that a service reading it as another user (API vs worker) can serve it
        if tmp_path.exists():
            os.chmod(tmp_path, 0o666 & ~_UMASK)
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def _attr(value: Any) -> Any:
    if isinstance(value, (dict, list)):
        return json.dumps(value, sort_keys=True, default=str)
    if value is None:
        return "null"
    return value


def write_tsky(path: str | Path, result: Any) -> Path:
    """Write a :class:`autocal.tsky.TskyResult` to HDF5 atomically.

    Parameters
    ----------
    path
        Output file.
    result
        The table.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    from autocal import __version__

    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs["format"] = FORMAT
        h5.attrs["autocal_version"] = __version__
        for name in ("tsky", "freqs", "lsts", "f_above", "f_below"):
            h5.create_dataset(name, data=np.asarray(getattr(result, name), dtype=np.float64))
        h5["tsky"].attrs["units"] = "K"
        h5["tsky"].attrs["axes"] = "lst, freq"
        h5["freqs"].attrs["units"] = "Hz"
        h5["lsts"].attrs["units"] = "hour"
        for key, value in result.meta.items():
            h5.attrs[key] = _attr(value)
    return path


def read_tsky(path: str | Path) -> Any:
    """Read a Tsky table written by :func:`write_tsky`.

    Raises
    ------
    ValueError
        If the file is not an autocal Tsky table.
    """
    from autocal.tsky import TskyResult

    path = Path(path)
    try:
        with h5py.File(path, "r") as h5:
            if h5.attrs.get("format") != FORMAT:
                raise ValueError(f"{path} is not an autocal Tsky table")
            arrays = {n: h5[n][()] for n in ("tsky", "freqs", "lsts", "f_above", "f_below")}
            meta: dict[str, Any] = {}
            for key, value in h5.attrs.items():
                if key in {"format", "autocal_version"}:
                    continue
                if isinstance(value, str) and value[:1] in "{[":
                    value = json.loads(value)
                elif isinstance(value, np.generic):
                    value = value.item()
                meta[key] = value
    except OSError as err:
        raise ValueError(f"{path} is not a readable HDF5 file: {err}") from err
    return TskyResult(meta=meta, **arrays)
