"""Calibrate one observation end to end: configuration in, products out.

``files -> scan -> Tsky(nu, LST) -> normal sums, block by block -> Solution -> products``

:func:`calibrate` is the one calibration function (``autocal.calibrate``; the CLI, the job
service and nightly runs call it); :func:`run_calibration` is its engine, which also returns
the run's summary. The stages live in their own modules: the settings
(:mod:`autocal.pipeline.config`), the inputs (:mod:`autocal.pipeline.sources`), each file's
partial sums (:mod:`autocal.pipeline.partials`, the unit of work, also on Dask workers via
:mod:`autocal.pipeline.scaleout`), the passes over the data (:mod:`autocal.pipeline.passes`),
the comparison's systematics (:mod:`autocal.pipeline.systematics`) and the products
(:mod:`autocal.pipeline.products`).

The data are streamed: each UVH5 file is read in blocks of integrations, each block is turned
into normal-equation sums and dropped, so memory is bounded by the block, whatever the length
of the night or the size of a file. The Tsky table is computed once for the night (and
cached) and sliced per block.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from autocal import __version__
from autocal.core.coords import night_epoch
from autocal.core.observation import Observation
from autocal.core.reprs import compact_repr
from autocal.core.stopping import checkpoint, stop_when
from autocal.fit.model import FitModel, mean_vectors
from autocal.fit.passes import covariance_scaling
from autocal.fit.priors import PriorTerm, TrxrPrior, parse_trxr_prior
from autocal.fit.separation import separation_summary
from autocal.fit.solution import Solution
from autocal.fit.solve import solve_sums
from autocal.fit.sums import NormalSums
from autocal.fit.total_uncertainty import TotalUncertainty, total_uncertainty
from autocal.io.miriad import read_miriad
from autocal.io.uvh5 import read_uvh5
from autocal.io.uvh5_integrity import input_integrity
from autocal.pipeline.config import CalibrationConfig, PipelineError, Progress, read_selection
from autocal.pipeline.decoded import BYTES_PER_SAMPLE, keep_decoded
from autocal.pipeline.flagging import mark_flag_reasons, scan_flags
from autocal.pipeline.passes import PassesResult, solution_of, sum_passes
from autocal.pipeline.products import (
    SUMMARY_NAME,
    check_per_time_memory,
    comparison_summary,
    write_products,
)
from autocal.pipeline.quality import flag_quality
from autocal.pipeline.readers import process_readers, reader_count
from autocal.pipeline.scaleout import dask_client
from autocal.pipeline.sources import (
    Source,
    detect_format,
    memory_source,
    open_edges,
    open_source,
    tsky_per_pol,
)
from autocal.pipeline.stage_clock import StageClock
from autocal.pipeline.systematics import alternative_solutions, block_trend

logger = logging.getLogger(__name__)

__all__ = [
    "CalibrationResult",
    "calibrate",
    "read",
    "read_summary",
    "run_calibration",
]


@dataclass
class CalibrationResult:
    """What a calibration run produced."""

    solution: Solution
    products: dict[str, str]
    summary: dict[str, Any]
    timings: dict[str, float] = field(default_factory=dict)

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        return compact_repr(self)


def _check_references(paths: list[str] | None) -> None:
    """Refuse reference files that are not calibrations before the run reads any data.

    Raises
    ------
    autocal.io.calsol_files.CalsolFormatError
        For a missing, empty, corrupt or non-calibration file (its first bytes and header
        only are read: :func:`autocal.io.calsol_files.sniff_cal_file`).
    """
    if not paths:
        return
    from autocal.io.calsol_files import sniff_cal_file

    for path in paths:
        sniff_cal_file(Path(path).expanduser())


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
    readers: int | None = None,
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
    readers
        Processes that read the UVH5 files (the flagging's reads and the fit's partial
        sums) without Dask (:mod:`autocal.pipeline.readers`): ``None`` (default) one per
        core for a night of at least two files and
        :data:`~autocal.pipeline.readers.MIN_AUTO_BYTES`; ``1`` in this process. The
        solution is identical. Not used with ``dask_scheduler``.

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
    if readers is not None and int(readers) < 1:
        raise PipelineError(f"the number of reader processes must be at least 1, got {readers}")
    with stop_when(should_stop):  # every checkpoint of the run, Tsky's too, reads it
        if dask_scheduler is None:
            nreaders = 1 if observation is not None else _reader_count(config, readers)
            if nreaders < 2:
                return _calibrate(config, folder, progress, None, block_size, observation)
            # started first: the workers start up while this process scans and computes Tsky
            with process_readers(nreaders) as executor:
                return _calibrate(config, folder, progress, executor, block_size)
        # Connect first: a wrong address fails before any work is done.
        with dask_client(dask_scheduler, dask_workers) as executor:
            return _calibrate(config, folder, progress, executor, block_size, observation)


def _decoded_blocks(
    config: CalibrationConfig, source: Source, pols: tuple[str, ...], executor: Any
) -> AbstractContextManager[Any]:
    """Keep the decoded blocks between this process's reads of a small UVH5 observation.

    :mod:`autocal.pipeline.decoded`, when the whole selection fits its budget and a later
    read is certain (the flagging, or two passes); never with reader processes or Dask,
    whose reads are elsewhere.
    """
    rereads = config.rfi_flagging or config.passes == 2
    if executor is not None or source.kind != "uvh5" or not rereads:
        return nullcontext()
    nant = len(source.antenna_numbers(config.antennas))
    samples = nant * len(pols) * source.lsts.size * source.freqs.size
    return keep_decoded(samples * BYTES_PER_SAMPLE)


def _reader_count(config: CalibrationConfig, readers: int | None) -> int:
    """Return the reader processes of a run of ``config.inputs`` (1: in this process)."""
    paths = [Path(p).expanduser().absolute() for p in config.inputs]
    return reader_count(readers, detect_format(paths, config.input_format), paths)


def _calibrate(
    config: CalibrationConfig,
    out: Path | None,
    progress: Progress | None,
    executor: Any,
    block_size: int | None,
    observation: Observation | None = None,
) -> CalibrationResult:
    """Run the calibration (see :func:`run_calibration`).

    ``executor``: reader processes, Dask or ``None`` (this process).
    """
    report = _reporter(progress)
    clock = StageClock()
    _check_references(config.reference)  # before any work: the comparison comes last
    report(0.0, "scanning inputs")
    source = open_source(config) if observation is None else memory_source(observation, config)
    clock.lap("scan_s", clock.started)

    pols = source.pol_names(config.pols)
    prior = _read_prior(config, source, pols)  # read and checked before any work is done
    if out is not None:  # a per-time calh5 too large to hold is refused before any reading
        nant = len(source.antenna_numbers(config.antennas))
        shape = (nant, len(pols), source.freqs.size, source.lsts.size)
        constant = config.model == "constant" or config.order == 0
        check_per_time_memory(config.products, shape, constant=constant)
    epoch = night_epoch(source.jds, source.site.lon_deg)
    report(
        0.05, f"Tsky for {len(pols)} pol(s), {source.freqs.size} channels, {source.lsts.size} LSTs"
    )
    t1 = clock.now()
    tsky_all, tsky_meta = tsky_per_pol(config.sky, config, source, pols, epoch)
    clock.lap("tsky_s", t1)

    with _decoded_blocks(config, source, pols, executor) as decoded:  # reads after the first
        t_flag = clock.now()
        mask, flagging = scan_flags(config, source, tsky_all, block_size, report, executor)
        clock.lap("flagging_s", t_flag)
        if decoded is not None and config.passes != 2:  # the fit's read is likely the last
            decoded.final_read()
        model = FitModel.for_lsts(
            source.lsts, config.model, 0 if config.model == "constant" else config.order
        )
        t2 = clock.now()
        run = sum_passes(
            config,
            source,
            pols,
            tsky_all,
            model,
            report,
            progress,
            executor,
            block_size,
            mask,
        )
        clock.lap("fit_s", t2)

    scaling = covariance_scaling(config.weights, config.inflate_errors)
    prior_fn = _prior_term(prior, source, run, pols, scaling)
    t_solve = clock.now()
    solved, total = _solve(run, model, source, scaling, prior_fn, report)
    clock.lap("solve_s", t_solve)  # with the total uncertainty
    mark_flag_reasons(solved, mask)
    provenance = _provenance(config, source, run, tsky_meta, epoch, total, prior)
    provenance["rfi_flagging"] = flagging
    solution = solution_of(
        model,
        run,
        solved,
        source,
        pols,
        {"calibration": config.model_dump(mode="json"), "provenance": provenance},
        total,
    )
    if mask is not None and mask.integrations.any():
        solution = replace(solution, time_flags=mask.integrations)
    comparison_inputs: dict[str, Any] = {}
    if config.reference:
        report(0.84, "alternative sky models for the comparison's systematics budget")
        comparison_inputs = {
            **block_trend(run, source, tsky_all, pols),
            "alternatives": alternative_solutions(
                config, source, pols, model, epoch, scaling, block_size, prior_fn, mask
            ),
        }
    # the block sums (0.8 GB for a HERA file) have given the total uncertainty and the
    # trend; the products need the waterfall only
    run = replace(run, blocks=None)
    t3 = clock.now()
    made: dict[str, dict[str, Any]] = {}

    def summary_of(staged: dict[str, str], products: dict[str, str]) -> dict[str, Any]:
        clock.lap("products_s", t3)
        clock.lap("total_s", clock.started)
        made["summary"] = {
            "solution": solution.describe(),
            "separation": separation_summary(solution),
            "quality": flag_quality(solution),
            "rfi_flagging": flagging,
            "comparison": comparison_summary(staged),
            "config": config.model_dump(mode="json"),
            "provenance": provenance,
            "products": dict(products),
            **clock.summary(),  # timings_s (wall) and cpu_s (this process's CPU)
            "execution": run.execution,
        }
        return made["summary"]

    if out is None:
        products: dict[str, str] = {}
        summary = summary_of({}, products)
    else:
        report(0.85, "writing products")
        # summary.json is staged with the other products: all are published or none
        products = write_products(
            config, solution, source.lsts, run, out, comparison_inputs, summary_of=summary_of
        )
        summary = {**made["summary"], "products": products}
    # not report(): the products are published, a stop asked for now has nothing to stop
    logger.info("100% done")
    if progress is not None:
        progress(1.0, "done")
    return CalibrationResult(solution, products, summary, clock.wall)


def _reporter(progress: Progress | None) -> Callable[[float, str], None]:
    """Return the run's progress report: logged, passed on, and a stopping checkpoint."""

    def report(fraction: float, message: str) -> None:
        logger.info("%3.0f%% %s", 100 * fraction, message)
        if progress is not None:
            progress(fraction, message)
        checkpoint(message)

    return report


def _read_prior(
    config: CalibrationConfig, source: Source, pols: tuple[str, ...]
) -> TrxrPrior | None:
    """Read the configuration's receiver prior and check it covers the selection."""
    if config.trxr_prior is None:
        return None
    prior = parse_trxr_prior(config.trxr_prior, sigma_k=config.trxr_prior_sigma_k)
    prior.at(source.freqs, antennas=source.antenna_numbers(config.antennas), pols=pols)
    return prior


def _prior_term(
    prior: TrxrPrior | None,
    source: Source,
    run: PassesResult,
    pols: tuple[str, ...],
    scaling: bool | str,
) -> Callable[[NormalSums, np.ndarray, np.ndarray], NormalSums] | None:
    """Return the function that adds the receiver prior to normal sums (``None``: no prior)."""
    if prior is None:
        return None
    return PriorTerm(*prior.at(source.freqs, antennas=run.antennas, pols=pols), scaling)


def _solve(
    run: PassesResult,
    model: FitModel,
    source: Source,
    scaling: bool | str,
    prior_fn: Callable[[NormalSums, np.ndarray, np.ndarray], NormalSums] | None,
    report: Callable[[float, str], None],
) -> tuple[dict[str, np.ndarray], TotalUncertainty | None]:
    """Solve the run's sums (with the prior) and, with time blocks, the total uncertainty."""
    sums = run.sums
    if prior_fn is not None:
        sums = prior_fn(sums, *mean_vectors(model, source.lsts))
    solved = solve_sums(sums, scale_covariance=scaling)
    total = None
    if run.blocks is not None:
        report(0.82, f"total uncertainty ({run.blocks.nblocks} time blocks)")
        total = total_uncertainty(run.blocks, solved, scale_covariance=scaling, prior=prior_fn)
    return solved, total


def _provenance(
    config: CalibrationConfig,
    source: Source,
    run: PassesResult,
    tsky_meta: dict[str, Any],
    epoch: float,
    total: TotalUncertainty | None,
    prior: TrxrPrior | None,
) -> dict[str, Any]:
    """Return what the solution was made from and how (stored with it and in the summary)."""
    return {
        "autocal_version": __version__,
        "inputs": run.checksums,
        "input_format": source.kind,
        "integrity": input_integrity(source.kind, run.checksums),
        "sky": tsky_meta.get("sky"),
        "beam": tsky_meta.get("beam"),
        "site": source.site.describe(),
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
    readers: int | None = None,
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
        Polled at checkpoints; returning ``True`` aborts with
        :class:`autocal.errors.RunCancelledError`.
    dask_scheduler, dask_workers
        Map the files over a Dask cluster (:func:`run_calibration`); the same solution.
    block_size
        Integrations read per block (default: about 8 M values).
    readers
        Processes that read a night's UVH5 files (:func:`run_calibration`; default: one
        per core for nights large enough, ``1``: in this process); the same solution.
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
    >>> sol  # doctest: +SKIP
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
        readers=readers,
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
    kind = detect_format(files, config.input_format)
    sel = read_selection(config)
    if kind == "edges":
        return open_edges(files, config, sel).observation  # type: ignore[return-value]
    if kind == "miriad":
        return read_miriad(files, **sel)
    return read_uvh5(files, **sel)
