"""Submitting calibrations: one observation (``POST /jobs``) or a whole night (``POST /nightly``).

Both go through :func:`submit_calibration`, which validates the options as a
:class:`~autocal.pipeline.config.CalibrationConfig`, resolves every path under the allowed roots
(:mod:`autocal.service.paths`) and queues the job idempotently: the deduplication key is
the SHA-256 of the job kind, the sorted resolved inputs and the rest of the configuration,
so the same observation with the same settings is not calibrated twice unless forced.

Nightly grouping (:func:`find_observations`)
--------------------------------------------
HERA files are named ``zen.<JD>.<fraction>.<suffix>`` with ``uvh5`` in the suffix (e.g.
``zen.2458116.30448.HH.uvh5``). Files are grouped by folder, integer JD and suffix (the
file "kind": ``HH.uvh5`` and ``xx.HH.XRAA.uvh5`` are different data products); within a
group, sorted by start time ``JD.fraction``, a gap larger than 2.5 times the typical spacing
between consecutive starts (the lower median of the spacings) begins a new observation. Each
observation becomes one job.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from autocal.errors import AutocalError
from autocal.pipeline.config import CalibrationConfig
from autocal.service.input_check import fingerprint_config
from autocal.service.paths import InputPathError, check_under_roots, resolve_input
from autocal.service.settings import Settings
from autocal.service.store import JobStore

logger = logging.getLogger(__name__)

#: HERA file names: ``zen.<JD>.<fraction>.<suffix containing uvh5>``.
ZEN_NAME = re.compile(r"^zen\.(?P<jd>\d{7})\.(?P<frac>\d+)\.(?P<kind>.*uvh5.*)$")
#: Any ``zen.<JD>.<fraction>`` name (for the night of an input).
ZEN_JD = re.compile(r"^zen\.(\d{7})\.\d+")
#: A gap larger than this many typical spacings starts a new observation.
GAP_FACTOR = 2.5
#: Beam names that are not paths.
NAMED_BEAMS = frozenset(
    {"dipole", "airy", "hera", "edges-low", "edges-low-45deg", "edges-mid", "edges-high"}
)


class NightlyError(AutocalError):
    """A nightly submission found nothing or was asked wrongly.

    Parameters
    ----------
    message
        What is wrong and what to do.
    status_code
        HTTP status for the API (404 nothing found, 400 bad arguments).
    """

    def __init__(self, message: str, status_code: int = 400) -> None:
        super().__init__(message)
        self.status_code = status_code


# one observation ------------------------------------------------------------------------


def checked_options(
    config_type: type[Any],
    settings: Settings,
    inputs: Sequence[str],
    options: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """Validate job options against ``config_type`` and resolve the sky and beam they name.

    Field errors come first, before any file I/O; then the sky model is looked up and a
    beam file resolved inside the allowed roots. The inputs are left to the caller.
    """
    from autocal.sky.models import get_sky

    opts = dict(options or {})
    if "inputs" in opts:
        raise NightlyError("give the inputs separately from the options")
    config_type(inputs=list(inputs), **opts)
    if opts.get("sky") is not None:
        get_sky(str(opts["sky"]))
    beam = opts.get("beam")
    if beam is not None and str(beam).strip().lower() not in NAMED_BEAMS:
        named = ", ".join(sorted(NAMED_BEAMS))
        try:
            opts["beam"] = str(resolve_input(str(beam), settings, what="beam"))
        except InputPathError as err:
            if err.status_code != 400:  # outside the roots (403): as it is
                raise
            raise InputPathError(
                f"beam {beam!r} is neither a named beam ({named}) nor a beam file under the "
                f"data roots ({err})"
            ) from None
    prior = opts.get("trxr_prior")
    if isinstance(prior, str):  # a table or solution under the roots, read and checked now
        from autocal.fit.priors import parse_trxr_prior, prior_value

        value = prior_value(prior)
        if isinstance(value, str):
            value = str(resolve_input(value, settings, what="trxr prior"))
        opts["trxr_prior"] = value
        sigma = (
            opts.get("trxr_prior_sigma_k")
            or config_type.model_fields["trxr_prior_sigma_k"].get_default()
        )
        parse_trxr_prior(value, sigma_k=float(sigma))
    return opts


def build_config(
    settings: Settings, inputs: Sequence[str], options: Mapping[str, Any] | None = None
) -> CalibrationConfig:
    """Validate calibration options and resolve every path they name.

    Parameters
    ----------
    settings
        The service settings (allowed roots).
    inputs
        Input paths (absolute, relative to a data root) or upload ids.
    options
        Further :class:`CalibrationConfig` fields (``sky``, ``beam``, ``freq_range_mhz``...).

    Returns
    -------
    CalibrationConfig
        With resolved absolute inputs, reference and beam file; the ``hdf5`` product is
        always included (the API reads results from it).

    Raises
    ------
    pydantic.ValidationError
        For invalid or unknown options.
    InputPathError
        For paths outside the allowed roots or missing.
    autocal.sky.models.SkyModelError
        For an unknown sky model.
    autocal.service.submission_checks.SubmissionError
        For an option that does nothing with the others, a file listed twice, an input the
        reader refuses, a selection the inputs cannot satisfy, a frequency range outside
        the data's band, a sky that would flag every channel or a reference file that is
        not a calibration.
    """
    check_options(options)
    opts = checked_options(CalibrationConfig, settings, inputs, options)
    if opts.get("reference"):
        opts["reference"] = [
            str(resolve_input(str(r), settings, what="reference")) for r in opts["reference"]
        ]
    products = list(
        opts.get("products")
        or CalibrationConfig.model_fields["products"].get_default(call_default_factory=True)
    )
    if "hdf5" not in products:
        products.append("hdf5")
    opts["products"] = products
    resolved = [resolve_input(str(p), settings) for p in inputs]
    check_submission(resolved, opts)
    return CalibrationConfig(inputs=[str(p) for p in resolved], **opts)


#: Submission checks about one observation's files: a nightly submission reports an
#: observation refused for these and submits the others; any other refusal (the sky, a
#: reference, an option) is the whole request's.
OBSERVATION_FIELDS = frozenset({"inputs", "antennas", "pols", "lst_range_h", "freq_range_mhz"})


def check_options(options: Mapping[str, Any] | None) -> None:
    """Refuse calibration options that do nothing with the others given, or no products.

    Raises
    ------
    autocal.service.submission_checks.SubmissionError
        Naming the field (:func:`autocal.pipeline.option_rules.calibration_refusals`, or an
        empty ``products``).
    """
    from autocal.pipeline.option_rules import calibration_refusals
    from autocal.service.submission_checks import SubmissionError

    for name, why in calibration_refusals(dict(options or {})):
        raise SubmissionError(name, why)
    if options is not None and options.get("products") == []:
        raise SubmissionError(
            "products",
            "products is empty: name at least one of calh5, calfits, hdf5, png (the hdf5 "
            "product is always written), or leave it out for calh5, hdf5 and png",
        )


def check_submission(inputs: Sequence[Path], opts: Mapping[str, Any]) -> None:
    """Run the checks of :mod:`autocal.service.submission_checks` on a calibration."""
    from autocal.service.submission_checks import (
        check_distinct,
        check_input_kind,
        check_references,
        check_sky_varies,
        check_uvh5_inputs,
    )

    check_distinct(inputs, "inputs")
    if opts.get("reference"):
        check_distinct(opts["reference"], "reference")
    if check_input_kind(inputs, opts) == "uvh5":
        check_uvh5_inputs(inputs, opts)
    check_sky_varies(opts.get("sky"), opts.get("trxr_prior"))
    if opts.get("reference"):
        check_references(opts["reference"])


def job_key(kind: str, config: CalibrationConfig) -> str:
    """Return the deduplication key of a job.

    Parameters
    ----------
    kind
        The job kind.
    config
        The resolved configuration.

    Returns
    -------
    str
        SHA-256 (hex) of the kind, the sorted inputs and the rest of the configuration.
    """
    payload = config.model_dump(mode="json")
    inputs = sorted(payload.pop("inputs"))
    text = json.dumps({"kind": kind, "inputs": inputs, "config": payload}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def night_of(paths: Iterable[str | Path]) -> int | None:
    """Return the integer JD of the first (earliest) ``zen.<JD>.*`` input, if any."""
    nights = [int(m.group(1)) for p in paths if (m := ZEN_JD.match(Path(p).name))]
    return min(nights) if nights else None


def submit_calibration(
    store: JobStore,
    settings: Settings,
    inputs: Sequence[str],
    options: Mapping[str, Any] | None = None,
    *,
    kind: str = "calibrate",
    force: bool = False,
    submitted_by: str | None = None,
) -> tuple[dict[str, Any], bool]:
    """Queue a calibration of one observation, idempotently.

    Parameters
    ----------
    store
        The job store.
    settings
        The service settings.
    inputs
        Input paths or upload ids.
    options
        Further :class:`CalibrationConfig` fields.
    kind
        The job kind.
    force
        Queue a new job even if an identical one is queued, running or succeeded.
    submitted_by
        The name of the API token that asked for it.

    Returns
    -------
    (dict, bool)
        The job record and whether it was created (``False``: an identical job exists).
    """
    config = build_config(settings, inputs, options)
    key = job_key(kind, config)
    # The store makes identical concurrent submissions safe (a unique active-key column).
    stored = config.model_dump(mode="json")
    job, created = store.submit(
        stored,
        kind=kind,
        night=night_of(config.inputs),
        antennas=config.antennas,
        dedupe_key=key,
        force=force,
        max_attempts=settings.max_attempts,
        submitted_by=submitted_by,
        input_fingerprints=fingerprint_config(stored, settings),
    )
    logger.info(
        "%s job %s (%s, %d input(s))",
        "queued" if created else "existing",
        job["id"],
        kind,
        len(config.inputs),
    )
    return job, created


# nights ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class NightFile:
    """A file named ``zen.<JD>.<fraction>.<kind>``."""

    path: Path
    night: int
    start: float
    kind: str


@dataclass
class ObservationGroup:
    """Files of one night, folder and kind with consecutive start times."""

    night: int
    kind: str
    folder: Path
    files: list[NightFile] = field(default_factory=list)

    @property
    def paths(self) -> list[str]:
        """The files, in time order."""
        return [str(f.path) for f in self.files]


def parse_file_name(path: Path) -> NightFile | None:
    """Return the night, start JD and kind of a ``zen.<JD>.<fraction>.*uvh5*`` file name."""
    match = ZEN_NAME.match(path.name)
    if match is None:
        return None
    jd = int(match.group("jd"))
    return NightFile(path, jd, jd + float("0." + match.group("frac")), match.group("kind"))


def find_night_files(
    settings: Settings, *, night: int | None = None, folder: str | Path | None = None
) -> list[NightFile]:
    """Find the UVH5 files of a night (in the data roots) or in a folder.

    Parameters
    ----------
    settings
        The service settings.
    night
        Integer JD; searched recursively in every data root (or only in ``folder``).
    folder
        A folder under the allowed roots, searched recursively.

    Returns
    -------
    list of NightFile
        Resolved files under the allowed roots, sorted by start time.
    """
    if night is None and folder is None:
        raise NightlyError("give a night (integer JD) or a folder")
    if folder is not None:
        top = resolve_input(str(folder), settings, what="folder")
        if not top.is_dir():
            raise InputPathError(f"folder {str(folder)!r} is not a folder")
        tops = [top]
    else:
        tops = [r for r in settings.resolved_data_roots() if r.is_dir()]
        if not tops:
            raise NightlyError(
                "no data roots to search: set AUTOCAL_DATA_ROOTS (or AUTOCAL_DATA_DIR)"
            )
    pattern = f"zen.{night}.*" if night is not None else "zen.*"
    found: dict[Path, NightFile] = {}
    for top in tops:
        try:
            candidates = list(top.rglob(pattern))
        except OSError as err:
            logger.warning("cannot scan %s: %s", top, err)
            continue
        for path in candidates:
            parsed = parse_file_name(path)
            if parsed is None or (night is not None and parsed.night != night):
                continue
            real = check_under_roots(path, settings)
            if real is None:
                logger.warning("skipping %s: it resolves outside the allowed roots", path)
                continue
            if not real.is_file() or real in found:
                continue
            found[real] = NightFile(real, parsed.night, parsed.start, parsed.kind)
    return sorted(found.values(), key=lambda f: (f.start, str(f.path)))


def group_observations(
    files: Iterable[NightFile], gap_factor: float = GAP_FACTOR
) -> list[ObservationGroup]:
    """Group files into observations (see the module docstring).

    Parameters
    ----------
    files
        The files of one or more nights.
    gap_factor
        A gap between consecutive starts larger than ``gap_factor`` times the typical
        spacing of the group (the lower median) starts a new observation.

    Returns
    -------
    list of ObservationGroup
        Sorted by night, then start time.
    """
    groups: dict[tuple[Path, int, str], list[NightFile]] = {}
    for f in files:
        groups.setdefault((f.path.parent, f.night, f.kind), []).append(f)
    out: list[ObservationGroup] = []
    for (folder, night, kind), members in groups.items():
        members.sort(key=lambda f: f.start)
        starts = np.array([f.start for f in members])
        steps = np.diff(starts)
        # the lower median: with two steps, the shorter one (a gap cannot hide itself)
        typical = float(np.sort(steps)[(steps.size - 1) // 2]) if steps.size else 0.0
        current = ObservationGroup(night, kind, folder, [members[0]])
        for step, member in zip(steps, members[1:], strict=True):
            if typical > 0 and step > gap_factor * typical:
                out.append(current)
                current = ObservationGroup(night, kind, folder, [])
            current.files.append(member)
        out.append(current)
    out.sort(key=lambda g: (g.night, g.files[0].start, g.kind))
    return out


def find_observations(
    settings: Settings, *, night: int | None = None, folder: str | Path | None = None
) -> list[ObservationGroup]:
    """Find and group the observations of a night or a folder (nothing is submitted).

    Parameters
    ----------
    settings
        The service settings.
    night
        Integer JD.
    folder
        A folder under the allowed roots.

    Returns
    -------
    list of ObservationGroup
        The observations.

    Raises
    ------
    NightlyError
        If nothing matches (status 404) or neither ``night`` nor ``folder`` is given.
    """
    files = find_night_files(settings, night=night, folder=folder)
    if not files:
        where = str(folder) if folder is not None else "the data roots"
        what = f"zen.{night}.*uvh5* files" if night is not None else "zen.<JD>.*uvh5* files"
        raise NightlyError(f"no {what} found under {where}", status_code=404)
    return group_observations(files)


def submit_nightly(
    store: JobStore,
    settings: Settings,
    *,
    night: int | None = None,
    folder: str | Path | None = None,
    force: bool = False,
    options: Mapping[str, Any] | None = None,
    submitted_by: str | None = None,
) -> dict[str, Any]:
    """Submit one calibration job per observation of a night or folder, idempotently.

    Parameters
    ----------
    store
        The job store.
    settings
        The service settings.
    night
        Integer JD of the night (files searched recursively in the data roots, or in
        ``folder`` when given).
    folder
        A folder under the allowed roots (all nights found in it when ``night`` is None).
    force
        Submit new jobs even for observations that already have one.
    options
        Calibration options shared by every job (:class:`CalibrationConfig` fields other
        than ``inputs``).
    submitted_by
        The name of the API token that asked for the jobs.

    Returns
    -------
    dict
        ``night``, ``observations`` (each ``night``, ``kind``, ``files``, ``job_id``,
        ``state``, ``created``, ``error``; an observation whose own files the submission
        checks refuse (:data:`OBSERVATION_FIELDS`) has no job, state ``refused`` and the
        reason in ``error``), ``created``, ``existing`` and ``refused`` counts.

    Raises
    ------
    NightlyError
        Nothing found or bad arguments.
    InputPathError
        A folder or option path outside the allowed roots.
    pydantic.ValidationError
        Invalid options.
    autocal.service.submission_checks.SubmissionError
        For the whole request: an option that does nothing with the others, a sky or a
        reference the checks refuse, or every observation refused.
    """
    from autocal.service.submission_checks import SubmissionError

    check_options(options)  # the whole request's: refused before any observation
    observations = find_observations(settings, night=night, folder=folder)
    entries = []
    for group in observations:
        entry: dict[str, Any] = {"night": group.night, "kind": group.kind, "files": group.paths}
        try:
            job, created = submit_calibration(
                store, settings, group.paths, options, force=force, submitted_by=submitted_by
            )
        except SubmissionError as err:
            if err.field not in OBSERVATION_FIELDS:  # the request's (sky, reference...)
                raise
            # this observation's files (a truncated file, an antenna or LSTs it lacks):
            # reported with it, the night's other observations still submitted
            logger.warning("nightly: observation %s refused: %s", group.paths[0], err)
            entry.update(job_id=None, state="refused", created=False, error=str(err))
        else:
            entry.update(job_id=job["id"], state=job["state"], created=created, error=None)
        entries.append(entry)
    nights = sorted({g.night for g in observations})
    ncreated = sum(e["created"] for e in entries)
    nrefused = sum(e["job_id"] is None for e in entries)
    if entries and nrefused == len(entries):
        first = next(e for e in entries if e["error"])
        raise SubmissionError(
            "inputs",
            f"every observation ({nrefused}) was refused; the first: {first['error']}",
        )
    logger.info(
        "nightly %s: %d observation(s), %d new job(s)",
        night if night is not None else folder,
        len(entries),
        ncreated,
    )
    return {
        "night": night if night is not None else (nights[0] if len(nights) == 1 else None),
        "observations": entries,
        "created": ncreated,
        "existing": len(entries) - ncreated - nrefused,
        "refused": nrefused,
    }
