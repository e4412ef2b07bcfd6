"""Diagnose one observation end to end: configuration in, products out.

``UVH5 files -> Observation -> band edges and RFI flagged -> model Tsky and effect templates
-> diagnose -> products``

The shared entry point of ``autocal diagnose`` and the service's ``diagnose`` jobs
(:mod:`autocal.service.worker`). :func:`run_diagnosis` reads the autos
(:func:`autocal.diagnosis.reading.read_observation`, a block of integrations at a time),
flags band edges and RFI in them as a calibration does before its fit
(:func:`autocal.pipeline.flagging.flag_observation`; ``rfi_flagging=False`` turns it off),
computes the model Tsky and the templates of the candidate effects
(:func:`autocal.diagnosis.effects.sky_templates`), runs the discrepancy workflow
(:func:`autocal.diagnosis.stepwise.diagnose`, DESIGN.md section 5) and writes its products:
``diagnosis.json``, ``summary.txt``, the residual plots
(:func:`autocal.diagnosis.report.write_diagnosis`) and ``summary.json`` (accepted effects,
final gap, provenance, timings).

As in :mod:`autocal.pipeline.calibrate`, products are written to a staging folder inside ``out``
and moved into place only when all of them succeeded (``summary.json`` last), so a failed
or cancelled run never leaves a half-written product set.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    field_validator,
    model_validator,
)

from autocal import __version__
from autocal.core.coords import night_epoch
from autocal.core.files import make_staging, publish_staged
from autocal.core.memory import available_memory
from autocal.core.observation import Observation
from autocal.core.stopping import checkpoint, stop_when
from autocal.diagnosis import effects, report
from autocal.diagnosis.effects import SkyTemplates
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.reading import read_observation
from autocal.diagnosis.report import Diagnosis
from autocal.diagnosis.stepwise import diagnose
from autocal.diagnosis.trials import ALPHA, BIC_THRESHOLD
from autocal.fit.priors import parse_trxr_prior
from autocal.io.uvh5_integrity import input_integrity
from autocal.pipeline.config import check_prior_spec, check_ranges
from autocal.pipeline.flagging import TURNED_OFF, flag_observation
from autocal.plots import file_stems

logger = logging.getLogger(__name__)

Progress = Callable[[float, str], None]
#: Beam polarisation of each data polarisation the diagnosis accepts (x points east).
BEAM_POLS = {"ee": "ee", "nn": "nn", "xx": "ee", "yy": "nn"}
#: Name of the summary product (always written, moved into place last).
SUMMARY = "summary.json"


class DiagnoseConfig(BaseModel):
    """Everything that defines one diagnosis (shared by the CLI, the API and workers).

    Frequencies in MHz, LSTs in hours, temperatures in kelvin. The statistic settings
    (``bic_threshold``, ``alpha``, ``max_steps``) default to those of
    :func:`autocal.diagnosis.stepwise.diagnose`.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    inputs: list[Annotated[str, StringConstraints(min_length=1)]] = Field(
        ..., min_length=1, description="UVH5 files of one observation"
    )
    sky: str = Field(
        "gsm2008", min_length=1, description="model sky (autocal.sky.models.get_sky spec)"
    )
    beam: str = Field(
        "hera", min_length=1, description="model beam (autocal.sky.beam_names.get_beam spec)"
    )
    tgnd_k: float = Field(300.0, ge=0.0, description="model ground temperature")
    nside: int = Field(64, ge=1, le=8192, description="HEALPix resolution of the templates")
    antennas: list[Annotated[int, Field(ge=0)]] | None = Field(
        None, min_length=1, description="antenna numbers (default: every antenna with autos)"
    )
    pols: list[Literal["ee", "nn", "xx", "yy"]] | None = Field(
        None, min_length=1, description="polarisations (default: the file's ee/nn or xx/yy)"
    )
    freq_range_mhz: tuple[float, float] | None = Field(None, description="(low, high) MHz")
    lst_range_h: tuple[float, float] | None = Field(
        None, description="(start, stop) hours; start > stop wraps through 24 h"
    )
    trxr_prior: float | str | None = Field(
        None,
        description="known receiver temperature: a number (K), a CSV table "
        "freq_mhz,trxr_k[,sigma_k] or a previous solution.h5; makes effects that are "
        "constant in time (sky_offset, ground_temperature, missing_cmb) and sky scalings "
        "identifiable",
    )
    trxr_prior_sigma_k: float = Field(
        1.0, gt=0.0, description="1-sigma of a number prior or a table without sigma_k"
    )
    bic_threshold: float = Field(
        BIC_THRESHOLD, ge=0.0, description="Delta BIC an effect must exceed to be accepted"
    )
    alpha: float = Field(
        ALPHA,
        gt=0.0,
        le=1.0,
        description="largest chi^2 survival probability of an accepted effect's Delta chi^2",
    )
    max_steps: int = Field(5, ge=0, le=50, description="most effects added")
    rfi_flagging: bool = Field(
        True,
        description="flag band edges and RFI from the autos before the fits, as calibrate "
        "does (autocal.pipeline.flagging); false: the data's own flags only (the outliers "
        "of the residuals are flagged either way)",
    )

    @field_validator("pols", mode="before")
    @classmethod
    def _lower_pols(cls, value: Any) -> Any:
        if isinstance(value, list | tuple):
            return [v.strip().lower() if isinstance(v, str) else v for v in value]
        return value

    @field_validator("nside")
    @classmethod
    def _power_of_two(cls, value: int) -> int:
        if value & (value - 1):
            raise ValueError(f"nside must be a power of two (got {value})")
        return value

    @model_validator(mode="after")
    def _check(self) -> DiagnoseConfig:
        check_ranges(self.freq_range_mhz, self.lst_range_h)
        check_prior_spec(self.trxr_prior, self.trxr_prior_sigma_k)
        return self


def product_name(filename: str) -> str:
    """Return the product name of a file (``diagnosis.json`` -> ``diagnosis``).

    JSON files are named by their stem (``diagnosis``, ``summary``), other files by stem
    and suffix (``summary_txt``, ``residuals_png``, ``residuals_step1_png``), as the
    calibration's ``residuals_png``.
    """
    path = Path(filename)
    suffix = path.suffix.lower().lstrip(".")
    return path.stem if suffix in ("json", "") else f"{path.stem}_{suffix}"


def _strict_json(value: Any) -> Any:
    """``value`` as strict JSON data: numpy to Python, non-finite floats to ``None``."""
    if isinstance(value, dict):
        return {str(k): _strict_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_strict_json(v) for v in value]
    if isinstance(value, np.ndarray | np.generic):
        return _strict_json(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return str(value)


def _input_paths(config: DiagnoseConfig) -> list[Path]:
    paths = [Path(p).expanduser().absolute() for p in config.inputs]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise DiagnoseError(f"input(s) not found: {missing}")
    folders = [str(p) for p in paths if p.is_dir()]
    if folders:
        raise DiagnoseError(
            f"diagnose reads UVH5 files; {folders} are folders (Miriad data: convert them "
            "to UVH5 first)"
        )
    return paths


def _beam_pols(pols: tuple[str, ...]) -> tuple[str, ...]:
    unknown = [p for p in pols if p not in BEAM_POLS]
    if unknown:
        raise DiagnoseError(
            f"polarisation(s) {unknown} have no power beam: diagnose ee/nn (or xx/yy); "
            "select them with pols"
        )
    return tuple(BEAM_POLS[p] for p in pols)


#: Peak memory of a diagnosis: this much plus :data:`BYTES_PER_SAMPLE` per sample (antenna x
#: pol x channel x integration), measured with ``benchmarks/diagnose_scale.py`` (``autocal
#: diagnose`` on the first file of the HERA-size night, 192 integrations x 1536 channels x 2
#: pols; README, "Diagnosing", **Size.**): 1.83 GB for 30 antennas (17.7 M samples), 6.33 GB
#: for all 350 (206 M). The fit streams antennas in chunks
#: (:func:`autocal.diagnosis.extended_fit.fit_extended`), so what grows with the samples is the
#: observation (float64 data, flags), the float32 weights and, while outliers are flagged,
#: their high-passed residuals.
BASE_BYTES = 1.5e9
#: See :data:`BASE_BYTES` (the slope between those two runs, 23.8 bytes, rounded up).
BYTES_PER_SAMPLE = 26.0
#: What the benchmark above does not reach, per sample: the check that an accepted
#: candidate is the same in both halves of the band
#: (:func:`autocal.diagnosis.consistency.band_consistency`) copies one half of the data at a
#: time (float64 data and nsamples, bool flags: 17 bytes per sample of the half), and that
#: benchmark's night (the model's own sky) never accepts a candidate.
HALF_BAND_BYTES_PER_SAMPLE = 8.5


def check_memory(shape: tuple[int, ...]) -> None:
    """Refuse a diagnosis the machine has no memory for, saying how to make it smaller.

    Parameters
    ----------
    shape
        ``(Nant, Npol, Ntime, Nfreq)`` of the observation.

    Raises
    ------
    autocal.diagnosis.errors.DiagnoseError
        When the estimate (:data:`BASE_BYTES` + :data:`BYTES_PER_SAMPLE` and
        :data:`HALF_BAND_BYTES_PER_SAMPLE` per sample) exceeds :func:`available_memory`.
    """
    nsamples = math.prod(shape)
    need = BASE_BYTES + (BYTES_PER_SAMPLE + HALF_BAND_BYTES_PER_SAMPLE) * nsamples
    avail = available_memory()
    if avail is not None and need > avail:
        nant, npol, ntime, nfreq = shape
        raise DiagnoseError(
            f"diagnosing {nsamples / 1e6:.1f} M samples ({nant} antennas x {npol} pols x "
            f"{nfreq} channels x {ntime} integrations) needs about {need / 1e9:.1f} GB and "
            f"{max(avail, 0) / 1e9:.1f} GB are available: select fewer antennas (--antennas, "
            "API 'antennas'), channels (--freq-range) or LSTs (--lst-range)"
        )
    logger.debug("diagnosis of %d samples: about %.1f GB", nsamples, need / 1e9)


#: Fewest channels a diagnosis fits: a smooth bandpass and a cable reflection across the band
#: (four channels made the reflection fit's least squares empty).
MIN_CHANNELS = 8


def _check_channels(obs: Observation) -> None:
    """Refuse a selection too narrow for the frequency-domain fits, saying what to do."""
    if obs.nfreq >= MIN_CHANNELS:
        return
    band = f"{obs.freqs.min() / 1e6:.3f}-{obs.freqs.max() / 1e6:.3f} MHz" if obs.nfreq else "none"
    raise DiagnoseError(
        f"the selection has {obs.nfreq} channel(s) ({band}): the diagnosis fits smooth "
        f"bandpasses and cable reflections across the band and needs at least {MIN_CHANNELS}; "
        "widen --freq-range (freq_range_mhz)"
    )


def run_diagnosis(
    config: DiagnoseConfig,
    out: str | Path,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> Path:
    """Diagnose one observation and write its products.

    Parameters
    ----------
    config
        The diagnosis settings.
    out
        Output folder (created when the products are written). Products:
        ``diagnosis.json``, ``summary.txt``, ``residuals_step<i>.png`` (before/after each
        accepted step; ``residuals.png`` when nothing was accepted), ``gain_series.png``
        (when a per-integration gain series was accepted) and ``summary.json``
        (``effects``, ``final_gap``, ``rfi_flagging``, ``config``, ``provenance``,
        ``products``, ``timings_s``).
    progress
        Called with (fraction done, message) at each stage.
    should_stop
        Polled between stages and before every model fit of the search; returning
        ``True`` aborts with :class:`autocal.errors.RunCancelledError` (the service's cancellation
        or shutdown) and publishes nothing.

    Returns
    -------
    pathlib.Path
        The output folder.

    Raises
    ------
    autocal.diagnosis.errors.DiagnoseError
        Missing inputs, folders instead of UVH5 files, polarisations without a beam, or
        data the diagnosis cannot fit.
    autocal.errors.RunCancelledError
        When cancelled.
    """
    with stop_when(should_stop):  # every checkpoint of the run, Tsky's too, reads it
        return _run_diagnosis(config, Path(out), progress)


def _run_diagnosis(config: DiagnoseConfig, out: Path, progress: Progress | None) -> Path:

    def advance(fraction: float, message: str) -> None:
        logger.info("%3.0f%% %s", 100 * fraction, message)
        if progress is not None:
            progress(fraction, message)
        checkpoint(message)

    out = Path(out)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    paths = _input_paths(config)
    prior = None
    if config.trxr_prior is not None:  # a malformed prior fails before any reading
        prior = parse_trxr_prior(config.trxr_prior, sigma_k=config.trxr_prior_sigma_k)
    advance(0.0, f"reading {len(paths)} UVH5 file(s)")
    mhz = config.freq_range_mhz
    obs = read_observation(
        paths,
        antennas=config.antennas,
        pols=config.pols,
        freq_range=None if mhz is None else (mhz[0] * 1e6, mhz[1] * 1e6),
        lst_range=config.lst_range_h,
        check=check_memory,
    )
    timings["read_s"] = time.perf_counter() - t0
    _check_channels(obs)
    prior_mean = prior_sigma = None
    if prior is not None:
        prior_mean, prior_sigma = prior.at(obs.freqs, antennas=obs.antennas, pols=obs.pols)

    beam_pols = _beam_pols(tuple(p.lower() for p in obs.pols))
    epoch = night_epoch(obs.jds, obs.site.lon_deg)
    advance(
        0.15,
        f"sky templates for {len(beam_pols)} pol(s), {obs.nfreq} channels, {obs.ntime} LSTs",
    )
    t1 = time.perf_counter()
    templates = _templates(config, obs, beam_pols, epoch)
    timings["templates_s"] = time.perf_counter() - t1
    flagging = dict(TURNED_OFF)
    if config.rfi_flagging:  # the flags in time follow the model sky's band level
        advance(0.45, "flagging band edges and RFI from the autos")
        t_flag = time.perf_counter()
        obs, flagging = flag_observation(obs, tsky=templates.total)
        timings["flagging_s"] = time.perf_counter() - t_flag

    advance(
        0.5,
        f"diagnosing {len(obs.antennas)} antenna(s) x {len(obs.pols)} pol(s): fitting the "
        "model and the candidate effects",
    )
    t2 = time.perf_counter()
    diag = diagnose(
        obs,
        templates,
        trxr_prior=prior_mean,
        trxr_prior_sigma=1.0 if prior_sigma is None else prior_sigma,
        bic_threshold=config.bic_threshold,
        alpha=config.alpha,
        max_steps=config.max_steps,
        progress=lambda fraction, message: advance(0.5 + 0.4 * fraction, message),
    )
    timings["diagnose_s"] = time.perf_counter() - t2
    diag.rfi_flagging = flagging
    logger.info("accepted effects: %s", ", ".join(diag.effects) or "none")

    advance(0.9, "writing products")
    t3 = time.perf_counter()
    summary = _summary(config, obs, paths, templates, epoch, diag)

    def write(staging: Path) -> None:
        report.write_diagnosis(diag, staging, obs, stems=file_stems(paths))

    products = _publish(out, write, summary, timings, t0, t3)
    logger.info("wrote %d products to %s", len(products), out)
    if progress is not None:  # the products are in place: too late to cancel
        progress(1.0, f"done: {', '.join(diag.effects) or 'no significant effect'}")
    return out


def _templates(
    config: DiagnoseConfig, obs: Observation, beam_pols: tuple[str, ...], epoch: float
) -> SkyTemplates:
    """Compute the model Tsky and the candidates' templates on the observation's grid."""
    return effects.sky_templates(
        config.sky,
        config.beam,
        obs.site,
        obs.freqs,
        obs.lsts,
        pols=beam_pols,
        tgnd=config.tgnd_k,
        nside=config.nside,
        epoch=epoch,  # the frame tilts by the span (sky_templates' default)
    )


def _summary(
    config: DiagnoseConfig,
    obs: Observation,
    paths: list[Path],
    templates: SkyTemplates,
    epoch: float,
    diag: Diagnosis,
) -> dict[str, Any]:
    """Return ``summary.json`` without its products and timings (:func:`_publish` adds them)."""
    tsky_meta = templates.meta.get("tsky", {})
    provenance = {
        "autocal_version": __version__,
        "inputs": obs.meta.get("sha256", {}),
        "input_bytes": {str(p): p.stat().st_size for p in paths},
        "input_format": "uvh5",
        "integrity": input_integrity("uvh5", paths),
        "sky": tsky_meta.get("sky"),
        "beam": tsky_meta.get("beam"),
        "site": obs.site.describe(),
        "tgnd_K": config.tgnd_k,
        "cmb": tsky_meta.get("cmb"),
        "frame": tsky_meta.get("frame"),
        "epoch_jd": epoch,
        "nside": config.nside,
        "created_unix": time.time(),
    }
    doc = diag.to_dict()
    return {
        "kind": "diagnose",
        "effects": list(diag.effects),
        "steps": [
            {
                "name": step.get("name"),
                "statistic": step.get("statistic"),
                "delta": step.get("delta"),
                "parameters": step.get("parameters"),
            }
            for step in doc.get("steps", [])
        ],
        "initial_gap": doc.get("initial_gap"),
        "final_gap": doc.get("final_gap"),
        "rfi_flagging": diag.rfi_flagging,
        "observation": obs.describe(),
        "config": config.model_dump(mode="json"),
        "provenance": provenance,
    }


def _publish(
    out: Path,
    write: Callable[[Path], None],
    summary: dict[str, Any],
    timings: dict[str, float],
    t0: float,
    t_write: float,
) -> dict[str, str]:
    """Write the products into a staging folder inside ``out``, then move them into ``out``.

    ``summary.json`` (with the final product paths and timings) is written last into the
    staging folder and moved last; the staging folder is removed whatever happens.
    """
    staging = make_staging(out)
    try:
        write(staging)
        files = sorted(p.name for p in staging.iterdir() if p.name != SUMMARY)
        products = {product_name(name): str(out / name) for name in files}
        products[product_name(SUMMARY)] = str(out / SUMMARY)
        timings["products_s"] = time.perf_counter() - t_write
        timings["total_s"] = time.perf_counter() - t0
        summary = {
            **summary,
            "products": products,
            "timings_s": {k: round(v, 3) for k, v in timings.items()},
        }
        text = json.dumps(_strict_json(summary), indent=2, allow_nan=False)
        (staging / SUMMARY).write_text(text + "\n")
        checkpoint("publishing")  # last chance to stop: nothing is published yet
        publish_staged(staging, out, [*files, SUMMARY])  # flushed to disk, summary last
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return products


def read_summary(out: str | Path) -> dict[str, Any]:
    """Return the ``summary.json`` of a diagnosis written by :func:`run_diagnosis`.

    Parameters
    ----------
    out
        The output folder.

    Returns
    -------
    dict
        The summary (``effects``, ``final_gap``, ``provenance``, ``products``...).
    """
    return json.loads((Path(out) / SUMMARY).read_text())
