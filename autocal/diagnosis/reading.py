"""Reading the autos of UVH5 files into one observation, a block of integrations at a time.

:func:`read_observation` gives the values :func:`autocal.io.uvh5.read_uvh5` returns for the
same selections, but copies the blocks of :func:`autocal.io.uvh5.iter_uvh5` straight into
the observation's arrays, so a whole HERA file is read with one copy of its data.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.errors import DiagnoseError
from autocal.io.uvh5 import iter_uvh5
from autocal.io.uvh5_meta import scan_uvh5

logger = logging.getLogger(__name__)


def read_observation(
    paths: list[Path],
    *,
    antennas: list[int] | None = None,
    pols: list[str] | None = None,
    freq_range: tuple[float, float] | None = None,
    lst_range: tuple[float, float] | None = None,
    check: Callable[[tuple[int, int, int, int]], None] | None = None,
) -> Observation:
    """Read the autos of UVH5 files into one observation, a block of integrations at a time.

    The values are those :func:`autocal.io.uvh5.read_uvh5` returns for the same selections,
    but the blocks (:func:`autocal.io.uvh5.iter_uvh5`) are copied straight into the
    observation's arrays: :func:`~autocal.io.uvh5.read_uvh5` holds several copies of the
    data while it joins them (a peak of 8.0 GB for a whole HERA file, whose observation is
    1.9 GB). ``nsamples`` uniform over the observation are kept as one number.

    Parameters
    ----------
    paths
        The UVH5 files.
    antennas, pols, freq_range, lst_range
        As for :func:`~autocal.io.uvh5.read_uvh5` (``freq_range`` in Hz).
    check
        Called with ``(Nant, Npol, Ntime, Nfreq)`` (``Ntime``: every integration of the
        files, before the LST selection) once the first block is read, before the
        observation's arrays are allocated (:func:`autocal.diagnosis.run.check_memory`).

    Returns
    -------
    autocal.core.observation.Observation
        The observation.
    """
    files = scan_uvh5(paths)
    arrays = _ObservationArrays(ntime_max=sum(f.jds.size for f in files), check=check)
    for block in iter_uvh5(
        paths,
        antennas=antennas,
        pols=pols,
        freq_range=freq_range,
        lst_range=lst_range,
        block_size=0,
    ):
        arrays.add(block)
    if arrays.first is None:
        spans = ", ".join(f"{f.lsts[0]:.3f}-{f.lsts[-1]:.3f}" for f in files[:4])  # in time
        raise DiagnoseError(
            f"no integrations in LST range {tuple(lst_range or ())} h: the data cover LST "
            f"{spans}{' ...' if len(files) > 4 else ''} h; choose LSTs inside them"
        )
    obs = arrays.observation()
    logger.info(
        "read %d file(s): %d antennas, pols %s, %d times, %d channels",
        len(arrays.used),
        obs.nant,
        ",".join(obs.pols),
        obs.ntime,
        obs.nfreq,
    )
    return obs


@dataclass(eq=False)
class _ObservationArrays:
    """The observation's arrays, filled a block of integrations at a time.

    Allocated for every integration of the files (``ntime_max``) when the first block is
    read (after ``check``); ``nsamples`` stays one number while it is uniform.
    """

    ntime_max: int
    check: Callable[[tuple[int, int, int, int]], None] | None = None
    first: Any = None
    data: np.ndarray | None = None
    flags: np.ndarray | None = None
    nsamples: np.ndarray | None = None
    uniform: float | None = None
    lsts: list[np.ndarray] = field(default_factory=list)
    jds: list[np.ndarray] = field(default_factory=list)
    tint: list[np.ndarray] = field(default_factory=list)
    sha: dict[str, str] = field(default_factory=dict)
    used: list[str] = field(default_factory=list)
    starts: list[int] = field(default_factory=list)
    t: int = 0

    def add(self, block: Any) -> None:
        """Copy a block (:func:`autocal.io.uvh5.iter_uvh5`) into the arrays."""
        nant, npol, nt, nfreq = block.data.shape
        t = self.t
        if self.first is None:
            self.first = block
            if self.check is not None:
                self.check((nant, npol, self.ntime_max, nfreq))
            self.data = np.empty((nant, npol, self.ntime_max, nfreq))
            self.flags = np.empty(self.data.shape, bool)
            self.uniform = float(block.nsamples.flat[0])
        assert self.data is not None and self.flags is not None
        self.data[:, :, t : t + nt] = block.data
        self.flags[:, :, t : t + nt] = block.flags
        if self.nsamples is None and not np.all(block.nsamples == self.uniform):
            self.nsamples = np.empty(self.data.shape)
            self.nsamples[:, :, :t] = self.uniform
        if self.nsamples is not None:
            self.nsamples[:, :, t : t + nt] = block.nsamples
        self.lsts.append(block.lsts)
        self.jds.append(block.jds)
        self.tint.append(block.integration_time)
        self.sha.update(block.meta.get("sha256", {}))
        new = [f for f in block.meta.get("files", []) if f not in self.used]
        if new or not self.starts:
            self.starts.append(t)  # a file's first integration (the flagging's stretches)
        self.used += new
        self.t = t + nt

    def observation(self) -> Observation:
        """Return the observation of the blocks added (only the integrations read)."""
        first, data, flags, nsamples, t = self.first, self.data, self.flags, self.nsamples, self.t
        assert first is not None and data is not None and flags is not None
        if t < self.ntime_max:  # an LST selection: keep only what was read
            data = np.ascontiguousarray(data[:, :, :t])
            flags = np.ascontiguousarray(flags[:, :, :t])
            nsamples = None if nsamples is None else np.ascontiguousarray(nsamples[:, :, :t])
        return Observation(
            data=data,
            freqs=first.freqs,
            lsts=np.concatenate(self.lsts),
            jds=np.concatenate(self.jds),
            antennas=first.antennas,
            pols=first.pols,
            site=first.site,
            flags=flags,
            channel_width=first.channel_width,
            integration_time=np.concatenate(self.tint),
            nsamples=self.uniform if nsamples is None else nsamples,
            antenna_names=first.antenna_names,
            telescope_name=first.telescope_name,
            meta={
                "source": "uvh5",
                "files": self.used,
                "sha256": self.sha,
                "file_starts": list(self.starts),
                **{k: first.meta[k] for k in ("x_orientation", "vis_units") if k in first.meta},
            },
        )
