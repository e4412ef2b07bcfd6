"""The comparison's products: ``compare.json``, ``compare.h5`` and ``compare.png``.

:func:`write_comparison` writes the summary as strict JSON (:func:`json_safe`), the arrays
as HDF5 (format ``autocal-compare-1``) and the figure
(:func:`~autocal.compare.figures.plot_comparison`), each atomically.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal import __version__
from autocal.compare.comparison import Comparison
from autocal.compare.figures import plot_comparison
from autocal.compare.names import OUTPUT_NAMES
from autocal.core.files import atomic_path

logger = logging.getLogger(__name__)


def json_safe(value: Any) -> Any:
    """Return a structure made strict-JSON safe (NaN/inf -> None, numpy -> Python).

    Parameters
    ----------
    value
        Nested dicts, lists, tuples, arrays and scalars.

    Returns
    -------
    object
        The same structure of Python scalars, lists and dicts (other objects as ``str``).
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def write_comparison(
    comparison: Comparison, out_dir: str | Path, *, overwrite: bool = False
) -> dict[str, Path]:
    """Write the JSON summary, the PNG plot and the arrays (HDF5) into ``out_dir``.

    Parameters
    ----------
    comparison
        The comparison.
    out_dir
        Output folder (created if missing).
    overwrite
        Replace existing output files.

    Returns
    -------
    dict
        ``{"json": path, "png": path, "h5": path}``.

    Raises
    ------
    FileExistsError
        If an output file exists and ``overwrite`` is false.
    """
    out_dir = Path(out_dir)
    paths = {k: out_dir / v for k, v in OUTPUT_NAMES.items()}
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{', '.join(existing)} exist(s); pass overwrite to replace")
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = json_safe({"autocal_version": __version__, **comparison.summary})
    with atomic_path(paths["json"]) as tmp:
        tmp.write_text(json.dumps(summary, indent=2, sort_keys=False) + "\n")
    with atomic_path(paths["h5"]) as tmp:
        _write_arrays(comparison, summary, tmp)
    plot_comparison(comparison, paths["png"])
    logger.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return paths


def _write_arrays(c: Comparison, summary: dict[str, Any], path: Path) -> None:
    """Write the comparison's arrays and JSON summary into the HDF5 file ``path``."""
    with h5py.File(path, "w") as h5:
        h5.attrs["format"] = "autocal-compare-1"
        h5.attrs["mode"] = c.mode
        h5.attrs["quantity"] = c.quantity
        h5.attrs["summary"] = json.dumps(summary)
        h5["antennas"] = c.antennas
        h5.create_dataset("pols", data=np.array(c.pols, dtype=object), dtype=h5py.string_dtype())
        h5["freqs"] = c.freqs
        for name in (
            "auto",
            "sigma_auto",
            "reference",
            "sigma_reference",
            "ratio",
            "sigma_ratio",
            "valid",
        ):
            h5[name] = getattr(c, name)
        for name in (
            "jy_per_k",
            "omega",
            "delays",
            "delay_amplitude",
            "reference_jds",
            "reference_series",
        ):
            value = getattr(c, name)
            if value is not None:
                h5[name] = value
        if c.auto_series:
            group = h5.create_group("auto_series")
            for (ant, pol), (jds, values) in c.auto_series.items():
                sub = group.create_group(f"{ant}_{pol}")
                sub["jds"] = np.asarray(jds, dtype=np.float64)
                sub["power_over_mean"] = np.asarray(values, dtype=np.float64)
