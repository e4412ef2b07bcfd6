"""The passes over the data: every file's partial sums, added in file order, per pass.

Radiometer weights built from the data bias ``G`` by ``-2 / (dnu dt N)`` relative; when
that exceeds :data:`autocal.fit.passes.REWEIGHT_THRESHOLD` (simulations with the paper's
``dnu dt = 5000``) a second pass weights by the first pass's model, otherwise (HERA data:
``dnu dt >~ 2e5``) the data are read once (:func:`autocal.fit.passes.run_passes` decides). The
files' partials (:func:`autocal.pipeline.partials.compute_partial`) are computed in this
process, in local reader processes (:mod:`autocal.pipeline.readers`) or mapped over a Dask
cluster (:mod:`autocal.pipeline.scaleout`), and added in file order in every case, so all
give the same result bit for bit.

The residual waterfall plot needs no second read: during the pass the weighted sums of the
data and of the model's design columns are kept per time bin for the shown antennas
(:data:`autocal.plots.MAX_PLOTTED` antenna-polarisations, whole antennas:
:func:`autocal.plots.waterfall_antennas`; at most :data:`MAX_WATERFALL_ROWS` bins), which
give the normalised residuals once solved.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from autocal.core.stopping import checkpoint
from autocal.fit.blocks import BlockSums, block_edges, extended_model, sums_nbytes
from autocal.fit.model import FitModel
from autocal.fit.passes import run_passes
from autocal.fit.solution import Solution
from autocal.fit.sums import NormalSums
from autocal.pipeline.config import CalibrationConfig, Progress, read_selection
from autocal.pipeline.partials import (
    FilePartial,
    FileTask,
    PartialSpec,
    add_stats,
    compute_partial,
    compute_partial_with_hits,
    fold,
)
from autocal.pipeline.readers import ProcessReaders
from autocal.pipeline.rfi import RfiMask
from autocal.pipeline.sources import Source
from autocal.plots import waterfall_antennas

logger = logging.getLogger(__name__)

#: Rows (time bins) of the residual waterfall; longer observations are binned in time.
MAX_WATERFALL_ROWS = 512


@dataclass
class PassesResult:
    """What the passes over the data produced.

    Attributes
    ----------
    sums
        The fitted model's normal sums over the whole observation (the last pass).
    blocks
        The time blocks' sums of the total uncertainty (``calibrate`` drops them, 0.8 GB for
        a HERA file, once the total uncertainty and the trend are computed).
    waterfall
        ``(Nshow, Npol, Nbins, Nfreq, nparam + 2)`` the waterfall rows' weighted sums
        (:attr:`autocal.pipeline.partials.FilePartial.waterfall`).
    bin_size
        Integrations per waterfall row.
    npass
        Passes made.
    antennas, antenna_names
        The selected antennas.
    checksums
        ``{path: sha256}`` of the inputs read.
    execution
        How the sums were computed (executor, read counters, timings), for the summary.
    """

    sums: NormalSums
    blocks: BlockSums | None
    waterfall: np.ndarray  # (S, P, Nbins, F, M + 2)
    bin_size: int
    npass: int
    antennas: np.ndarray
    antenna_names: tuple[str, ...]
    checksums: dict[str, str]
    execution: dict[str, Any]


def sum_passes(
    config: CalibrationConfig,
    source: Source,
    pols: tuple[str, ...],
    tsky_all: np.ndarray,
    model: FitModel,
    report: Callable[[float, str], None],
    progress: Progress | None,
    executor: Any,
    block_size: int | None,
    rfi: RfiMask | None = None,
) -> PassesResult:
    """Accumulate the normal sums file by file (one or two passes), here or on an executor.

    ``executor``: reader processes (:class:`~autocal.pipeline.readers.ProcessReaders`), a
    Dask executor (:class:`~autocal.pipeline.scaleout.DaskExecutor`) or ``None`` (this
    process, progress reported block by block).

    ``rfi``: band-edge and RFI flags ORed into every block (:mod:`autocal.pipeline.flagging`).
    """
    tasks = source.tasks(tsky_all)
    ntime = source.lsts.size
    bin_size = max(1, -(-ntime // MAX_WATERFALL_ROWS))
    nbins = -(-ntime // bin_size)
    nshow = waterfall_antennas(len(pols))
    edges = _time_block_edges(config, source, pols, model)
    client = _executor_for(executor, source)
    execution = _execution(source, tasks, block_size, client)
    stats_total: dict[str, int] = {}
    items: list[Any] = list(tasks)
    if rfi is not None and client is not None:
        # each file travels with the flagging's kept hits of its own blocks, the shared mask
        # without them (the hits of the whole night would be sent with every file)
        items = [(t, rfi.hits_between(t.offset, t.offset + t.lsts.size)) for t in tasks]
        rfi = rfi.portable()

    def one_pass(
        coeffs: np.ndarray | None, ipass: int, npass: int
    ) -> tuple[tuple[BlockSums, NormalSums, np.ndarray, list[FilePartial]], NormalSums, float]:
        spec = PartialSpec(
            model,
            config.weights,
            read_selection(config),
            nshow,
            bin_size,
            block_size,
            coeffs,
            tuple(int(e) for e in edges),
            rfi,
        )
        lo = 0.1 + 0.7 * ipass / npass
        hi = 0.1 + 0.7 * (ipass + 1) / npass
        if client is not None:
            func = compute_partial if rfi is None else compute_partial_with_hits
            partials = client.map_ordered(func, spec, items)
        else:
            partials = _serial_partials(spec, tasks, ntime, (lo, hi), progress)
        folded, waterfall, infos = fold(partials, len(tasks), (nbins,), report, (lo, hi))
        assert isinstance(folded, tuple)
        per_block, extended = folded
        blocks = BlockSums(
            [per_block[b] for b in range(len(edges) - 1)], model, edges, source.lsts, extended
        )
        _add_stats(stats_total, infos)
        bt_min = min(info.bt_min for info in infos)
        total = blocks.fitted_total()
        return (blocks, total, waterfall, infos), total, bt_min

    # inverse variances given by the format (EDGES): nothing to re-weight, one pass
    radiometer = config.weights == "radiometer" and source.weights is None
    (blocks, sums, waterfall, infos), npass = run_passes(
        one_pass, passes=config.passes, radiometer=radiometer
    )
    if client is not None:
        execution[execution["executor"]]["worker_peak_rss_bytes"] = client.worker_peak_rss()
    assert sums is not None and waterfall is not None and infos
    checksums: dict[str, str] = {}
    for info in infos:
        checksums.update(info.checksums)
    nant = len(infos[0].antennas)
    execution["samples_per_pass"] = int(ntime * source.freqs.size * len(pols) * nant)
    execution["passes"] = npass
    execution["io"] = stats_total
    execution["file_seconds"] = [round(info.seconds, 3) for info in infos]
    antennas, names = infos[0].antennas, infos[0].antenna_names
    return PassesResult(
        sums, blocks, waterfall, bin_size, npass, antennas, names, checksums, execution
    )


def _time_block_edges(
    config: CalibrationConfig, source: Source, pols: tuple[str, ...], model: FitModel
) -> Any:
    """Return the edges of the total uncertainty's time blocks (a memory budget per block)."""
    nbytes = sums_nbytes(
        extended_model(model),
        max(1, len(source.antenna_numbers(config.antennas))),
        len(pols),
        source.freqs.size,
    )
    return block_edges(source.lsts.size, bytes_per_block=nbytes)


def _executor_for(executor: Any, source: Source) -> Any:
    """Return the executor (Dask or reader processes) if the source is read file by file."""
    use = executor is not None and source.kind == "uvh5"
    if executor is not None and not use:
        logger.info("%s input is read whole in this process", source.kind)
    return executor if use else None


def executor_kind(executor: Any) -> str:
    """Return the summary's name of an executor: ``"dask"``, ``"readers"`` or ``"serial"``."""
    if executor is None:
        return "serial"
    return "readers" if isinstance(executor, ProcessReaders) else "dask"


def _execution(
    source: Source, tasks: list[FileTask], block_size: int | None, client: Any
) -> dict[str, Any]:
    """Return the run's execution record before the passes (completed after them)."""
    kind = executor_kind(client)
    execution: dict[str, Any] = {
        "executor": kind,
        "block_size": block_size or "auto",
        "files": len(tasks),
        "bytes_on_disk": source.disk_bytes(),
    }
    if client is not None:
        execution[kind] = client.describe()
    return execution


def _add_stats(stats_total: dict[str, int], infos: list[FilePartial]) -> None:
    """Add the files' read counters into the run's (the largest array: the maximum)."""
    for info in infos:
        add_stats(stats_total, info.stats)


def _serial_partials(
    spec: PartialSpec,
    tasks: list[FileTask],
    ntime: int,
    progress_range: tuple[float, float],
    progress: Progress | None,
) -> Iterator[FilePartial]:
    """Compute the files' partials in this process, reporting block by block.

    A checkpoint after every block (:func:`autocal.core.stopping.checkpoint`).
    """
    done = 0
    lo, hi = progress_range

    def tick(nt: int) -> None:
        nonlocal done
        done += nt
        if progress is not None:
            progress(lo + (hi - lo) * done / max(ntime, 1), f"{done}/{ntime} integrations")
        checkpoint("the next block")

    for task in tasks:
        yield compute_partial(spec, task, tick)


def solution_of(
    model: FitModel,
    run: PassesResult,
    solved: dict[str, np.ndarray],
    source: Source,
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
