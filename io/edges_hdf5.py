"""EDGES spectra in autocal's HDF5 layout, written and read with h5py.

:func:`write_edges_hdf5` keeps :class:`~autocal.io.edges_spectra.EdgesSpectra` (native or
binned) in one HDF5 file; :func:`read_edges_hdf5` reads it back.

HDF5 layout (``autocal-edges-spectra-1``, :data:`HDF5_FORMAT`)
--------------------------------------------------------------
Datasets ``p0``, ``p1``, ``p2`` (Ntime, Nfreq; raw linear power), ``freqs`` (Nfreq; Hz,
channel centres), ``channel_width`` (Nfreq; Hz), ``jds`` (Ntime; UTC Julian dates of the
cycles), ``integration_time`` (Ntime; s per switch position) and optional ``aux/adcmax``,
``aux/adcmin``, ``aux/data_drops`` (Ntime, 3). Root attributes: ``format``,
``telescope_name``, ``switch_positions`` (JSON), ``time_scale`` ("utc"), ``bin_factor``,
``native_channel_width_hz``, ``integration_time_source``, ``header`` (JSON of the ACQ
header), ``files`` and ``sha256`` (JSON provenance of the source files), ``history``.
Written atomically.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import h5py

from autocal import __version__
from autocal.core.files import atomic_path, file_checksum
from autocal.io.edges_spectra import (
    NATIVE_DF_HZ,
    SWITCH_POSITIONS,
    EdgesFormatError,
    EdgesSpectra,
    jsonable,
)

logger = logging.getLogger(__name__)

#: Format tag of the HDF5 form.
HDF5_FORMAT = "autocal-edges-spectra-1"


def write_edges_hdf5(path: str | Path, spectra: EdgesSpectra, history: str = "") -> Path:
    """Write spectra to the autocal EDGES HDF5 layout (see the module doc), atomically.

    Parameters
    ----------
    path
        Output file.
    spectra
        The spectra (native or binned).
    history
        Free text appended to the provenance.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    path = Path(path)
    meta = spectra.meta
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        for name in ("p0", "p1", "p2"):
            h5.create_dataset(name, data=getattr(spectra, name))
        h5.create_dataset("freqs", data=spectra.freqs)
        h5.create_dataset("channel_width", data=spectra.channel_width)
        h5.create_dataset("jds", data=spectra.jds)
        h5.create_dataset("integration_time", data=spectra.integration_time)
        for key, value in spectra.aux.items():
            h5.create_dataset(f"aux/{key}", data=value)
        h5["freqs"].attrs["unit"] = "Hz"
        h5["channel_width"].attrs["unit"] = "Hz"
        h5["jds"].attrs["unit"] = "Julian date (UTC)"
        h5["integration_time"].attrs["unit"] = "s per switch position"
        attrs = h5.attrs
        attrs["format"] = HDF5_FORMAT
        attrs["telescope_name"] = "EDGES"
        attrs["switch_positions"] = json.dumps(list(SWITCH_POSITIONS))
        attrs["time_scale"] = "utc"
        attrs["bin_factor"] = int(meta.get("bin_factor", 1))
        attrs["native_channel_width_hz"] = float(meta.get("native_channel_width_hz", NATIVE_DF_HZ))
        attrs["header"] = json.dumps(jsonable(meta.get("header", {})), sort_keys=True)
        attrs["files"] = json.dumps(list(meta.get("files", [])))
        attrs["sha256"] = json.dumps(dict(meta.get("sha256", {})), sort_keys=True)
        attrs["integration_time_source"] = str(meta.get("integration_time_source", "unknown"))
        attrs["history"] = "\n".join(
            s
            for s in (str(meta.get("history", "")), f"written by autocal {__version__}", history)
            if s
        )
    logger.info("wrote %s: %d cycle(s) x %d channel(s)", path, spectra.ntime, spectra.nfreq)
    return path


def read_edges_hdf5(
    path: str | Path,
    *,
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
) -> EdgesSpectra:
    """Read spectra written by :func:`write_edges_hdf5`.

    Parameters
    ----------
    path
        The HDF5 file.
    freq_range, bin_factor
        As for :func:`~autocal.io.edges_acq.read_acq_spectra` (applied to the stored channels).

    Returns
    -------
    EdgesSpectra
        The stored spectra; ``meta["files"]`` names the HDF5 file, ``meta["parents"]``
        the files it was made from.

    Raises
    ------
    EdgesFormatError
        If the file is not HDF5, not in this layout, or damaged.
    """
    path = Path(path)
    arrays, aux, attrs = _read_stored(path)
    resolved = str(path.resolve())

    def text(key: str, default: str) -> str:
        v = attrs.get(key, default)
        return v.decode() if isinstance(v, bytes) else str(v)

    try:
        spec = EdgesSpectra(
            p0=arrays["p0"],
            p1=arrays["p1"],
            p2=arrays["p2"],
            freqs=arrays["freqs"],
            jds=arrays["jds"],
            channel_width=arrays["channel_width"],
            integration_time=arrays["integration_time"],
            aux=aux,
            meta={
                "source": "edges-hdf5",
                "files": [resolved],
                "sha256": {resolved: file_checksum(path)},
                "parents": json.loads(text("files", "[]")),
                "parent_sha256": json.loads(text("sha256", "{}")),
                "header": json.loads(text("header", "{}")),
                "bin_factor": int(attrs.get("bin_factor", 1)),
                "native_channel_width_hz": float(
                    attrs.get("native_channel_width_hz", NATIVE_DF_HZ)
                ),
                "integration_time_source": text("integration_time_source", "unknown"),
                "history": text("history", ""),
            },
        )
    except ValueError as exc:
        raise EdgesFormatError(f"{path}: inconsistent EDGES HDF5 contents ({exc})") from exc
    if freq_range is not None or bin_factor != 1:
        spec = spec.select(freq_range, bin_factor)
    return spec


def _read_stored(path: Path) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """Return the data sets, ``aux`` data sets and root attributes of an autocal EDGES file."""
    if not path.exists():
        raise FileNotFoundError(f"EDGES HDF5 file {path} does not exist")
    try:
        with h5py.File(path, "r") as h5:
            fmt = h5.attrs.get("format", "")
            fmt = fmt.decode() if isinstance(fmt, bytes) else str(fmt)
            if fmt != HDF5_FORMAT:
                raise EdgesFormatError(
                    f"{path} is HDF5 but not an autocal EDGES spectra file (format "
                    f"{fmt!r}, expected {HDF5_FORMAT!r}); write it with write_edges_hdf5"
                )
            arrays = {
                k: h5[k][()]
                for k in ("p0", "p1", "p2", "freqs", "channel_width", "jds", "integration_time")
            }
            aux = {k: h5["aux"][k][()] for k in h5["aux"]} if "aux" in h5 else {}
            attrs = {k: h5.attrs[k] for k in h5.attrs}
    except EdgesFormatError:
        raise
    except (OSError, KeyError, ValueError) as exc:
        raise EdgesFormatError(
            f"{path} is not a readable autocal EDGES HDF5 file ({type(exc).__name__}: "
            f"{str(exc)[:200]}); re-create it with write_edges_hdf5 or re-copy it"
        ) from exc
    return arrays, aux, attrs
