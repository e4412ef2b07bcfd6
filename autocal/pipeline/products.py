"""The products of a calibration: solution files, plots, comparison and ``summary.json``.

Products are written to a staging folder inside ``out`` and moved into place only when
all of them succeeded (:func:`write_products`), so a failed run never leaves a half-written
product set. :func:`write_solution_products` is also the writer of
:meth:`autocal.fit.solution.Solution.write`.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.files import atomic_path, make_staging, publish_staged
from autocal.core.memory import available_memory
from autocal.fit.solution import Solution
from autocal.io.products import write_solution
from autocal.pipeline.config import CalibrationConfig, PipelineError
from autocal.pipeline.passes import PassesResult
from autocal.plots import band_core, file_stems, plot_residuals, run_title

#: File name of each product of a solution (``CalibrationConfig.products``).
PRODUCT_FILES: dict[str, str] = {
    "calh5": "solution.calh5",
    "calfits": "solution.calfits",
    "hdf5": "solution.h5",
    "png": "solution.png",
}

#: The figures ``autocal calibrate`` writes beside ``solution.png`` (with the ``png``
#: product): summary key -> file name.
FIGURE_FILES: dict[str, str] = {
    "residuals_png": "residuals.png",
    "delay_png": "delay_spectra.png",
    "data_model_png": "data_model.png",
}

#: Name of the run's JSON summary in the output folder.
SUMMARY_NAME = "summary.json"

logger = logging.getLogger(__name__)

#: Bytes in memory per gain value (antenna x pol x channel x integration) of a per-time
#: product, by product and by whether the time model is constant. calfits: pyuvdata's
#: ``UVCal`` writes it whole, through float64 (one 350-antenna, 1536-channel,
#: 192-integration night file with the calfits alone: peak 7.15 GB, 5.5 GB above the
#: fit's, for 206 M values: 27 bytes each).
#: calh5 is written an antenna at a time (:mod:`autocal.io.calsol_write`): a constant
#: model's gains, flags and qualities are one integration's, seen at every time, and only
#: the flags of integrations flagged whole are held per time (1 byte); a time-varying
#: model's are held whole (complex64 gains, flags, float32 qualities, and a second flag
#: array while the integrations flagged whole are added: 14 bytes).
PER_TIME_BYTES_PER_VALUE = {
    ("calh5", True): 1,
    ("calh5", False): 14,
    ("calfits", True): 27,
    ("calfits", False): 27,
}


def check_per_time_memory(
    products: Sequence[str], shape: tuple[int, int, int, int], *, constant: bool = False
) -> None:
    """Refuse, before any data are read, a per-time UVCal product the machine cannot hold.

    Parameters
    ----------
    products
        The requested products (``calh5`` and ``calfits`` are per time).
    shape
        ``(Nant, Npol, Nfreq, Ntime)`` of the solution.
    constant
        Whether the time model is constant (its per-time gains are one integration's).

    Raises
    ------
    PipelineError
        When :data:`PER_TIME_BYTES_PER_VALUE` per gain value exceeds
        :func:`~autocal.core.memory.available_memory`, with what to do instead.
    """
    per_time = [p for p in products if p in ("calh5", "calfits")]
    if not per_time:
        return
    nant, npol, nfreq, ntime = shape
    per_value = max(PER_TIME_BYTES_PER_VALUE[(p, constant)] for p in per_time)
    need = per_value * nant * npol * nfreq * ntime
    avail = available_memory()
    if avail is not None and need > avail:
        raise PipelineError(
            f"the per-time {'/'.join(per_time)} of {ntime} integrations x {nant} antennas x "
            f"{npol} pols x {nfreq} channels needs about {need / 1e9:.1f} GB in memory "
            f"and {max(avail, 0) / 1e9:.1f} GB are available: "
            "calibrate the files one by one (as `autocal nightly` does; hera_cal applies one "
            "calibration file per data file), or ask only for products=hdf5,png (every G(t) "
            "of the time model is in solution.h5)"
        )


def write_solution_products(
    solution: Solution,
    out: str | Path,
    products: Sequence[str],
    *,
    overwrite: bool = False,
    stems: tuple[str, ...] = (),
) -> dict[str, str]:
    """Write a solution's products into ``out`` (:data:`PRODUCT_FILES`; each atomically).

    The writers of ``autocal calibrate`` and :meth:`autocal.fit.solution.Solution.write`:
    calh5/calfits through pyuvdata ``UVCal`` (:mod:`autocal.io.calsol_uvcal`), the HDF5 product
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
    stems
        Input file stems, named in the figure's title.

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
        # pyuvdata and the figures' modules are imported by the products that need them
        # (a run writing only hdf5 starts ~3 s sooner)
        if name == "calh5":
            from autocal.io.calsol_write import write_calh5

            write_calh5(solution, path, overwrite=overwrite)
        elif name == "calfits":
            from autocal.io.calsol_write import write_calfits

            write_calfits(solution, path, overwrite=overwrite)
        elif name == "hdf5":
            write_solution(solution, path, overwrite=overwrite)
        else:
            from autocal.solution_plots import plot_solution

            if path.exists() and not overwrite:
                raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
            plot_solution(solution, path, stems=stems)
        written[name] = str(path)
    return written


def waterfall_residuals(
    solution: Solution, run: PassesResult, config: CalibrationConfig, lsts: np.ndarray
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


def data_model_curves(
    solution: Solution, run: PassesResult, lsts: np.ndarray, core: np.ndarray
) -> dict[str, Any]:
    """Return the data and model curves of :func:`~autocal.solution_plots.data_model_figure`.

    Of the data and of the fitted model: weighted means over time (``(K, Nfreq)``), and
    per waterfall row (``(K, Nbins)``) the mean over the channels in ``core`` with data in
    every row of the row's weighted means.
    """
    wf = run.waterfall
    ns = wf.shape[0]
    model_sum = np.einsum("spbfm,spfm->spbf", wf[..., 2:], solution.coeffs[:ns])
    data_sum, wsum = wf[..., 0], wf[..., 1]
    flat = (-1, data_sum.shape[-1])
    flagged = solution.flags[:ns]
    with np.errstate(divide="ignore", invalid="ignore"):
        wf_t = wsum.sum(axis=2)
        data = np.where(wf_t > 0, data_sum.sum(axis=2) / wf_t, np.nan)
        model = np.where(wf_t > 0, model_sum.sum(axis=2) / wf_t, np.nan)
        # the channels inside the band with data in every row (a set changing from row to
        # row makes the mean jump); any with data in the row if no channel has it in all
        band = (core & ~flagged)[:, :, None, :] & (wsum > 0)
        always = band.all(axis=2, keepdims=True)
        use = np.where(always.any(axis=-1, keepdims=True), always & band, band)
        count = np.count_nonzero(use, axis=-1)
        per_bin = np.where(use, wsum, 1.0)
        data_t = np.where(use, data_sum / per_bin, 0.0).sum(axis=-1) / count
        model_t = np.where(use, model_sum / per_bin, 0.0).sum(axis=-1) / count
    labels = [f"ant {a} {p}" for a in solution.antennas[:ns].tolist() for p in solution.pols]
    centre = np.minimum(np.arange(wf.shape[2]) * run.bin_size + run.bin_size // 2, lsts.size - 1)
    return {
        "labels": labels,
        "freqs": solution.freqs,
        "lsts": lsts[centre],
        "data": np.where(flagged, np.nan, data).reshape(flat),
        "model": np.where(flagged, np.nan, model).reshape(flat),
        "data_t": data_t.reshape(len(labels), -1),
        "model_t": model_t.reshape(len(labels), -1),
    }


def write_figures(
    solution: Solution, run: PassesResult, config: CalibrationConfig, lsts: np.ndarray, out: Path
) -> None:
    """Write :data:`FIGURE_FILES` into ``out``: residuals, delay spectra, data vs model."""
    from autocal.solution_plots import plot_data_model, plot_delay_spectra

    stems = file_stems(config.inputs)
    core = band_core(solution.G, solution.flags)
    total = solution.antennas.size * len(solution.pols)
    labels, resid, bin_lsts = waterfall_residuals(solution, run, config, lsts)
    if len(labels) < total:
        logger.info(
            "residuals.png and data_model.png show %d of %d antenna-pols (%s)",
            len(labels),
            total,
            ", ".join(labels),
        )
    head = run_title(solution.jds, solution.antennas, solution.pols, stems)
    path = out / FIGURE_FILES["residuals_png"]
    plot_residuals(
        labels, resid, solution.freqs, bin_lsts, path, title=head, total=total, channels=core
    )
    plot_delay_spectra(solution, out / FIGURE_FILES["delay_png"], stems=stems)
    curves = data_model_curves(solution, run, lsts, core)
    title = f"{head}\ndata vs {solution.model.kind} model"
    path = out / FIGURE_FILES["data_model_png"]
    plot_data_model(curves, path, title=title, total=total, core=core)


def write_products(
    config: CalibrationConfig,
    solution: Solution,
    lsts: np.ndarray,
    run: PassesResult,
    out: Path,
    comparison_inputs: dict[str, Any] | None = None,
    summary_of: Callable[[dict[str, str], dict[str, str]], dict[str, Any]] | None = None,
) -> dict[str, str]:
    """Write every product into a staging folder, then move them into ``out``.

    ``lsts`` are the observation's (hours), for the residual waterfall's rows. With
    ``summary_of``, ``summary.json`` is part of the set: ``summary_of(staged, products)``
    (product paths in the staging folder, where they can be read, and their final paths)
    returns the summary, written into the staging folder like every other product. Nothing
    is moved into ``out`` until every product, the summary included, was written; then the
    files are flushed to disk and renamed, ``summary.json`` last, so a folder with a
    ``summary.json`` holds the whole set.
    """
    staging = make_staging(out)
    names = {**PRODUCT_FILES, **FIGURE_FILES}
    try:
        stems = file_stems(config.inputs)
        write_solution_products(solution, staging, config.products, stems=stems)
        if "png" in config.products:
            write_figures(solution, run, config, lsts, staging)
        if config.reference:
            from autocal.compare.comparison import compare
            from autocal.compare.report import write_comparison
            from autocal.io.calsol_read import read_reference_gains

            reference = read_reference_gains(config.reference)
            comparison = compare(solution, reference, **(comparison_inputs or {}))
            paths = write_comparison(comparison, staging)
            names.update({f"compare_{k}": Path(v).name for k, v in paths.items()})
        files = sorted(item.name for item in staging.iterdir())
        keys = {name: next((k for k, v in names.items() if v == name), name) for name in files}
        staged = {keys[name]: str(staging / name) for name in files}
        written = {keys[name]: str(out / name) for name in files}
        if summary_of is not None:
            summary = summary_of(staged, written)
            (staging / SUMMARY_NAME).write_text(
                json.dumps(summary, indent=2, default=_json_default)
            )
            files.append(SUMMARY_NAME)
        publish_staged(staging, out, files)
        if summary_of is not None:
            written["summary"] = str(out / SUMMARY_NAME)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return written


def write_summary(out: Path, summary: dict[str, Any]) -> str:
    """Write a run's summary as :data:`SUMMARY_NAME` into ``out`` (atomically); return its path."""
    summary_path = out / SUMMARY_NAME
    with atomic_path(summary_path) as tmp:
        tmp.write_text(json.dumps(summary, indent=2, default=_json_default))
    return str(summary_path)


def comparison_summary(products: dict[str, str]) -> dict[str, Any] | None:
    """Return the written reference comparison's JSON summary (``None`` without one)."""
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
