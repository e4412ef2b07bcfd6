"""A UVH5 file of auto-correlations written in parts, in memory bounded by a part.

:class:`UVH5AutosWriter` writes the header pyuvdata makes
(:func:`~autocal.io.uvh5_uvdata.build_uvdata`, so it is what
:func:`autocal.io.uvh5.write_uvh5` writes), then the data sets a block of integrations at
a time through h5py, with a chosen data type (:data:`WRITE_DTYPES`), chunks and
compression. Night-size test files and the benchmarks' files are written with it.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal.core.observation import ObservationError
from autocal.core.sites import Site
from autocal.io.pyuvdata_helpers import warnings_to_log
from autocal.io.uvh5_uvdata import build_uvdata, file_history, header_keywords

logger = logging.getLogger(__name__)


def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.INFO)


#: Data types :class:`UVH5AutosWriter` can store: complex64, complex128, and the HERA
#: correlator's int32 compound type (fields ``r``, ``i``; values rounded to integers).
WRITE_DTYPES: dict[str, Any] = {
    "c8": np.dtype("c8"),
    "c16": np.dtype("c16"),
    "int32": np.dtype([("r", "<i4"), ("i", "<i4")]),
}


class UVH5AutosWriter:
    """Write a UVH5 file of auto-correlations in parts (memory bounded by a part).

    The header comes from pyuvdata (:meth:`pyuvdata.UVData.initialize_uvh5_file` on a
    metadata-only UVData, so it is what :func:`write_uvh5` writes); the three data sets
    ``Data/visdata``, ``Data/flags`` and ``Data/nsamples`` of shape ``(Nblts, Nfreqs,
    Npols)`` are created with chunks of one integration (all antennas) by
    ``chunk_channels`` channels by one polarisation, HDF5 byte shuffle and LZF or gzip
    compression (flags and nsamples with the same filter; LZF when the data are not
    compressed), which pyuvdata and h5py read without plugins. The baseline-time axis
    is time-major (antennas fastest), as HERA's correlator writes it.

    Use as a context manager: the file is written under a temporary name and renamed
    onto ``path`` only when every integration was written and the block exits cleanly.

    Parameters
    ----------
    path
        Output file.
    freqs, channel_width
        ``(Nfreq,)`` Hz.
    jds, lsts, integration_time
        ``(Ntime,)`` Julian dates, LSTs (hours) and integration times (s).
    antennas
        Antenna numbers.
    pols
        Polarisation names (``ee``/``nn`` or ``xx``/``yy``).
    site
        Telescope site.
    telescope_name
        ``"HERA"`` takes pyuvdata's HERA telescope metadata (all 350 antennas).
    antenna_names
        Names when the telescope is not HERA (default ``ant<N>``).
    history, extra_keywords
        Header history and extra keywords.
    dtype
        ``"c8"`` (default), ``"c16"`` or ``"int32"`` (HERA correlator compound type).
    compression
        ``"lzf"`` (default), ``"gzip"`` or ``None``.
    compression_level
        gzip level (1-9; 1 decodes fastest and compresses noise-like data nearly as
        well as higher levels).
    shuffle
        Apply HDF5's byte-shuffle filter before compressing (default True: the zero
        imaginary parts and the slowly varying high bytes then compress to little).
    chunk_channels
        Channels per chunk.
    overwrite
        Replace an existing file.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        freqs: np.ndarray,
        channel_width: np.ndarray | float,
        jds: np.ndarray,
        lsts: np.ndarray,
        integration_time: np.ndarray | float,
        antennas: Sequence[int],
        pols: Sequence[str],
        site: Site,
        telescope_name: str = "HERA",
        antenna_names: Sequence[str] | None = None,
        history: str = "",
        extra_keywords: dict[str, Any] | None = None,
        dtype: str = "c8",
        compression: str | None = "lzf",
        compression_level: int = 1,
        shuffle: bool = True,
        chunk_channels: int = 256,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path} exists; pass overwrite=True to replace it")
        if dtype not in WRITE_DTYPES:
            raise ObservationError(f"unknown UVH5 data type {dtype!r}: use {list(WRITE_DTYPES)}")
        if compression not in ("lzf", "gzip", None):
            raise ObservationError(f"unknown compression {compression!r}: use lzf, gzip or None")
        self.freqs = np.atleast_1d(np.asarray(freqs, np.float64))
        self.jds = np.atleast_1d(np.asarray(jds, np.float64))
        self.antennas = np.atleast_1d(np.asarray(antennas, np.int64))
        self.pols = tuple(str(p).lower() for p in pols)
        nfreq, ntime, nant = self.freqs.size, self.jds.size, self.antennas.size
        width = np.broadcast_to(np.asarray(channel_width, np.float64), (nfreq,))
        tint = np.broadcast_to(np.asarray(integration_time, np.float64), (ntime,))
        if np.any(width <= 0) or np.any(tint <= 0):
            raise ObservationError("channel widths and integration times must be positive")
        if ntime > 1 and np.any(np.diff(self.jds) <= 0):
            raise ObservationError("JDs must be strictly increasing to write UVH5")
        if np.unique(self.antennas).size != nant:
            raise ObservationError("antenna numbers are not unique")
        names = tuple(antenna_names or (f"ant{a}" for a in self.antennas))
        self.uv = build_uvdata(
            self.path.name,
            freqs=self.freqs,
            pols=self.pols,
            jds=self.jds,
            lsts=np.asarray(lsts, np.float64),
            antennas=self.antennas,
            antenna_names=names,
            site=site,
            telescope_name=telescope_name,
            integration_time=np.asarray(tint),
            channel_width=np.asarray(width),
            history=file_history({}, history, writer="UVH5AutosWriter"),
            extra_keywords=header_keywords({}, extra_keywords),
        )
        self.dtype = dtype
        self._options = {
            "compression": compression,
            "compression_opts": int(compression_level) if compression == "gzip" else None,
            "shuffle": bool(shuffle and compression is not None),
        }
        self._chunks = (nant, max(1, min(int(chunk_channels), nfreq)), 1)
        self._written = np.zeros(ntime, bool)
        self._tmp: Path | None = None
        self._h5: Any = None

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """``(Nant, Npol, Ntime, Nfreq)`` of the file."""
        return (self.antennas.size, len(self.pols), self.jds.size, self.freqs.size)

    def __enter__(self) -> UVH5AutosWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.{time.time_ns()}.tmp")
        self._tmp = tmp
        with _warnings_to_log(f"initialising {self.path.name}"):
            self.uv.initialize_uvh5_file(str(tmp), clobber=False)
        nblt, nfreq, npol = self.uv.Nblts, self.freqs.size, len(self.pols)
        h5 = h5py.File(tmp, "r+")
        try:
            del h5["Data"]  # re-create the data sets with our chunks and filters
            group = h5.create_group("Data")
            shape = (nblt, nfreq, npol)
            group.create_dataset(
                "visdata",
                shape,
                dtype=WRITE_DTYPES[self.dtype],
                chunks=self._chunks,
                **self._options,
            )
            aux = {**self._options, "compression": self._options["compression"] or "lzf"}
            group.create_dataset("flags", shape, dtype="b1", chunks=self._chunks, **aux)
            group.create_dataset("nsamples", shape, dtype="f4", chunks=self._chunks, **aux)
        except Exception:
            h5.close()
            tmp.unlink(missing_ok=True)
            raise
        self._h5 = h5
        return self

    def write(
        self,
        start: int,
        data: np.ndarray,
        flags: np.ndarray | None = None,
        nsamples: np.ndarray | float = 1.0,
    ) -> None:
        """Write integrations ``start .. start + Ntime_part - 1``.

        Parameters
        ----------
        start
            Index of the first integration of the part.
        data
            ``(Nant, Npol, Ntime_part, Nfreq)`` real auto-correlation power. Non-finite
            values are stored as 0 and flagged.
        flags
            Boolean flags like ``data`` (default none).
        nsamples
            Sample counts, broadcastable to ``data``.
        """
        if self._h5 is None:
            raise RuntimeError("use UVH5AutosWriter as a context manager (with ... as w:)")
        data = np.asarray(data)
        nant, npol, ntime, nfreq = self.shape
        if data.ndim != 4 or data.shape[:2] != (nant, npol) or data.shape[3] != nfreq:
            raise ObservationError(
                f"part has shape {data.shape}; expected (Nant, Npol, Ntime, Nfreq) with "
                f"Nant={nant}, Npol={npol}, Nfreq={nfreq}"
            )
        nt = data.shape[2]
        if not 0 <= start <= ntime - nt:
            raise ObservationError(
                f"integrations {start}..{start + nt - 1} are outside 0..{ntime - 1}"
            )
        bad = ~np.isfinite(data)
        flag = bad if flags is None else (np.broadcast_to(flags, data.shape) | bad)
        real = np.where(bad, 0.0, data) if np.any(bad) else data

        def to_blt(arr: np.ndarray) -> np.ndarray:
            return arr.transpose(2, 0, 3, 1).reshape(nt * nant, nfreq, npol)

        rows = slice(start * nant, (start + nt) * nant)
        out = np.zeros((nt * nant, nfreq, npol), WRITE_DTYPES[self.dtype])
        if self.dtype == "int32":
            values = np.rint(to_blt(real))
            if np.any(np.abs(values) > np.iinfo(np.int32).max):
                raise ObservationError("data exceed the int32 range of the correlator type")
            out["r"] = values
        else:
            out.real = to_blt(real)
        group = self._h5["Data"]
        group["visdata"][rows] = out
        del out
        group["flags"][rows] = to_blt(np.asarray(flag, bool))
        group["nsamples"][rows] = to_blt(
            np.broadcast_to(np.asarray(nsamples, np.float32), data.shape)
        )
        self._written[start : start + nt] = True

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        h5, tmp = self._h5, self._tmp
        self._h5 = None
        if h5 is not None:
            h5.close()
        if tmp is None:
            return
        if exc_type is not None:
            tmp.unlink(missing_ok=True)
            return
        if not np.all(self._written):
            tmp.unlink(missing_ok=True)
            missing = np.flatnonzero(~self._written)
            raise ObservationError(
                f"{self.path.name}: {missing.size} integration(s) were never written "
                f"(first {missing[0]}); the file was not created"
            )
        os.replace(tmp, self.path)
        logger.info("wrote %s: %s (ant, pol, time, chan) in parts", self.path, self.shape)
