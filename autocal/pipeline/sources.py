"""The inputs of one calibration: files found, scanned and described as a :class:`Source`.

UVH5 files are only scanned here (their axes, not their data: the data are streamed later,
file by file, by :func:`autocal.pipeline.partials.compute_partial`); small inputs (Miriad
folders, EDGES spectra) and observations already in memory are held whole. The model sky
temperature of the source's grid (:func:`tsky_per_pol`) is computed once per night.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal.core.observation import Observation
from autocal.core.sites import EDGES
from autocal.io.edges_read import read_edges_spectra
from autocal.io.miriad import is_miriad, read_miriad
from autocal.io.uvh5_meta import file_meta_of, lst_mask, scan_uvh5, select_pols
from autocal.pipeline.config import CalibrationConfig, PipelineError, read_selection
from autocal.pipeline.partials import FileTask
from autocal.tsky.compute import compute_tsky

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Source:
    """The files of one observation, in time order, with their concatenated axes."""

    kind: str
    files: list[Path]
    lsts: np.ndarray
    jds: np.ndarray
    freqs: np.ndarray
    pols: tuple[str, ...]
    site: Any
    observation: Observation | None = None  # small inputs read whole (Miriad, EDGES)
    weights: np.ndarray | None = None  # inverse variances when the format defines them
    scanned: tuple[Any, ...] = ()  # UVH5File per file (uvh5)
    ntimes: tuple[int, ...] = ()  # selected integrations per file (uvh5)

    def antenna_numbers(self, antennas: list[int] | None) -> list[int]:
        """Return the antennas a selection keeps, in the order they are read."""
        if antennas is not None:
            return [int(a) for a in antennas]
        if self.observation is not None:
            return [int(a) for a in self.observation.antennas]
        return [int(a) for a in file_meta_of(self.scanned[0]).auto_ants] if self.scanned else []

    def pol_names(self, pols: Sequence[str] | None) -> tuple[str, ...]:
        """Return the selected polarisations as the data name them (lower case).

        A UVH5 file's polarisation asked for by an alias (``xx`` of an ``ee``/``nn`` file
        whose x feed points east) is the file's name, as the reader selects it
        (:func:`autocal.io.uvh5_meta.select_pols`), so that the solution, its products and
        the service's history name one feed one way.
        """
        if not pols:
            return tuple(p.lower() for p in self.pols)
        if self.kind == "uvh5" and self.scanned:
            meta = file_meta_of(self.scanned[0])
            return tuple(meta.pol_names[i].lower() for i in select_pols(meta, list(pols)))
        return tuple(p.lower() for p in pols)

    def tasks(self, tsky_all: np.ndarray) -> list[FileTask]:
        """One task per file (uvh5) or one for the whole in-memory observation."""
        if self.kind != "uvh5":
            assert self.observation is not None
            return [FileTask(0, None, 0, self.lsts, tsky_all, self.observation, self.weights)]
        tasks = []
        offset = 0
        for index, (file, nt) in enumerate(zip(self.scanned, self.ntimes, strict=True)):
            window = slice(offset, offset + nt)
            tasks.append(FileTask(index, file, offset, self.lsts[window], tsky_all[:, window]))
            offset += nt
        return tasks

    def disk_bytes(self) -> int:
        """Bytes of the input files on disk (UVH5 only; 0 otherwise)."""
        return sum(Path(f).stat().st_size for f in self.files) if self.kind == "uvh5" else 0


def detect_format(paths: list[Path], fmt: str) -> str:
    """Return the format of the inputs: ``fmt``, or for ``"auto"`` the one they hold.

    Raises
    ------
    PipelineError
        If an input is missing or the inputs mix formats.
    """
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise PipelineError(f"input(s) not found: {missing}")
    if fmt != "auto":
        return fmt
    kinds = {"miriad" if is_miriad(p) else ("edges" if is_edges(p) else "uvh5") for p in paths}
    if len(kinds) > 1:
        raise PipelineError("inputs mix Miriad folders and UVH5 files: give one format")
    return kinds.pop()


def is_edges(path: Path) -> bool:
    """Whether a file holds EDGES three-position spectra (ACQ, or autocal's EDGES HDF5)."""
    if path.suffix.lower() == ".acq":
        return True
    try:
        with h5py.File(path, "r") as h5:
            return {"p0", "p1", "p2"} <= set(h5.keys())
    except (OSError, RuntimeError):
        return False


def open_edges(paths: list[Path], config: CalibrationConfig, sel: dict[str, Any]) -> Source:
    """Read EDGES spectra whole, with the inverse variances of the fitted ratio as weights."""
    spectra = read_edges_spectra(
        paths, freq_range=sel["freq_range"], bin_factor=config.edges_bin
    ).sorted()
    obs = spectra.to_observation(r=config.edges_r, site=EDGES)
    if sel["lst_range"] is not None:
        obs = obs.select(lst_range=sel["lst_range"])
        keep = np.isin(spectra.jds, obs.jds)
    else:
        keep = np.ones(spectra.jds.size, bool)
    channels = np.isin(spectra.freqs, obs.freqs)  # to_observation drops channels < 1 MHz
    with np.errstate(divide="ignore", invalid="ignore"):
        weights = 1.0 / spectra.variance(config.edges_r)[np.ix_(keep, channels)]
    weights = np.where(np.isfinite(weights), weights, 0.0)[None, None]
    return Source("edges", paths, obs.lsts, obs.jds, obs.freqs, obs.pols, obs.site, obs, weights)


def open_source(config: CalibrationConfig) -> Source:
    """Find and scan (UVH5) or read (Miriad, EDGES) the configuration's inputs."""
    paths = [Path(p).expanduser().absolute() for p in config.inputs]
    kind = detect_format(paths, config.input_format)
    sel = read_selection(config)
    _warn_edges_options(config, kind)
    if kind == "edges":
        return open_edges(paths, config, sel)
    if kind == "uvh5":
        return _open_uvh5(paths, config, sel)
    obs = read_miriad(paths, **sel)  # small legacy data sets: read once and kept
    return Source("miriad", paths, obs.lsts, obs.jds, obs.freqs, obs.pols, obs.site, obs)


def _warn_edges_options(config: CalibrationConfig, kind: str) -> None:
    """Log that options of EDGES spectra set away from their defaults do nothing here."""
    defaults = CalibrationConfig.model_fields
    edges_options = [
        f"{name}={getattr(config, name)!r}"
        for name in ("edges_r", "edges_bin")
        if getattr(config, name) != defaults[name].default
    ]
    if kind != "edges" and edges_options:
        logger.warning(
            "%s: options of EDGES spectra, ignored for %s input", ", ".join(edges_options), kind
        )


def _open_uvh5(paths: list[Path], config: CalibrationConfig, sel: dict[str, Any]) -> Source:
    """Scan UVH5 files: the ones with integrations in the LST range, their selected axes."""
    files = scan_uvh5(paths)
    kept = [f for f in files if np.any(lst_mask(f.lsts, sel["lst_range"]))]
    if not kept:
        spans = ", ".join(f"{f.lsts.min():.3f}-{f.lsts.max():.3f}" for f in files[:4])
        raise PipelineError(
            f"no integrations in LST range {config.lst_range_h} h: the data cover LST "
            f"{spans}{' ...' if len(files) > 4 else ''} h; choose LSTs inside them"
        )
    masks = [lst_mask(f.lsts, sel["lst_range"]) for f in kept]
    freqs = kept[0].freqs
    if sel["freq_range"] is not None:
        lo, hi = sel["freq_range"]
        freqs = freqs[(freqs >= lo) & (freqs <= hi)]
    check_band(freqs, kept[0].freqs, config.freq_range_mhz)
    return Source(
        "uvh5",
        [f.path for f in kept],
        np.concatenate([f.lsts[m] for f, m in zip(kept, masks, strict=True)]),
        np.concatenate([f.jds[m] for f, m in zip(kept, masks, strict=True)]),
        freqs,
        kept[0].pols,
        kept[0].site,
        scanned=tuple(kept),
        ntimes=tuple(int(m.sum()) for m in masks),
    )


def check_band(
    selected: np.ndarray, band: np.ndarray, freq_range_mhz: tuple[float, float] | None
) -> None:
    """Raise :class:`PipelineError` naming the data's band when a selection keeps no channel.

    Parameters
    ----------
    selected
        Frequencies (Hz) the selection keeps.
    band
        Every frequency (Hz) of the data.
    freq_range_mhz
        The selection (MHz).
    """
    if selected.size or band.size == 0:
        return
    lo, hi = freq_range_mhz if freq_range_mhz is not None else (np.nan, np.nan)
    raise PipelineError(
        f"frequency range {lo:g}-{hi:g} MHz keeps no channel: the data cover "
        f"{band.min() / 1e6:.3f}-{band.max() / 1e6:.3f} MHz ({band.size} channels); "
        "choose a range inside that band"
    )


def memory_source(obs: Observation, config: CalibrationConfig) -> Source:
    """Return the source of an observation in memory, the configuration's selection applied."""
    sel = read_selection(config)
    if any(v is not None for v in sel.values()):
        obs = obs.select(
            antennas=sel["antennas"],
            pols=sel["pols"],
            freq_range=sel["freq_range"],
            lst_range=sel["lst_range"],
        )
    files = [Path(f) for f in obs.meta.get("files") or []]
    return Source("memory", files, obs.lsts, obs.jds, obs.freqs, obs.pols, obs.site, obs)


def beam_pol(pol: str) -> str:
    """Return the beam polarisation of a data polarisation (``xx`` -> ``ee``: x is east)."""
    mapping = {"ee": "ee", "nn": "nn", "xx": "ee", "yy": "nn"}
    if pol not in mapping:
        raise PipelineError(f"polarisation {pol!r} has no power beam: calibrate ee/nn (xx/yy)")
    if pol in ("xx", "yy"):
        logger.info(
            "polarisation %s has no orientation in the file; using beam %s", pol, mapping[pol]
        )
    return mapping[pol]


def tsky_per_pol(
    sky: str, config: CalibrationConfig, source: Source, pols: tuple[str, ...], epoch: float
) -> tuple[np.ndarray, dict[str, Any]]:
    """Return Tsky ``(Npol, Ntime, Nfreq)`` of the observation's grid and the last meta.

    Filled pol by pol into one array (no stacked copy), each pol with its own beam.
    """
    tsky_all: np.ndarray | None = None
    meta: dict[str, Any] = {}
    for ip, pol in enumerate(pols):
        result = compute_tsky(
            sky,
            config.beam,
            source.site,
            source.freqs,
            source.lsts,
            tgnd=config.tgnd_k,
            nside=config.nside,
            epoch=epoch,
            pol=beam_pol(pol),
        )
        if tsky_all is None:
            tsky_all = np.empty((len(pols), *result.tsky.shape))
        tsky_all[ip] = result.tsky
        meta = result.meta
        del result
    assert tsky_all is not None
    return tsky_all, meta
