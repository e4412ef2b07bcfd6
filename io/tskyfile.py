"""HDF5 Tsky tables and Tsky harmonics.

Tables (:func:`write_tsky`, format ``autocal-tsky-1``): datasets ``tsky`` (Nlst, Nfreq;
kelvin), ``freqs`` (Hz), ``lsts`` (hours), ``f_above`` and ``f_below`` (Nfreq; beam
fractions above/below the horizon); root attributes ``sky``, ``beam``, ``site`` (JSON),
``tgnd_K``, ``nside``, ``epoch_jd``, ``method``, ``engine_version``, ``cmb``, ``frame``,
``azimuth_convention``, ``autocal_version``.

Harmonics (:func:`write_harmonics`, format ``autocal-tsky-harmonics-1``, the Tsky cache's
entries): datasets ``coef`` (M, Nfreq; complex, kelvin times beam integral), ``freqs``,
``sum_all`` and ``sum_below`` (Nfreq); the same root attributes but ``tgnd_K``.

Files are written atomically (temporary file, then rename).
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
from autocal.tsky.result import TskyError, TskyHarmonics, TskyResult

FORMAT = "autocal-tsky-1"
HARMONICS_FORMAT = "autocal-tsky-harmonics-1"


class TskyFileError(AutocalError):
    """A file that is not a readable autocal Tsky table or harmonics file."""


def _attr(value: Any) -> Any:
    if isinstance(value, (dict, list)):
        return json.dumps(value, sort_keys=True, default=str)
    if value is None:
        return "null"
    return value


def write_tsky(path: str | Path, result: TskyResult) -> Path:
    """Write a :class:`autocal.tsky.result.TskyResult` to HDF5 atomically.

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
    arrays = {
        name: np.asarray(getattr(result, name), dtype=np.float64)
        for name in ("tsky", "freqs", "lsts", "f_above", "f_below")
    }
    labels = {
        "tsky": {"units": "K", "axes": "lst, freq"},
        "freqs": {"units": "Hz"},
        "lsts": {"units": "hour"},
    }
    return _write(path, FORMAT, arrays, labels, result.meta)


def _write(
    path: str | Path,
    fmt: str,
    arrays: dict[str, np.ndarray],
    labels: dict[str, dict[str, str]],
    meta: dict[str, Any],
) -> Path:
    """Write datasets (with attributes ``labels``) and root attributes ``meta`` atomically."""
    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs["format"] = fmt
        h5.attrs["autocal_version"] = __version__
        for name, data in arrays.items():
            h5.create_dataset(name, data=data)
            h5[name].attrs.update(labels.get(name, {}))
        for key, value in meta.items():
            h5.attrs[key] = _attr(value)
    return path


def _read_meta(h5: h5py.File) -> dict[str, Any]:
    meta: dict[str, Any] = {}
    for key, value in h5.attrs.items():
        if key in {"format", "autocal_version"}:
            continue
        if isinstance(value, str) and value[:1] in "{[":
            value = json.loads(value)
        elif isinstance(value, np.generic):
            value = value.item()
        meta[key] = value
    return meta


def read_tsky(path: str | Path) -> TskyResult:
    """Read a Tsky table written by :func:`write_tsky`.

    Raises
    ------
    TskyFileError
        If the file is not an autocal Tsky table.
    """
    path = Path(path)
    try:
        with h5py.File(path, "r") as h5:
            if h5.attrs.get("format") != FORMAT:
                raise TskyFileError(f"{path} is not an autocal Tsky table")
            arrays = {n: h5[n][()] for n in ("tsky", "freqs", "lsts", "f_above", "f_below")}
            meta = _read_meta(h5)
    except OSError as err:
        raise TskyFileError(f"{path} is not a readable HDF5 file: {err}") from err
    return TskyResult(meta=meta, **arrays)


_HARMONICS_ARRAYS = ("coef", "freqs", "sum_all", "sum_below")


def write_harmonics(path: str | Path, harmonics: TskyHarmonics) -> Path:
    """Write :class:`autocal.tsky.result.TskyHarmonics` to HDF5 atomically.

    Parameters
    ----------
    path
        Output file.
    harmonics
        The harmonics.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    arrays = {name: np.asarray(getattr(harmonics, name)) for name in _HARMONICS_ARRAYS}
    labels = {"coef": {"axes": "m, freq"}, "freqs": {"units": "Hz"}}
    return _write(path, HARMONICS_FORMAT, arrays, labels, harmonics.meta)


def read_harmonics(path: str | Path) -> TskyHarmonics:
    """Read Tsky harmonics written by :func:`write_harmonics`.

    Raises
    ------
    TskyFileError
        If the file is not autocal Tsky harmonics or its arrays are inconsistent.
    """
    path = Path(path)
    try:
        with h5py.File(path, "r") as h5:
            if h5.attrs.get("format") != HARMONICS_FORMAT:
                raise TskyFileError(f"{path} is not an autocal Tsky harmonics file")
            arrays = {n: h5[n][()] for n in _HARMONICS_ARRAYS}
            meta = _read_meta(h5)
    except OSError as err:
        raise TskyFileError(f"{path} is not a readable HDF5 file: {err}") from err
    if arrays["coef"].dtype.kind != "c":
        raise TskyFileError(f"{path}: harmonics are not complex")
    try:
        return TskyHarmonics(meta=meta, **arrays)
    except TskyError as err:
        raise TskyFileError(f"{path}: {err}") from err
