"""Calibrate one observation end to end: configuration in, products out.

``files -> scan -> Tsky(nu, LST) -> normal sums, file by file -> Solution -> products``

The data are streamed: each file's autos are read, turned into normal-equation sums
(:func:`autocal.fit.accumulate`) and dropped, so memory does not grow with the length of
the night. Radiometer weights built from the data bias ``G`` by ``-2 / (dnu dt N)``
relative; when that exceeds :data:`REWEIGHT_THRESHOLD` (simulations with the paper's
``dnu dt = 5000``) a second pass weights by the first pass's model, otherwise (real HERA
data: ``dnu dt ~ 1e6``) the data are read once. The residual waterfall plot reads the
autos of at most :data:`MAX_PLOTTED` antenna-polarisations once more.

Products are written to a staging folder inside ``out`` and moved into place only when
all of them succeeded, so a failed run never leaves a half-written product set.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from autocal.fit import (
    FitModel,
    NormalSums,
    Solution,
    accumulate,
    design,
    solve_sums,
    weights_for,
)
from autocal.observation import Observation

logger = logging.getLogger(__name__)

#: Relative bias of data-derived radiometer weights above which a second pass is made.
REWEIGHT_THRESHOLD = 1e-5
#: Antenna-polarisations shown in the residual waterfall.
MAX_PLOTTED = 4

ProductName = Literal["calh5", "calfits", "hdf5", "png"]
Progress = Callable[[float, str], None]


class PipelineError(ValueError):
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
    sky: str = Field("gsm2008", description="sky model (autocal.sky.get_sky spec)")
    beam: str = Field("hera", description="beam (autocal.beams.get_beam spec)")
    tgnd_k: float = Field(300.0, ge=0.0, description="ground temperature")
    nside: int = Field(64, description="HEALPix resolution of the Tsky computation")
    model: Literal["constant", "legendre"] = "constant"
    order: int = Field(1, ge=0, le=10, description="Legendre order (model=legendre)")
    weights: Literal["radiometer", "identity"] = "radiometer"
    passes: Literal["auto", 1, 2] = Field(
        "auto", description="radiometer weighting passes (auto: 2 only when data weights bias G)"
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
        True,
        description="radiometer weights: scale each channel's covariance by chi2/dof when it "
        "exceeds 1, so errors cover unmodelled structure (identity weights always scale)",
    )

    @model_validator(mode="after")
    def _check(self) -> CalibrationConfig:
        if self.freq_range_mhz is not None:
            lo, hi = self.freq_range_mhz
            if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
                raise ValueError("freq_range_mhz must be (low, high) MHz with 0 < low < high")
            if hi > 1e5:
                raise ValueError("freq_range_mhz is in MHz, not Hz")
        if self.lst_range_h is not None and not all(0 <= v <= 24 for v in self.lst_range_h):
            raise ValueError("lst_range_h values must be hours within [0, 24]")
        return self


@dataclass
class CalibrationResult:
    """What a calibration run produced."""

    solution: Solution
    products: dict[str, str]
    summary: dict[str, Any]
    timings: dict[str, float] = field(default_factory=dict)


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

    def chunks(self, **selection: Any) -> Iterator[Observation]:
        if self.kind == "uvh5":
            from autocal.io.uvh5 import iter_uvh5

            yield from iter_uvh5(self.files, **selection)
        else:  # small inputs read whole at the scan (Miriad, EDGES): reuse, never re-read
            assert self.observation is not None
            obs = self.observation
            if selection.get("antennas") is not None:
                obs = obs.select(antennas=selection["antennas"])
            yield obs


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
    from autocal.io.edges import read_edges_spectra
    from autocal.sites import EDGES

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
        )
    from autocal.io.miriad import read_miriad

    obs = read_miriad(paths, **sel)  # small legacy data sets: read once and kept
    return _Source("miriad", paths, obs.lsts, obs.jds, obs.freqs, obs.pols, obs.site, obs)


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


# the run --------------------------------------------------------------------------------


def run_calibration(
    config: CalibrationConfig,
    out: str | Path,
    *,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> CalibrationResult:
    """Calibrate one observation and write its products.

    Parameters
    ----------
    config
        The calibration settings.
    out
        Output folder (created). Products: ``solution.calh5``, ``solution.calfits``,
        ``solution.h5``, ``solution.png``, ``residuals.png`` (as configured) and always
        ``summary.json``.
    progress
        Called with (fraction done, message).
    should_stop
        Polled between files; returning ``True`` aborts with :class:`PipelineError`
        (the service's cancellation).

    Returns
    -------
    CalibrationResult
        The solution, product paths and a JSON-serialisable summary.
    """
    from autocal import __version__
    from autocal.tsky import compute_tsky

    def report(fraction: float, message: str) -> None:
        logger.info("%3.0f%% %s", 100 * fraction, message)
        if progress is not None:
            progress(fraction, message)
        if should_stop is not None and should_stop():
            raise PipelineError("cancelled")

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    report(0.0, "scanning inputs")
    source = _open_source(config)
    timings["scan_s"] = time.perf_counter() - t0

    pols = tuple(p.lower() for p in (config.pols or source.pols))
    sel = _selection(config)
    epoch = float(np.mean(source.jds))
    report(
        0.05, f"Tsky for {len(pols)} pol(s), {source.freqs.size} channels, {source.lsts.size} LSTs"
    )
    t1 = time.perf_counter()
    site = source.site
    tsky_tables = {}
    tsky_meta: dict[str, Any] = {}
    for pol in pols:
        result = compute_tsky(
            config.sky,
            config.beam,
            site,
            source.freqs,
            source.lsts,
            tgnd=config.tgnd_k,
            nside=config.nside,
            epoch=epoch,
            pol=_beam_pol(pol),
        )
        tsky_tables[pol] = result.tsky
        tsky_meta = result.meta
    tsky_all = np.stack([tsky_tables[p] for p in pols])  # (P, T, F)
    timings["tsky_s"] = time.perf_counter() - t1

    model = FitModel.for_lsts(
        source.lsts, config.model, 0 if config.model == "constant" else config.order
    )
    t2 = time.perf_counter()
    sums, first_obs, npass = _stream_fit(config, source, sel, pols, tsky_all, model, report)
    timings["fit_s"] = time.perf_counter() - t2

    if config.weights == "identity":
        scaling: bool | str = True
    else:
        scaling = "inflate" if config.inflate_errors else False
    solved = solve_sums(sums, scale_covariance=scaling)
    provenance = {
        "autocal_version": __version__,
        "inputs": first_obs.meta.get("sha256_all", {}),
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
        "passes": npass,
        "errors": "covariance x max(1, chi2/dof)"
        if (config.weights == "radiometer" and config.inflate_errors)
        else ("covariance x chi2/dof" if config.weights == "identity" else "covariance"),
        "created_unix": time.time(),
    }
    solution = Solution.from_solved(
        model,
        sums,
        solved,
        antennas=first_obs.antennas,
        pols=pols,
        freqs=source.freqs,
        lsts=source.lsts,
        jds=source.jds,
        antenna_names=first_obs.antenna_names,
        config={"calibration": config.model_dump(mode="json"), "provenance": provenance},
    )
    report(0.85, "writing products")
    t3 = time.perf_counter()
    products = _write_products(config, solution, source, sel, pols, tsky_all, Path(out))
    timings["products_s"] = time.perf_counter() - t3
    timings["total_s"] = time.perf_counter() - t0
    summary = {
        "solution": solution.describe(),
        "comparison": _comparison_summary(Path(out), products),
        "config": config.model_dump(mode="json"),
        "provenance": provenance,
        "products": products,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
    }
    summary_path = Path(out) / "summary.json"
    from autocal.io.tskyfile import atomic_path

    with atomic_path(summary_path) as tmp:
        tmp.write_text(json.dumps(summary, indent=2, default=_json_default))
    products["summary"] = str(summary_path)
    report(1.0, "done")
    return CalibrationResult(solution, products, summary, timings)


def _comparison_summary(out: Path, products: dict[str, str]) -> dict[str, Any] | None:
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


def _stream_fit(
    config: CalibrationConfig,
    source: _Source,
    sel: dict[str, Any],
    pols: tuple[str, ...],
    tsky_all: np.ndarray,
    model: FitModel,
    report: Callable[[float, str], None],
) -> tuple[NormalSums, Observation, int]:
    """Accumulate the normal sums file by file (one or two passes)."""
    npass = 1 if config.weights != "radiometer" or config.passes == 1 else 2
    coeffs = None
    sums: NormalSums | None = None
    first_obs: Observation | None = None
    checksums: dict[str, str] = {}
    nfiles = max(len(source.files), 1)
    ipass = 0
    while ipass < npass:
        sums = None
        offset = 0
        for ichunk, chunk in enumerate(source.chunks(**sel)):
            if first_obs is None:
                first_obs = chunk
            checksums.update(chunk.meta.get("sha256", {}))
            nt = chunk.ntime
            tsky = tsky_all[:, offset : offset + nt]
            if not np.allclose(chunk.lsts, source.lsts[offset : offset + nt], atol=1e-6):
                raise PipelineError("file LSTs changed between the scan and the read")
            weights: str | np.ndarray = config.weights
            bt = chunk.bandwidth_time() if config.weights == "radiometer" else None
            if source.weights is not None and config.weights == "radiometer":
                weights, bt, npass = source.weights[:, :, offset : offset + nt], None, 1
            if bt is not None and not np.all(bt[~chunk.flags] > 0):
                raise PipelineError(
                    f"{chunk.meta.get('files')}: radiometer weights need positive channel "
                    "width, integration time and nsamples; use weights='identity'"
                )
            reference = None
            if coeffs is not None:
                pred = np.einsum("pftm,apfm->aptf", design(model, tsky, chunk.lsts), coeffs)
                reference = np.where(np.isfinite(pred) & (pred > 0), pred, chunk.data)
            part = accumulate(
                model,
                chunk.data,
                tsky,
                chunk.lsts,
                flags=chunk.flags,
                weights=weights,
                bandwidth_time=bt,
                reference=reference,
            )
            sums = part if sums is None else sums + part
            offset += nt
            done = (ipass + (ichunk + 1) / nfiles) / npass
            report(0.1 + 0.7 * done, f"pass {ipass + 1}/{npass}: {chunk.meta.get('files')}")
            if ipass == 0 and ichunk == 0 and config.passes == "auto" and npass == 2:
                bias = 2.0 / np.min(bt[bt > 0]) if bt is not None and np.any(bt > 0) else 0.0
                if bias < REWEIGHT_THRESHOLD:
                    npass = 1
        if sums is None or first_obs is None:
            raise PipelineError("the selection left no data")
        if offset != source.lsts.size:
            raise PipelineError("the files yielded a different number of integrations than scanned")
        if ipass + 1 < npass:
            coeffs = solve_sums(sums)["coeffs"]
        ipass += 1
    assert sums is not None and first_obs is not None
    first_obs.meta["sha256_all"] = checksums
    return sums, first_obs, npass


def _residual_waterfalls(
    solution: Solution,
    config: CalibrationConfig,
    source: _Source,
    sel: dict[str, Any],
    tsky_all: np.ndarray,
) -> tuple[list[str], np.ndarray]:
    """Normalised residuals of up to MAX_PLOTTED antenna-pols: labels, (K, T, F)."""
    ants = solution.antennas[: max(1, MAX_PLOTTED // len(solution.pols))].tolist()
    rows: list[np.ndarray] = []
    offset = 0
    for chunk in source.chunks(**{**sel, "antennas": ants}):
        nt = chunk.ntime
        tsky = tsky_all[:, offset : offset + nt]
        sub = replace(
            solution,
            antennas=np.asarray(ants),
            coeffs=solution.coeffs[: len(ants)],
            cov=solution.cov[: len(ants)],
            chi2=solution.chi2[: len(ants)],
            dof=solution.dof[: len(ants)],
            count=solution.count[: len(ants)],
            nflagged=solution.nflagged[: len(ants)],
            flag_reason=solution.flag_reason[: len(ants)],
            lsts=chunk.lsts,
            jds=chunk.jds,
            antenna_names=(),
        )
        pred = sub.predict(tsky, chunk.lsts)
        usable = np.isfinite(chunk.data) & ~chunk.flags
        if source.weights is not None and config.weights == "radiometer":
            w = np.where(usable, source.weights[: len(ants), :, offset : offset + nt], 0.0)
        else:
            bt = chunk.bandwidth_time() if config.weights == "radiometer" else None
            w = weights_for(
                config.weights, chunk.data, usable, bt, pred if bt is not None else None
            )
        if config.weights == "identity":
            w = w / sub.reduced_chi2[:, :, None, :]
        rows.append(np.where(usable, (chunk.data - pred) * np.sqrt(w), np.nan))
        offset += nt
    resid = np.concatenate(rows, axis=2)
    labels = [f"ant {a} {p}" for a in ants for p in solution.pols]
    return labels, resid.reshape(-1, resid.shape[2], resid.shape[3])


def _write_products(
    config: CalibrationConfig,
    solution: Solution,
    source: _Source,
    sel: dict[str, Any],
    pols: tuple[str, ...],
    tsky_all: np.ndarray,
    out: Path,
) -> dict[str, str]:
    """Write every product into a staging folder, then move them into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    staging = out / f".staging-{os.getpid()}-{time.time_ns()}"
    staging.mkdir()
    names = {
        "calh5": "solution.calh5",
        "calfits": "solution.calfits",
        "hdf5": "solution.h5",
    }
    written: dict[str, str] = {}
    try:
        if "calh5" in config.products:
            from autocal.io.calsol import write_calh5

            write_calh5(solution, staging / names["calh5"])
        if "calfits" in config.products:
            from autocal.io.calsol import write_calfits

            write_calfits(solution, staging / names["calfits"])
        if "hdf5" in config.products:
            from autocal.io.products import write_solution

            write_solution(solution, staging / names["hdf5"])
        if "png" in config.products:
            from autocal.plots import plot_residuals, plot_solution

            plot_solution(solution, staging / "solution.png")
            labels, resid = _residual_waterfalls(solution, config, source, sel, tsky_all)
            plot_residuals(labels, resid, solution.freqs, source.lsts, staging / "residuals.png")
            names["png"] = "solution.png"
            names["residuals_png"] = "residuals.png"
        if config.reference:
            from autocal.compare import compare, write_comparison
            from autocal.io.calsol import read_reference_gains

            reference = read_reference_gains(config.reference)
            comparison = compare(solution, reference)
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
