"""Calibrate one observation end to end: configuration in, products out.

``files -> scan -> Tsky(nu, LST) -> normal sums, block by block -> Solution -> products``

The data are streamed: each UVH5 file is read in blocks of integrations
(:func:`autocal.io.uvh5_blocks.iter_uvh5_blocks`), each block is turned into normal-equation
sums (:func:`autocal.fit.lsq.accumulate`) and dropped, so memory is bounded by the block,
whatever the length of the night or the size of a file. A file's blocks add up to the
file's partial sums (:func:`compute_partial`), and the files' partials are added in file
order, on this process or mapped over a Dask cluster (:mod:`autocal.pipeline.scaleout`): the
two give the same result bit for bit. The Tsky table is computed once for the night
(and cached) and sliced per block.

Radiometer weights built from the data bias ``G`` by ``-2 / (dnu dt N)`` relative; when
that exceeds :data:`REWEIGHT_THRESHOLD` (simulations with the paper's ``dnu dt = 5000``)
a second pass weights by the first pass's model, otherwise (HERA data: ``dnu dt >~ 2e5``)
the data are read once. The residual waterfall plot needs no second read either: during
the pass the weighted sums of the data and of the model's design columns are kept per
time bin for the shown antennas (:data:`MAX_PLOTTED` antenna-polarisations, at most
:data:`MAX_WATERFALL_ROWS` bins), which give the normalised residuals once solved.

Products are written to a staging folder inside ``out`` and moved into place only when
all of them succeeded, so a failed run never leaves a half-written product set.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from autocal.core.coords import night_epoch
from autocal.core.observation import Observation
from autocal.errors import AutocalError
from autocal.fit.lsq import (
    DEFAULT_INFLATE_ERRORS,
    DEFAULT_PASSES,
    REWEIGHT_THRESHOLD,
    FitModel,
    NormalSums,
    Passes,
    Solution,
    accumulate,
    covariance_scaling,
    design,
    run_passes,
    solve_sums,
    weights_for,
)
from autocal.fit.priors import add_trxr_prior
from autocal.fit.uncertainty import (
    BlockSums,
    base_sums,
    block_edges,
    extended_model,
    mean_vectors,
    separation_summary,
    sums_nbytes,
    total_uncertainty,
)

logger = logging.getLogger(__name__)

__all__ = [
    "REWEIGHT_THRESHOLD",
    "CalibrationConfig",
    "CalibrationResult",
    "PipelineError",
    "calibrate",
    "read",
    "read_summary",
    "run_calibration",
]

#: Antenna-polarisations shown in the residual waterfall.
MAX_PLOTTED = 4
#: Rows (time bins) of the residual waterfall; longer observations are binned in time.
MAX_WATERFALL_ROWS = 512

ProductName = Literal["calh5", "calfits", "hdf5", "png"]
Progress = Callable[[float, str], None]


#: Default 1-sigma (K) of a receiver prior given as a number or a table without sigma_k.
DEFAULT_PRIOR_SIGMA_K = 10.0


class PipelineError(AutocalError):
    """The calibration could not be configured or run."""


class CalibrationConfig(BaseModel):
    """Everything that defines one calibration (shared by the CLI, the API and workers).

    Frequencies in MHz, LSTs in hours, temperatures in kelvin.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    inputs: list[str] = Field(..., min_length=1, description="UVH5 files or Miriad folders")
    input_format: Literal["auto", "uvh5", "miriad", "edges"] = "auto"
    edges_r: Literal["q", "p0"] = Field(
        "q", description="EDGES: fit Q = (p0 - p1)/(p2 - p1) or the raw antenna power p0"
    )
    edges_bin: int = Field(64, ge=1, description="EDGES: native channels averaged per bin")
    sky: str = Field("gsm2008", description="sky model (autocal.sky.models.get_sky spec)")
    beam: str = Field("hera", description="beam (autocal.sky.beams.get_beam spec)")
    tgnd_k: float = Field(300.0, ge=0.0, description="ground temperature")
    nside: int = Field(64, ge=2, description="HEALPix resolution of Tsky (a power of two)")
    model: Literal["constant", "legendre"] = "constant"
    order: int = Field(1, ge=0, le=10, description="Legendre order (model=legendre)")
    weights: Literal["radiometer", "identity"] = "radiometer"
    passes: Passes = Field(
        DEFAULT_PASSES,
        description="radiometer weighting passes (auto: 2 only when data weights bias G)",
    )
    antennas: list[int] | None = None
    pols: list[str] | None = None
    freq_range_mhz: tuple[float, float] | None = None
    lst_range_h: tuple[float, float] | None = None
    products: list[ProductName] = Field(default_factory=lambda: ["calh5", "hdf5", "png"])
    reference: list[str] | None = Field(
        None, description="reference gains (calfits/calh5) to compare |g| with"
    )
    inflate_errors: bool = Field(
        DEFAULT_INFLATE_ERRORS,
        description="radiometer weights: scale each channel's covariance by chi2/dof when it "
        "exceeds 1, so errors cover unmodelled structure (identity weights always scale)",
    )
    trxr_prior: float | str | None = Field(
        None,
        description="receiver-temperature prior: a number (K), a CSV table "
        "freq_mhz,trxr_k[,sigma_k] or a previous solution.h5 of the same antennas/pols",
    )
    trxr_prior_sigma_k: float = Field(
        DEFAULT_PRIOR_SIGMA_K,
        gt=0.0,
        description="1-sigma (K) of a number prior and of a table without sigma_k",
    )

    @model_validator(mode="after")
    def _check(self) -> CalibrationConfig:
        check_ranges(self.freq_range_mhz, self.lst_range_h)
        check_prior_spec(self.trxr_prior, self.trxr_prior_sigma_k)
        if self.nside & (self.nside - 1):
            raise ValueError(f"nside must be a power of two (got {self.nside})")
        return self


def check_prior_spec(spec: float | str | None, sigma_k: float) -> None:
    """Raise ``ValueError`` for a receiver prior that is not a finite number or a path."""
    if isinstance(spec, bool):
        raise ValueError("trxr_prior must be a number (K) or a path, not a boolean")
    if isinstance(spec, float) and not np.isfinite(spec):
        raise ValueError("trxr_prior must be a finite temperature in K")
    if isinstance(spec, str) and not spec.strip():
        raise ValueError("trxr_prior is empty: give a number in K or a .csv/.h5 path")
    if not np.isfinite(sigma_k):
        raise ValueError("trxr_prior_sigma_k must be finite")


def check_ranges(
    freq_range_mhz: tuple[float, float] | None, lst_range_h: tuple[float, float] | None
) -> None:
    """Raise ``ValueError`` unless the frequency (MHz) and LST (h) selections make sense."""
    if freq_range_mhz is not None:
        lo, hi = freq_range_mhz
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
            raise ValueError("freq_range_mhz must be (low, high) MHz with 0 < low < high")
        if hi > 1e5:
            raise ValueError("freq_range_mhz is in MHz, not Hz")
    if lst_range_h is not None and not all(0 <= v <= 24 for v in lst_range_h):
        raise ValueError("lst_range_h values must be hours within [0, 24]")


@dataclass
class CalibrationResult:
    """What a calibration run produced."""

    solution: Solution
    products: dict[str, str]
    summary: dict[str, Any]
    timings: dict[str, float] = field(default_factory=dict)

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        from autocal.core.reprs import compact_repr

        return compact_repr(self)


# inputs ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Source:
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
        from autocal.io.uvh5_blocks import _meta_of

        return [int(a) for a in _meta_of(self.scanned[0]).auto_ants] if self.scanned else []

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


def _detect(paths: list[Path], fmt: str) -> str:
    from autocal.io.miriad import is_miriad

    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise PipelineError(f"input(s) not found: {missing}")
    if fmt != "auto":
        return fmt
    kinds = {"miriad" if is_miriad(p) else ("edges" if _is_edges(p) else "uvh5") for p in paths}
    if len(kinds) > 1:
        raise PipelineError("inputs mix Miriad folders and UVH5 files: give one format")
    return kinds.pop()


def _is_edges(path: Path) -> bool:
    """Whether a file holds EDGES three-position spectra (ACQ, or autocal's EDGES HDF5)."""
    if path.suffix.lower() == ".acq":
        return True
    try:
        import h5py

        with h5py.File(path, "r") as h5:
            return {"p0", "p1", "p2"} <= set(h5.keys())
    except OSError:
        return False


def _open_edges(paths: list[Path], config: CalibrationConfig, sel: dict[str, Any]) -> _Source:
    from autocal.core.sites import EDGES
    from autocal.io.edges import read_edges_spectra

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
    return _Source("edges", paths, obs.lsts, obs.jds, obs.freqs, obs.pols, obs.site, obs, weights)


def _open_source(config: CalibrationConfig) -> _Source:
    paths = [Path(p).expanduser().absolute() for p in config.inputs]
    kind = _detect(paths, config.input_format)
    sel = _selection(config)
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
    if kind == "edges":
        return _open_edges(paths, config, sel)
    if kind == "uvh5":
        from autocal.io.uvh5 import _lst_mask, scan_uvh5

        files = scan_uvh5(paths)
        kept = [f for f in files if np.any(_lst_mask(f.lsts, sel["lst_range"]))]
        if not kept:
            raise PipelineError(f"no integrations in LST range {config.lst_range_h} h")
        masks = [_lst_mask(f.lsts, sel["lst_range"]) for f in kept]
        freqs = kept[0].freqs
        if sel["freq_range"] is not None:
            lo, hi = sel["freq_range"]
            freqs = freqs[(freqs >= lo) & (freqs <= hi)]
        return _Source(
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
    from autocal.io.miriad import read_miriad

    obs = read_miriad(paths, **sel)  # small legacy data sets: read once and kept
    return _Source("miriad", paths, obs.lsts, obs.jds, obs.freqs, obs.pols, obs.site, obs)


def _memory_source(obs: Observation, config: CalibrationConfig) -> _Source:
    """Return the source of an observation in memory, the configuration's selection applied."""
    sel = _selection(config)
    if any(v is not None for v in sel.values()):
        obs = obs.select(
            antennas=sel["antennas"],
            pols=sel["pols"],
            freq_range=sel["freq_range"],
            lst_range=sel["lst_range"],
        )
    files = [Path(f) for f in obs.meta.get("files") or []]
    return _Source("memory", files, obs.lsts, obs.jds, obs.freqs, obs.pols, obs.site, obs)


def _selection(config: CalibrationConfig) -> dict[str, Any]:
    return {
        "antennas": config.antennas,
        "pols": config.pols,
        "freq_range": None
        if config.freq_range_mhz is None
        else (config.freq_range_mhz[0] * 1e6, config.freq_range_mhz[1] * 1e6),
        "lst_range": config.lst_range_h,
    }


def _beam_pol(pol: str) -> str:
    """Return the beam polarisation of a data polarisation (``xx`` -> ``ee``: x is east)."""
    mapping = {"ee": "ee", "nn": "nn", "xx": "ee", "yy": "nn"}
    if pol not in mapping:
        raise PipelineError(f"polarisation {pol!r} has no power beam: calibrate ee/nn (xx/yy)")
    if pol in ("xx", "yy"):
        logger.info(
            "polarisation %s has no orientation in the file; using beam %s", pol, mapping[pol]
        )
    return mapping[pol]


# per-file partial sums (the unit of work, serial or on a Dask worker) ------------------


@dataclass(frozen=True)
class PartialSpec:
    """What every file's partial sums of one pass need (shared by all tasks of a pass).

    Attributes
    ----------
    model
        The fit model (its LST span covers the whole observation).
    weights
        ``"radiometer"`` or ``"identity"``.
    selection
        Antennas, pols, frequency range (Hz) and LST range (hours) to read.
    nshow
        Antennas (the first of the selection) whose residual waterfall is kept.
    bin_size
        Integrations per waterfall row.
    block_size
        Integrations per read block (``None``: automatic, see
        :data:`autocal.io.uvh5.BLOCK_SAMPLES`).
    coeffs
        ``(Nant, Npol, Nfreq, nparam)`` the previous pass's solution: radiometer
        weights then use its model instead of the data (``None`` in the first pass).
    edges
        Integration indices (of the whole observation) that split it into the time
        blocks of the total uncertainty (:func:`autocal.fit.uncertainty.block_edges`): the
        partial then holds one set of sums of the extended model
        (:func:`autocal.fit.uncertainty.extended_model`) per block it overlaps. ``None``:
        one set of sums of ``model``.
    """

    model: FitModel
    weights: str
    selection: dict[str, Any]
    nshow: int
    bin_size: int
    block_size: int | None = None
    coeffs: np.ndarray | None = None
    edges: tuple[int, ...] | None = None


@dataclass(frozen=True)
class FileTask:
    """One file of the observation (or the whole in-memory observation).

    Attributes
    ----------
    index
        Position of the file in time order.
    file
        The scanned UVH5 file (``None`` for an in-memory observation).
    offset
        Index of the file's first selected integration in the observation.
    lsts
        The file's selected LSTs (hours), as scanned.
    tsky
        ``(Npol, Ntime_file, Nfreq)`` model Tsky of the file's integrations.
    observation
        In-memory data (Miriad, EDGES) instead of a file.
    weights
        Inverse variances of in-memory data whose format defines them (EDGES).
    """

    index: int
    file: Any
    offset: int
    lsts: np.ndarray
    tsky: np.ndarray
    observation: Observation | None = None
    weights: np.ndarray | None = None


@dataclass
class FilePartial:
    """A file's normal sums and the by-products of reading it once.

    Attributes
    ----------
    index
        The task's index.
    sums
        The file's normal sums (its read blocks added in order); ``None`` with time blocks.
    blocks
        With ``PartialSpec.edges``: ``{block: sums of the fitted model}`` for the time
        blocks the file overlaps; else ``None``.
    extended
        With ``PartialSpec.edges``: the file's sums of the extended model
        (:func:`autocal.fit.uncertainty.extended_model`); else ``None``.
    waterfall
        ``(Nshow, Npol, Nbins_file, Nfreq, nparam + 2)`` per waterfall row: the sums
        over its integrations of ``w R``, ``w`` and ``w a_m`` (``a`` the design columns).
    bin0
        Waterfall row of ``waterfall[:, :, 0]``.
    ntime
        Integrations read.
    antennas, antenna_names
        The selected antennas.
    checksums
        ``{path: sha256}`` of the inputs read.
    bt_min
        Smallest positive ``dnu dt N`` of the usable samples (``inf`` when none).
    stats
        :class:`autocal.io.uvh5_blocks.ReadStats` counters.
    seconds
        Wall time spent on the file.
    """

    index: int
    sums: NormalSums | None
    waterfall: np.ndarray
    bin0: int
    ntime: int
    antennas: np.ndarray
    antenna_names: tuple[str, ...]
    checksums: dict[str, str]
    bt_min: float
    stats: dict[str, int]
    seconds: float
    blocks: dict[int, NormalSums] | None = None
    extended: NormalSums | None = None


def compute_partial(
    spec: PartialSpec, task: FileTask, tick: Callable[[int], None] | None = None
) -> FilePartial:
    """Read one file block by block and return its partial normal sums.

    This is the unit of work of the serial run and of a Dask worker: both add the
    blocks of a file in order, so the partial is the same wherever it is computed.

    Parameters
    ----------
    spec
        The pass's settings.
    task
        The file.
    tick
        Called with the number of integrations after each block (progress).

    Returns
    -------
    FilePartial
        The file's sums, waterfall sums, checksums and read counters.

    Raises
    ------
    PipelineError
        If the file's LSTs changed since the scan, it yields a different number of
        integrations, or radiometer weights lack channel widths / times / nsamples.
    """
    from autocal.io.uvh5_blocks import ReadStats, iter_uvh5_blocks

    started = time.perf_counter()
    stats = ReadStats()
    sel = spec.selection
    if task.observation is not None:
        obs = task.observation
        if sel.get("antennas") is not None:
            obs = obs.select(antennas=sel["antennas"])
        chunks: Iterator[Observation] = iter([obs])
    else:
        chunks = iter_uvh5_blocks(  # each block is used up before the next is asked for
            task.file, **sel, block_size=spec.block_size, stats=stats, reuse_buffers=True
        )
    ntot = task.lsts.size
    bin0 = task.offset // spec.bin_size
    nbins = (task.offset + ntot - 1) // spec.bin_size - bin0 + 1
    sums: NormalSums | None = None
    blocks: dict[int, NormalSums] = {}
    acc_model = spec.model if spec.edges is None else extended_model(spec.model)
    waterfall: np.ndarray | None = None
    checksums: dict[str, str] = {}
    antennas: np.ndarray | None = None
    names: tuple[str, ...] = ()
    bt_min = np.inf
    offset = 0
    for chunk in chunks:
        nt = chunk.ntime
        window = slice(offset, offset + nt)
        if offset + nt > ntot or not np.allclose(chunk.lsts, task.lsts[window], atol=1e-6):
            raise PipelineError(f"{chunk.meta.get('files')}: LSTs changed between scan and read")
        if antennas is None:
            antennas, names = chunk.antennas, chunk.antenna_names
            nshow = min(spec.nshow, chunk.nant)
            waterfall = np.zeros(
                (nshow, chunk.data.shape[1], nbins, chunk.nfreq, spec.model.nparam + 2)
            )
        checksums.update(chunk.meta.get("sha256", {}))
        tsky = task.tsky[:, window]
        weights: str | np.ndarray = spec.weights
        bt = None
        if spec.weights == "radiometer":  # dnu dt N (Observation.bandwidth_time, one pass)
            bt = _bandwidth_time(chunk)
        if task.weights is not None and spec.weights == "radiometer":
            weights, bt = task.weights[:, :, window], None
        if bt is not None:
            # a (Ntime, Nfreq) bt is checked where any antenna-pol is unflagged (the same
            # result as broadcasting it to the block, 30x faster)
            used = ~chunk.flags if bt.ndim == 4 else ~chunk.flags.all(axis=(0, 1))
            if np.any((bt <= 0) & used):
                raise PipelineError(
                    f"{chunk.meta.get('files')}: radiometer weights need positive channel "
                    "width, integration time and nsamples; use weights='identity'"
                )
            bt_min = min(bt_min, float(np.min(bt, where=used, initial=np.inf)))
        reference = None
        if spec.coeffs is not None:
            pred = np.einsum("pftm,apfm->aptf", design(spec.model, tsky, chunk.lsts), spec.coeffs)
            reference = np.where(np.isfinite(pred) & (pred > 0), pred, chunk.data)
            del pred
        start = task.offset + offset
        for b, sl in _block_slices(spec.edges, start, start + nt):
            part = accumulate(  # added into the running sums of its block, in place
                acc_model,
                chunk.data[:, :, sl],
                tsky[:, sl],
                chunk.lsts[sl],
                flags=chunk.flags[:, :, sl],
                weights=_time_part(weights, sl, nt),
                bandwidth_time=_time_part(bt, sl, nt),
                reference=_time_part(reference, sl, nt),
                into=sums if spec.edges is None else blocks.get(b),
            )
            if spec.edges is None:
                sums = part
            else:
                blocks[b] = part
        assert waterfall is not None
        _add_waterfall(
            waterfall,
            spec,
            chunk,
            tsky,
            weights,
            bt,
            reference,
            task.offset + offset - bin0 * spec.bin_size,
        )
        offset += nt
        del chunk, bt, reference
        if tick is not None:
            tick(nt)
    if (sums is None and not blocks) or antennas is None or waterfall is None:
        raise PipelineError(f"file {task.index}: the selection left no data")
    extended: NormalSums | None = None
    if blocks:  # the extended sums once per file; per block, the fitted model's (copies)
        fitted: dict[int, NormalSums] = {}
        for b in sorted(blocks):
            fitted[b] = base_sums(blocks[b], spec.model)
            extended = blocks[b] if extended is None else _add_into(extended, blocks[b])
        blocks = fitted
    if offset != ntot:
        raise PipelineError(f"file {task.index} yielded {offset} integrations, {ntot} were scanned")
    return FilePartial(
        task.index,
        sums,
        waterfall,
        bin0,
        offset,
        antennas,
        names,
        checksums,
        bt_min,
        stats.as_dict(),
        time.perf_counter() - started,
        blocks or None,
        extended,
    )


def _block_slices(edges: tuple[int, ...] | None, start: int, stop: int) -> list[tuple[int, slice]]:
    """Split integrations ``start:stop`` of the observation at the time-block edges.

    Returns ``(block, slice of the chunk)`` pairs; without edges one pair for the whole
    chunk (block 0).
    """
    if edges is None:
        return [(0, slice(0, stop - start))]
    out = []
    for b in range(len(edges) - 1):
        lo, hi = max(start, edges[b]), min(stop, edges[b + 1])
        if hi > lo:
            out.append((b, slice(lo - start, hi - start)))
    return out


def _time_part(value: Any, sl: slice, ntime: int) -> Any:
    """Slice an array with a time axis of length ``ntime`` (the chunk's) to ``sl``.

    Arrays ``(..., Ntime, Nfreq)`` (per sample, per pol or shared by all); anything else
    (strings, scalars, ``(Nfreq,)`` rows, ``None``) is returned as it is.
    """
    if sl == slice(0, ntime) or not isinstance(value, np.ndarray):
        return value
    if value.ndim >= 2 and value.shape[-2] == ntime:  # (..., Ntime, Nfreq)
        return value[..., sl, :]
    return value


def _bandwidth_time(chunk: Observation) -> np.ndarray:
    """Return ``dnu dt N``: ``(Ntime, Nfreq)`` when ``nsamples`` is uniform, else per sample.

    The shared form spares a chunk-sized array and a third of the fit kernel's reads (which
    reads it as one ``(Nfreq,)`` row when the integration time is uniform too).
    """
    tf = chunk.integration_time[:, None] * chunk.channel_width
    ns = chunk.nsamples
    if ns.size and not np.any(ns != ns.flat[0]):
        return tf * float(ns.flat[0])
    return ns * tf


def _add_into(total: NormalSums, part: NormalSums) -> NormalSums:
    """Add ``part`` into ``total`` in place (the same values as ``total + part``).

    Saves a new set of arrays per file; ``total`` must be owned by the caller.
    """
    total += part
    return total


def _add_waterfall(
    waterfall: np.ndarray,
    spec: PartialSpec,
    chunk: Observation,
    tsky: np.ndarray,
    weights: str | np.ndarray,
    bt: np.ndarray | None,
    reference: np.ndarray | None,
    row0: int,
) -> None:
    """Add a block's weighted sums of the shown antennas into the waterfall rows.

    ``row0`` is the block's first integration counted from the start of the file's
    first waterfall row.
    """
    ns = waterfall.shape[0]
    data = chunk.data[:ns]
    usable = np.isfinite(data) & ~chunk.flags[:ns]
    if isinstance(weights, np.ndarray):
        w = np.where(usable, np.broadcast_to(weights, chunk.data.shape)[:ns], 0.0)
    else:
        w = weights_for(
            weights,
            data,
            usable,
            None if bt is None else bt[:ns] if bt.ndim == 4 else bt,
            None if reference is None else reference[:ns],
        )
    a = design(spec.model, tsky, chunk.lsts)  # (P, F, T, M)
    terms = np.concatenate(
        [
            (w * np.where(usable, data, 0.0))[..., None],
            w[..., None],
            w[..., None] * np.swapaxes(a, 1, 2)[None],
        ],
        axis=-1,
    )  # (S, P, T, F, M + 2)
    rows = (row0 + np.arange(chunk.ntime)) // spec.bin_size
    starts = np.flatnonzero(np.r_[True, np.diff(rows) != 0])
    waterfall[:, :, rows[starts]] += np.add.reduceat(terms, starts, axis=2)


def _fold(
    partials: Iterator[FilePartial],
    ntasks: int,
    waterfall_shape: tuple[int, ...] | None,
    report: Callable[[float, str], None],
    progress_range: tuple[float, float],
) -> tuple[NormalSums | tuple[dict[int, NormalSums], NormalSums], np.ndarray, list[FilePartial]]:
    """Add the files' partials in file order (the same order serially and on Dask).

    Returns the summed normal sums (or, with time blocks, the fitted model's sums of each
    block and the extended model's total), the waterfall sums and the partials' other
    information.
    """
    sums: NormalSums | None = None
    blocks: dict[int, NormalSums] = {}
    waterfall: np.ndarray | None = None
    infos: list[FilePartial] = []
    lo, hi = progress_range
    for i, partial in enumerate(partials):
        if partial.index != i:  # pragma: no cover - executors yield in order
            raise PipelineError(f"partial {partial.index} arrived in place of {i}")
        if partial.blocks is not None:
            for b, part in partial.blocks.items():
                blocks[b] = part if b not in blocks else _add_into(blocks[b], part)
            assert partial.extended is not None
            sums = partial.extended if sums is None else _add_into(sums, partial.extended)
            partial.blocks = partial.extended = None
        else:
            assert partial.sums is not None
            sums = partial.sums if sums is None else _add_into(sums, partial.sums)
        if waterfall is None:
            waterfall = np.zeros(
                (*partial.waterfall.shape[:2], waterfall_shape[0], *partial.waterfall.shape[3:])
                if waterfall_shape is not None
                else partial.waterfall.shape
            )
        nb = partial.waterfall.shape[2]
        waterfall[:, :, partial.bin0 : partial.bin0 + nb] += partial.waterfall
        partial.sums = None  # type: ignore[assignment]  # free the file's arrays
        partial.waterfall = None  # type: ignore[assignment]
        infos.append(partial)
        report(lo + (hi - lo) * (i + 1) / ntasks, f"file {i + 1}/{ntasks} summed")
    if sums is None or waterfall is None:
        raise PipelineError("the selection left no data")
    return (sums if not blocks else (blocks, sums)), waterfall, infos


# the run --------------------------------------------------------------------------------


def run_calibration(
    config: CalibrationConfig,
    out: str | Path | None,
    *,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
    dask_scheduler: str | None = None,
    dask_workers: int | None = None,
    block_size: int | None = None,
    observation: Observation | None = None,
) -> CalibrationResult:
    """Calibrate one observation and write its products (the engine of :func:`calibrate`).

    Parameters
    ----------
    config
        The calibration settings.
    out
        Output folder (created). Products: ``solution.calh5``, ``solution.calfits``,
        ``solution.h5``, ``solution.png``, ``residuals.png`` (as configured) and always
        ``summary.json``. ``None``: nothing is written (no reference comparison then).
    progress
        Called with (fraction done, message).
    should_stop
        Polled between blocks (serial) or files (Dask); returning ``True`` aborts with
        :class:`PipelineError` (the service's cancellation).
    dask_scheduler
        Map the files' partial sums over a Dask cluster: a scheduler address
        (``tcp://host:8786``) or ``"local"`` for a local cluster of ``dask_workers``
        processes. ``None`` (default): in this process. The solution is identical.
    dask_workers
        Workers of the local cluster (default: the number of CPUs).
    block_size
        Integrations read per block (default: about 8 M values per block).
    observation
        Calibrate this observation held in memory instead of reading ``config.inputs``
        (which then only name it); the configuration's selection is applied to it.

    Returns
    -------
    CalibrationResult
        The solution, product paths and a JSON-serialisable summary (with the read
        counters under ``execution``).
    """
    if block_size is not None and int(block_size) < 1:
        raise PipelineError(f"block_size must be at least 1 integration, got {block_size}")
    if out is None and config.reference:
        raise PipelineError("a comparison with reference gains writes products: give out")
    folder = None if out is None else Path(out)
    if dask_scheduler is None:
        return _calibrate(config, folder, progress, should_stop, None, block_size, observation)
    from autocal.pipeline.scaleout import dask_client

    # Connect first: a wrong address fails before any work is done.
    with dask_client(dask_scheduler, dask_workers) as executor:
        return _calibrate(config, folder, progress, should_stop, executor, block_size, observation)


def _calibrate(
    config: CalibrationConfig,
    out: Path | None,
    progress: Progress | None,
    should_stop: Callable[[], bool] | None,
    executor: Any,
    block_size: int | None,
    observation: Observation | None = None,
) -> CalibrationResult:
    """Run the calibration (see :func:`run_calibration`); ``executor``: Dask or None."""
    from autocal import __version__

    def report(fraction: float, message: str) -> None:
        logger.info("%3.0f%% %s", 100 * fraction, message)
        if progress is not None:
            progress(fraction, message)
        if should_stop is not None and should_stop():
            raise PipelineError("cancelled")

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    report(0.0, "scanning inputs")
    source = _open_source(config) if observation is None else _memory_source(observation, config)
    timings["scan_s"] = time.perf_counter() - t0

    pols = tuple(p.lower() for p in (config.pols or source.pols))
    prior = None
    if config.trxr_prior is not None:  # read and checked before any work is done
        from autocal.fit.priors import parse_trxr_prior

        prior = parse_trxr_prior(config.trxr_prior, sigma_k=config.trxr_prior_sigma_k)
        prior.at(source.freqs, antennas=source.antenna_numbers(config.antennas), pols=pols)
    site = source.site
    epoch = night_epoch(source.jds, site.lon_deg)
    report(
        0.05, f"Tsky for {len(pols)} pol(s), {source.freqs.size} channels, {source.lsts.size} LSTs"
    )
    t1 = time.perf_counter()
    tsky_all, tsky_meta = _tsky_per_pol(config.sky, config, source, pols, epoch)
    timings["tsky_s"] = time.perf_counter() - t1

    model = FitModel.for_lsts(
        source.lsts, config.model, 0 if config.model == "constant" else config.order
    )
    t2 = time.perf_counter()
    run = _run_passes(
        config,
        source,
        pols,
        tsky_all,
        model,
        report,
        progress,
        should_stop,
        executor,
        block_size,
    )
    timings["fit_s"] = time.perf_counter() - t2

    scaling = covariance_scaling(config.weights, config.inflate_errors)
    sums = run.sums
    prior_fn = None
    if prior is not None:
        ptrxr, psigma = prior.at(source.freqs, antennas=run.antennas, pols=pols)

        def prior_fn(part: NormalSums, pvg: np.ndarray, pvn: np.ndarray) -> NormalSums:
            return add_trxr_prior(part, pvg, pvn, ptrxr, psigma, scale_covariance=scaling)

        sums = prior_fn(sums, *mean_vectors(model, source.lsts))
    solved = solve_sums(sums, scale_covariance=scaling)
    total = None
    if run.blocks is not None:
        report(0.82, f"total uncertainty ({run.blocks.nblocks} time blocks)")
        total = total_uncertainty(run.blocks, solved, scale_covariance=scaling, prior=prior_fn)
    provenance = {
        "autocal_version": __version__,
        "inputs": run.checksums,
        "input_format": source.kind,
        "sky": tsky_meta.get("sky"),
        "beam": tsky_meta.get("beam"),
        "site": site.describe(),
        "tgnd_K": config.tgnd_k,
        "cmb": tsky_meta.get("cmb"),
        "frame": tsky_meta.get("frame"),
        "epoch_jd": epoch,
        "nside": config.nside,
        "weights": config.weights,
        "passes": run.npass,
        "errors": "covariance x max(1, chi2/dof)"
        if (config.weights == "radiometer" and config.inflate_errors)
        else ("covariance x chi2/dof" if config.weights == "identity" else "covariance"),
        "uncertainty": None if total is None else total.describe(),
        "trxr_prior": None if prior is None else prior.describe(),
        "created_unix": time.time(),
    }
    solution = _solution(
        model,
        run,
        solved,
        source,
        pols,
        {"calibration": config.model_dump(mode="json"), "provenance": provenance},
        total,
    )
    comparison_inputs: dict[str, Any] = {}
    if config.reference:
        report(0.84, "alternative sky models for the comparison's systematics budget")
        comparison_inputs = {
            **_block_trend(run, source, tsky_all, pols),
            "alternatives": _alternative_solutions(
                config, source, pols, model, epoch, scaling, block_size, prior_fn
            ),
        }
    t3 = time.perf_counter()
    products: dict[str, str] = {}
    if out is not None:
        report(0.85, "writing products")
        products = _write_products(config, solution, source, run, out, comparison_inputs)
    separation = separation_summary(solution)
    timings["products_s"] = time.perf_counter() - t3
    timings["total_s"] = time.perf_counter() - t0
    summary = {
        "solution": solution.describe(),
        "separation": separation,
        "comparison": _comparison_summary(products),
        "config": config.model_dump(mode="json"),
        "provenance": provenance,
        "products": products,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "execution": run.execution,
    }
    if out is not None:
        summary_path = out / SUMMARY_NAME
        from autocal.core.files import atomic_path

        with atomic_path(summary_path) as tmp:
            tmp.write_text(json.dumps(summary, indent=2, default=_json_default))
        products["summary"] = str(summary_path)
    report(1.0, "done")
    return CalibrationResult(solution, products, summary, timings)


#: Name of the run's JSON summary in the output folder.
SUMMARY_NAME = "summary.json"


def _config_for(
    inputs: Any, config: CalibrationConfig | None, options: dict[str, Any]
) -> tuple[CalibrationConfig, Observation | None]:
    """Resolve :func:`calibrate`'s arguments into one validated configuration.

    Options not given take :class:`CalibrationConfig`'s defaults (and nothing else's).
    """
    if isinstance(inputs, CalibrationConfig):
        if config is not None:
            raise PipelineError("give the configuration once: as inputs or as config")
        config, inputs = inputs, None
    observation = inputs if isinstance(inputs, Observation) else None
    fields: dict[str, Any] = {} if config is None else config.model_dump()
    unknown = sorted(set(options) - set(CalibrationConfig.model_fields) - {"inputs"})
    if unknown:
        raise PipelineError(
            f"unknown calibration option(s) {unknown}: see autocal.CalibrationConfig "
            "(the options of `autocal calibrate --help`)"
        )
    fields.update(options)
    if observation is not None:
        named = [str(f) for f in observation.meta.get("files") or []]
        fields["inputs"] = named or ["<in-memory observation>"]
    elif inputs is not None:
        paths = [inputs] if isinstance(inputs, str | os.PathLike) else list(inputs)
        fields["inputs"] = [str(p) for p in paths]
    if "inputs" not in fields:
        raise PipelineError("nothing to calibrate: give input files or an Observation")
    return CalibrationConfig(**fields), observation


def calibrate(
    inputs: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | Observation | Any,
    config: CalibrationConfig | None = None,
    *,
    out: str | Path | None = None,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
    dask_scheduler: str | None = None,
    dask_workers: int | None = None,
    block_size: int | None = None,
    **options: Any,
) -> Solution:
    """Calibrate one observation (``autocal.calibrate``; also the CLI's, service's and nightly's).

    The one calibration function: ``autocal calibrate``, the job service's workers and
    nightly runs call it. It reads the files block by block (or takes an observation in
    memory), computes ``Tsky(nu, LST)`` of each polarisation's beam in the frame of the
    data's night, fits ``R = G Tsky + n`` with the total uncertainty and, when ``out`` is
    given, writes the products. Options not given take the defaults of
    :class:`CalibrationConfig`, and of nothing else.

    Parameters
    ----------
    inputs
        A UVH5 file, Miriad folder or EDGES ACQ/HDF5 file, a list of them (consecutive in
        time), an :class:`~autocal.core.observation.Observation` (e.g. from :func:`read`) or a
        whole :class:`CalibrationConfig`.
    config
        Settings to start from (``options`` override them).
    out
        Output folder for the products (``config.products``) and ``summary.json``;
        ``None`` (default) writes nothing.
    progress
        Called with (fraction done, message).
    should_stop
        Polled at checkpoints; returning ``True`` aborts with :class:`PipelineError`.
    dask_scheduler, dask_workers
        Map the files over a Dask cluster (:func:`run_calibration`); the same solution.
    block_size
        Integrations read per block (default: about 8 M values).
    **options
        :class:`CalibrationConfig` fields, e.g. ``antennas=[23]``, ``model="legendre"``,
        ``freq_range_mhz=(110, 190)``.

    Returns
    -------
    Solution
        ``G``, ``n``, ``Trxr``, ``|g|`` with total errors (``sigma_*``) and their
        statistical parts (``sigma_*_stat``), flags; ``config`` holds the resolved
        configuration and provenance. :meth:`Solution.write` writes products later.

    Raises
    ------
    autocal.errors.AutocalError
        Bad input (missing or malformed files, options out of range, an empty
        selection); pydantic's ``ValidationError`` for options of the wrong type.

    Examples
    --------
    >>> import autocal
    >>> sol = autocal.calibrate("zen.2458116.30448.HH.uvh5", antennas=[23])  # doctest: +SKIP
    >>> print(sol)  # doctest: +SKIP
    """
    cfg, observation = _config_for(inputs, config, options)
    result = run_calibration(
        cfg,
        out,
        progress=progress,
        should_stop=should_stop,
        dask_scheduler=dask_scheduler,
        dask_workers=dask_workers,
        block_size=block_size,
        observation=observation,
    )
    return result.solution


def read_summary(out: str | Path) -> dict[str, Any]:
    """Return the ``summary.json`` a calibration wrote into ``out``.

    Its ``products`` map product names to paths, ``summary`` (the file itself) included.

    Raises
    ------
    PipelineError
        If ``out`` holds no calibration summary.
    """
    path = Path(out) / SUMMARY_NAME
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise PipelineError(f"{path}: no readable calibration summary ({err})") from err
    summary["products"] = {**(summary.get("products") or {}), "summary": str(path)}
    return summary


def read(
    paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    *,
    antennas: list[int] | None = None,
    pols: list[str] | None = None,
    freq_range_mhz: tuple[float, float] | None = None,
    lst_range_h: tuple[float, float] | None = None,
    input_format: str | None = None,
    edges_r: str | None = None,
    edges_bin: int | None = None,
) -> Observation:
    """Read the auto-correlations of one observation into memory (``autocal.read``).

    The formats and selections of :func:`calibrate` (UVH5 files, Miriad folders, EDGES
    ACQ/HDF5 spectra; MHz and hours); options not given take :class:`CalibrationConfig`'s
    defaults. For a long night prefer :func:`calibrate` on the files, which streams them.

    Parameters
    ----------
    paths
        Files or folders of one observation, consecutive in time.
    antennas, pols
        Selection (default: all).
    freq_range_mhz, lst_range_h
        Frequency range in MHz and LST range in hours (wraps at 24 h).
    input_format
        ``"auto"``, ``"uvh5"``, ``"miriad"`` or ``"edges"``.
    edges_r, edges_bin
        EDGES: the auto-correlation kind (``"q"`` or ``"p0"``) and native channels per bin.

    Returns
    -------
    Observation
        The data with flags, times, LSTs, frequencies, site and the files' checksums.
    """
    given = {
        "antennas": antennas,
        "pols": pols,
        "freq_range_mhz": freq_range_mhz,
        "lst_range_h": lst_range_h,
        "input_format": input_format,
        "edges_r": edges_r,
        "edges_bin": edges_bin,
    }
    config, _ = _config_for(paths, None, {k: v for k, v in given.items() if v is not None})
    files = [Path(p).expanduser().absolute() for p in config.inputs]
    kind = _detect(files, config.input_format)
    sel = _selection(config)
    if kind == "edges":
        return _open_edges(files, config, sel).observation  # type: ignore[return-value]
    if kind == "miriad":
        from autocal.io.miriad import read_miriad

        return read_miriad(files, **sel)
    from autocal.io.uvh5 import read_uvh5

    return read_uvh5(files, **sel)


def _comparison_summary(products: dict[str, str]) -> dict[str, Any] | None:
    path = products.get("compare_json")
    if path is None:
        return None
    return json.loads(Path(path).read_text())


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


@dataclass
class _Run:
    """What the passes over the data produced."""

    sums: NormalSums
    blocks: BlockSums | None
    waterfall: np.ndarray  # (S, P, Nbins, F, M + 2)
    bin_size: int
    npass: int
    antennas: np.ndarray
    antenna_names: tuple[str, ...]
    checksums: dict[str, str]
    execution: dict[str, Any]


def _run_passes(
    config: CalibrationConfig,
    source: _Source,
    pols: tuple[str, ...],
    tsky_all: np.ndarray,
    model: FitModel,
    report: Callable[[float, str], None],
    progress: Progress | None,
    should_stop: Callable[[], bool] | None,
    executor: Any,
    block_size: int | None,
) -> _Run:
    """Accumulate the normal sums file by file (one or two passes), serially or on Dask."""
    tasks = source.tasks(tsky_all)
    ntime = source.lsts.size
    bin_size = max(1, -(-ntime // MAX_WATERFALL_ROWS))
    nbins = -(-ntime // bin_size)
    nshow = max(1, MAX_PLOTTED // len(pols))
    nbytes = sums_nbytes(
        extended_model(model),
        max(1, len(source.antenna_numbers(config.antennas))),
        len(pols),
        source.freqs.size,
    )
    edges = block_edges(ntime, bytes_per_block=nbytes)
    use_dask = executor is not None and source.kind == "uvh5"
    if executor is not None and not use_dask:
        logger.info("%s input is read whole in this process; Dask is not used", source.kind)
    execution: dict[str, Any] = {
        "executor": "dask" if use_dask else "serial",
        "block_size": block_size or "auto",
        "files": len(tasks),
        "bytes_on_disk": source.disk_bytes(),
    }
    stats_total: dict[str, int] = {}
    client = executor if use_dask else None
    if client is not None:
        execution["dask"] = client.describe()

    def one_pass(
        coeffs: np.ndarray | None, ipass: int, npass: int
    ) -> tuple[tuple[BlockSums, NormalSums, np.ndarray, list[FilePartial]], NormalSums, float]:
        spec = PartialSpec(
            model,
            config.weights,
            _selection(config),
            nshow,
            bin_size,
            block_size,
            coeffs,
            tuple(int(e) for e in edges),
        )
        lo = 0.1 + 0.7 * ipass / npass
        hi = 0.1 + 0.7 * (ipass + 1) / npass
        if client is not None:
            partials = client.map_ordered(compute_partial, spec, tasks)
        else:
            partials = _serial_partials(spec, tasks, ntime, (lo, hi), progress, should_stop)
        folded, waterfall, infos = _fold(partials, len(tasks), (nbins,), report, (lo, hi))
        assert isinstance(folded, tuple)
        per_block, extended = folded
        blocks = BlockSums(
            [per_block[b] for b in range(len(edges) - 1)], model, edges, source.lsts, extended
        )
        for info in infos:
            for key, value in info.stats.items():
                if key == "largest_array":
                    stats_total[key] = max(stats_total.get(key, 0), value)
                else:
                    stats_total[key] = stats_total.get(key, 0) + value
        bt_min = min(info.bt_min for info in infos)
        total = blocks.fitted_total()
        return (blocks, total, waterfall, infos), total, bt_min

    # inverse variances given by the format (EDGES): nothing to re-weight, one pass
    radiometer = config.weights == "radiometer" and source.weights is None
    (blocks, sums, waterfall, infos), npass = run_passes(
        one_pass, passes=config.passes, radiometer=radiometer
    )
    if client is not None:
        execution["dask"]["worker_peak_rss_bytes"] = client.worker_peak_rss()
    assert sums is not None and waterfall is not None and infos
    checksums: dict[str, str] = {}
    for info in infos:
        checksums.update(info.checksums)
    nant = len(infos[0].antennas)
    execution["samples_per_pass"] = int(ntime * source.freqs.size * len(pols) * nant)
    execution["passes"] = npass
    execution["io"] = stats_total
    execution["file_seconds"] = [round(info.seconds, 3) for info in infos]
    return _Run(
        sums,
        blocks,
        waterfall,
        bin_size,
        npass,
        infos[0].antennas,
        infos[0].antenna_names,
        checksums,
        execution,
    )


def _serial_partials(
    spec: PartialSpec,
    tasks: list[FileTask],
    ntime: int,
    progress_range: tuple[float, float],
    progress: Progress | None,
    should_stop: Callable[[], bool] | None,
) -> Iterator[FilePartial]:
    """Compute the files' partials in this process, reporting block by block."""
    done = 0
    lo, hi = progress_range

    def tick(nt: int) -> None:
        nonlocal done
        done += nt
        if progress is not None:
            progress(lo + (hi - lo) * done / max(ntime, 1), f"{done}/{ntime} integrations")
        if should_stop is not None and should_stop():
            raise PipelineError("cancelled")

    for task in tasks:
        yield compute_partial(spec, task, tick)


def _waterfall_residuals(
    solution: Solution, run: _Run, config: CalibrationConfig, lsts: np.ndarray
) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Normalised residuals of the shown antenna-pols: labels, (K, Nbins, F), bin LSTs.

    A row's residual is ``sum w (R - model) / sqrt(sum w)`` over its integrations: the
    per-sample normalised residuals ``(R - model) sqrt(w)`` when a row is one
    integration, and a unit-variance average of them when rows are binned.
    """
    wf = run.waterfall
    ns = wf.shape[0]
    coeffs = solution.coeffs[:ns]  # (S, P, F, M)
    model_sum = np.einsum("spbfm,spfm->spbf", wf[..., 2:], coeffs)
    wsum = wf[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        resid = np.where(wsum > 0, (wf[..., 0] - model_sum) / np.sqrt(wsum), np.nan)
        if config.weights == "identity":
            resid = resid / np.sqrt(solution.reduced_chi2[:ns])[:, :, None, :]
    ants = solution.antennas[:ns].tolist()
    labels = [f"ant {a} {p}" for a in ants for p in solution.pols]
    centre = np.minimum(np.arange(wf.shape[2]) * run.bin_size + run.bin_size // 2, lsts.size - 1)
    return labels, resid.reshape(-1, *resid.shape[2:]), lsts[centre]


def _solution(
    model: FitModel,
    run: _Run,
    solved: dict[str, np.ndarray],
    source: _Source,
    pols: tuple[str, ...],
    config: dict[str, Any],
    total: Any = None,
) -> Solution:
    """Build the solution of a run's sums and their solve on the observation's axes."""
    return Solution.from_solved(
        model,
        run.sums,
        solved,
        antennas=run.antennas,
        pols=pols,
        freqs=source.freqs,
        lsts=source.lsts,
        jds=source.jds,
        antenna_names=run.antenna_names,
        config=config,
        total=total,
    )


#: Sky models whose fits the comparison's systematics budget sets beside the main one.
ALTERNATIVE_SKIES = (
    "gsm2008",
    "powerlaw:gsm2008@408:-2.5",
    "powerlaw:gsm2008@408:-2.55",
)


def _tsky_per_pol(
    sky: str, config: CalibrationConfig, source: _Source, pols: tuple[str, ...], epoch: float
) -> tuple[np.ndarray, dict[str, Any]]:
    """Return Tsky ``(Npol, Ntime, Nfreq)`` of the observation's grid and the last meta.

    Filled pol by pol into one array (no stacked copy), each pol with its own beam.
    """
    from autocal.tsky.engine import compute_tsky

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
            pol=_beam_pol(pol),
        )
        if tsky_all is None:
            tsky_all = np.empty((len(pols), *result.tsky.shape))
        tsky_all[ip] = result.tsky
        meta = result.meta
        del result
    assert tsky_all is not None
    return tsky_all, meta


def _alternative_solutions(
    config: CalibrationConfig,
    source: _Source,
    pols: tuple[str, ...],
    model: FitModel,
    epoch: float,
    scaling: bool | str,
    block_size: int | None,
    prior_fn: Callable[..., NormalSums] | None = None,
) -> dict[str, Solution]:
    """Fit the data again with the other sky models of :data:`ALTERNATIVE_SKIES`.

    One pass over the data each (data-derived weights), with the main fit's receiver prior
    (``prior_fn``) if any; only for a comparison with reference gains, whose systematics
    budget reports the spread of the ratio over them.
    """
    out: dict[str, Solution] = {}
    for sky in ALTERNATIVE_SKIES:
        if sky == config.sky:
            continue
        tsky = _tsky_per_pol(sky, config, source, pols, epoch)[0]
        alt = config.model_copy(update={"sky": sky, "passes": 1})
        run = _run_passes(
            alt, source, pols, tsky, model, lambda f, m: None, None, None, None, block_size
        )
        sums = run.sums
        if prior_fn is not None:
            sums = prior_fn(sums, *mean_vectors(model, source.lsts))
        solved = solve_sums(sums, scale_covariance=scaling)
        out[sky] = _solution(
            model, run, solved, source, pols, {"calibration": alt.model_dump(mode="json")}
        )
    return out


def _block_trend(
    run: _Run, source: _Source, tsky_all: np.ndarray, pols: tuple[str, ...]
) -> dict[str, Any]:
    """Return the raw autos' trend over the span from the time blocks' sums.

    A block's weighted mean power is its sums' ``sum w R / sum w``; the first and the last
    block are the ends of :func:`autocal.compare.gains.auto_trend` (10 blocks: 10 % each).
    """
    from autocal.compare.gains import auto_trend

    blocks = run.blocks
    if blocks is None or blocks.nblocks < 2:
        return {}
    nb = blocks.model.nbasis
    power = []
    for part in blocks.blocks:
        with np.errstate(invalid="ignore", divide="ignore"):
            power.append(part.aty[..., nb] / part.ata[..., nb, nb])
    edges = blocks.edges
    spans = [slice(int(edges[b]), int(edges[b + 1])) for b in range(blocks.nblocks)]
    jds = np.array([source.jds[sl].mean() for sl in spans])
    tsky = np.stack([tsky_all[:, sl].mean(axis=1) for sl in spans], axis=1)  # (P, B, F)
    return auto_trend(
        np.stack(power, axis=2),  # (A, P, B, F)
        jds,
        run.antennas,
        list(pols),
        tsky=tsky,
        end_fraction=1.0 / blocks.nblocks,
    )


#: File name of each product of a solution (``CalibrationConfig.products``).
PRODUCT_FILES: dict[str, str] = {
    "calh5": "solution.calh5",
    "calfits": "solution.calfits",
    "hdf5": "solution.h5",
    "png": "solution.png",
}


def write_solution_products(
    solution: Solution,
    out: str | Path,
    products: Sequence[str],
    *,
    overwrite: bool = False,
) -> dict[str, str]:
    """Write a solution's products into ``out`` (:data:`PRODUCT_FILES`; each atomically).

    The writers of ``autocal calibrate`` and :meth:`autocal.fit.lsq.Solution.write`:
    calh5/calfits through pyuvdata ``UVCal`` (:mod:`autocal.io.calsol`), the HDF5 product
    (:func:`autocal.io.products.write_solution`) and the solution plot.

    Parameters
    ----------
    solution
        The solution.
    out
        Folder (created).
    products
        Any of :data:`PRODUCT_FILES`' names.
    overwrite
        Replace existing files; otherwise an existing one is a ``FileExistsError``.

    Returns
    -------
    dict
        Product name -> path written.
    """
    unknown = sorted(set(products) - set(PRODUCT_FILES))
    if unknown:
        raise PipelineError(f"unknown product(s) {unknown}: use {sorted(PRODUCT_FILES)}")
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    written: dict[str, str] = {}
    for name in PRODUCT_FILES:  # a fixed order, whatever the order asked for
        if name not in products:
            continue
        path = folder / PRODUCT_FILES[name]
        if name == "calh5":
            from autocal.io.calsol import write_calh5

            write_calh5(solution, path, overwrite=overwrite)
        elif name == "calfits":
            from autocal.io.calsol import write_calfits

            write_calfits(solution, path, overwrite=overwrite)
        elif name == "hdf5":
            from autocal.io.products import write_solution

            write_solution(solution, path, overwrite=overwrite)
        else:
            if path.exists() and not overwrite:
                raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
            from autocal.plots import plot_solution

            plot_solution(solution, path)
        written[name] = str(path)
    return written


def _write_products(
    config: CalibrationConfig,
    solution: Solution,
    source: _Source,
    run: _Run,
    out: Path,
    comparison_inputs: dict[str, Any] | None = None,
) -> dict[str, str]:
    """Write every product into a staging folder, then move them into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    staging = out / f".staging-{os.getpid()}-{time.time_ns()}"
    staging.mkdir()
    names = dict(PRODUCT_FILES)
    written: dict[str, str] = {}
    try:
        write_solution_products(solution, staging, config.products)
        if "png" in config.products:
            from autocal.plots import plot_residuals

            labels, resid, bin_lsts = _waterfall_residuals(solution, run, config, source.lsts)
            plot_residuals(labels, resid, solution.freqs, bin_lsts, staging / "residuals.png")
            names["residuals_png"] = "residuals.png"
        if config.reference:
            from autocal.compare.gains import compare, write_comparison
            from autocal.io.calsol import read_reference_gains

            reference = read_reference_gains(config.reference)
            comparison = compare(solution, reference, **(comparison_inputs or {}))
            paths = write_comparison(comparison, staging)
            names.update({f"compare_{k}": Path(v).name for k, v in paths.items()})
        for item in sorted(staging.iterdir()):
            target = out / item.name
            os.replace(item, target)
            key = next((k for k, v in names.items() if v == item.name), item.name)
            written[key] = str(target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return written
