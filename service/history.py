"""Per-antenna history across nights: what every succeeded calibration found, antenna by antenna.

Every succeeded ``calibrate`` job adds one row per antenna and polarisation to the table
``antenna_history`` of the job store (same database, SQLite or PostgreSQL), keyed by night
(integer JD), observation (the first input file's name), antenna, polarisation, job and
configuration hash. A row holds, over the solved (unflagged) channels of the solution:

- the medians of ``G`` (raw/K), ``|g|`` (sqrt(raw/K)), ``Trxr`` (K) and the reduced chi^2,
  each with the median per-channel TOTAL 1-sigma (statistical plus systematic, as the
  solution product holds it); the channels' systematic errors are correlated, so the
  median sigma is kept rather than divided by the square root of the channel count;
- the same per band: 25 MHz bands on a fixed grid (100-125, 125-150 ... MHz), so that
  bands line up from night to night whatever the observation's channel range;
- the flagged fraction of the channels;
- the comparison's median ratio (autocal / reference) and its median sigma, when the job
  compared against reference gains;
- the diagnosis's named effects (in the order accepted), when a ``diagnose`` job of the same
  observation succeeded.

The worker records a job as it succeeds (:func:`record_job_safely`); :func:`backfill`
(``python -m autocal.service.history``) records the succeeded jobs already in a store.
Recording is idempotent: a job's rows are replaced, never duplicated.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import (
    JSON,
    DateTime,
    Float,
    Integer,
    String,
    UniqueConstraint,
    delete,
    select,
)
from sqlalchemy.exc import IntegrityError, OperationalError, ProgrammingError
from sqlalchemy.orm import Mapped, mapped_column

from autocal.service.store import Base, JobState, JobStore

logger = logging.getLogger(__name__)

#: Width (MHz) of the history's bands, on a grid starting at 0 MHz.
BAND_WIDTH_MHZ = 25.0
#: The quantities kept per antenna, pol and band: name -> (value array, sigma array).
QUANTITIES = ("G", "abs_g", "Trxr")


class AntennaNight(Base):
    """One antenna-polarisation of one succeeded calibration job."""

    __tablename__ = "antenna_history"
    __table_args__ = (UniqueConstraint("job_id", "antenna", "pol", name="uq_history_job_ant_pol"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(String(32), index=True)
    night: Mapped[int] = mapped_column(Integer, index=True)
    observation: Mapped[str] = mapped_column(String(256))
    jd: Mapped[float | None] = mapped_column(Float, nullable=True)
    antenna: Mapped[int] = mapped_column(Integer, index=True)
    pol: Mapped[str] = mapped_column(String(8))
    config_hash: Mapped[str] = mapped_column(String(16), index=True)
    recorded_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    G: Mapped[float | None] = mapped_column(Float, nullable=True)
    sigma_G: Mapped[float | None] = mapped_column(Float, nullable=True)  # noqa: N815 - the physics symbol
    abs_g: Mapped[float | None] = mapped_column(Float, nullable=True)
    sigma_abs_g: Mapped[float | None] = mapped_column(Float, nullable=True)
    Trxr: Mapped[float | None] = mapped_column(Float, nullable=True)
    sigma_Trxr: Mapped[float | None] = mapped_column(Float, nullable=True)  # noqa: N815 - the physics symbol
    reduced_chi2: Mapped[float | None] = mapped_column(Float, nullable=True)
    flagged_fraction: Mapped[float] = mapped_column(Float)
    bands: Mapped[list[dict[str, Any]]] = mapped_column(JSON)
    ratio: Mapped[float | None] = mapped_column(Float, nullable=True)
    sigma_ratio: Mapped[float | None] = mapped_column(Float, nullable=True)
    effects: Mapped[list[str] | None] = mapped_column(JSON, nullable=True)

    def to_dict(self) -> dict[str, Any]:
        """Return the row as plain data (``recorded_at`` as an ISO string)."""
        out = {c.name: getattr(self, c.name) for c in self.__table__.columns}
        out.pop("id")
        stamp = out["recorded_at"]
        out["recorded_at"] = (stamp if stamp.tzinfo else stamp.replace(tzinfo=UTC)).isoformat()
        return out


def ensure_table(store: JobStore) -> None:
    """Create the history table if missing (tolerating a concurrent creation)."""
    for attempt in range(5):
        try:
            Base.metadata.create_all(store.engine, tables=[AntennaNight.__table__])
            return
        except (IntegrityError, OperationalError, ProgrammingError):
            if attempt == 4:
                raise
            time.sleep(0.2 * (attempt + 1))


# values of a solution ----------------------------------------------------------------


def config_hash(config: dict[str, Any]) -> str:
    """Return a short hash of a job's configuration without its inputs.

    Two observations calibrated with the same settings share it, so their values can be
    compared night to night.
    """
    settings = {k: v for k, v in (config or {}).items() if k != "inputs"}
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def observation_name(config: dict[str, Any]) -> str:
    """Return the name of an observation: its first input file (sorted), plus the count."""
    inputs = sorted(Path(str(p)).name for p in (config or {}).get("inputs") or [])
    if not inputs:
        return "unknown"
    more = f" (+{len(inputs) - 1} files)" if len(inputs) > 1 else ""
    return f"{inputs[0][: 255 - len(more)]}{more}"  # the column holds 256 characters


def _median(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else None


def band_edges(freqs_mhz: np.ndarray) -> list[tuple[float, float]]:
    """Return the grid bands (:data:`BAND_WIDTH_MHZ` wide) that hold a channel."""
    starts = np.unique(np.floor(np.asarray(freqs_mhz) / BAND_WIDTH_MHZ) * BAND_WIDTH_MHZ)
    return [(float(s), float(s + BAND_WIDTH_MHZ)) for s in starts]


def _values(arrays: dict[str, np.ndarray], keep: np.ndarray) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for name in QUANTITIES:
        out[name] = _median(arrays[name][keep])
        out[f"sigma_{name}"] = _median(arrays[f"sigma_{name}"][keep])
    return out


def solution_rows(solution: Any) -> list[dict[str, Any]]:
    """Per antenna and polarisation: medians with sigmas overall and per band.

    Parameters
    ----------
    solution
        An :class:`autocal.fit.solution.Solution`.

    Returns
    -------
    list of dict
        ``antenna``, ``pol``, ``G``, ``sigma_G``, ``abs_g``, ``sigma_abs_g``, ``Trxr``,
        ``sigma_Trxr``, ``reduced_chi2``, ``flagged_fraction``, ``bands`` (list of
        ``{band, lo_mhz, hi_mhz, n_channels, G, sigma_G, ...}``) and ``jd``.
    """
    flags = np.asarray(solution.flags, dtype=bool)
    freqs_mhz = np.asarray(solution.freqs, dtype=np.float64) / 1e6
    arrays = {
        "G": solution.G,
        "sigma_G": solution.sigma_G,
        "abs_g": solution.abs_g,
        "sigma_abs_g": solution.sigma_abs_g,
        "Trxr": solution.Trxr,
        "sigma_Trxr": solution.sigma_Trxr,
        "reduced_chi2": solution.reduced_chi2,
    }
    jds = np.asarray(getattr(solution, "jds", []), dtype=np.float64)
    jd = float(np.mean(jds)) if jds.size else None
    edges = band_edges(freqs_mhz)
    rows = []
    for ia, ant in enumerate(np.asarray(solution.antennas).tolist()):
        for ip, pol in enumerate(solution.pols):
            one = {name: np.asarray(arr[ia, ip], dtype=np.float64) for name, arr in arrays.items()}
            ok = ~flags[ia, ip]
            bands = []
            for lo, hi in edges:
                keep = ok & (freqs_mhz >= lo) & (freqs_mhz < hi)
                band = {"band": f"{lo:g}-{hi:g}", "lo_mhz": lo, "hi_mhz": hi}
                bands.append({**band, "n_channels": int(keep.sum()), **_values(one, keep)})
            rows.append(
                {
                    "antenna": int(ant),
                    "pol": str(pol),
                    "jd": jd,
                    **_values(one, ok),
                    "reduced_chi2": _median(one["reduced_chi2"][ok]),
                    "flagged_fraction": float(1.0 - ok.mean()) if ok.size else 1.0,
                    "bands": bands,
                }
            )
    return rows


def comparison_ratios(result: dict[str, Any] | None) -> dict[tuple[int, str], tuple[Any, Any]]:
    """Return ``{(antenna, pol): (median ratio, median sigma)}`` of a job's comparison."""
    comparison = (result or {}).get("comparison") or {}
    out = {}
    for entry in comparison.get("per_antenna_pol") or []:
        key = (int(entry["antenna"]), str(entry["pol"]))
        out[key] = (entry.get("ratio_median"), entry.get("sigma_ratio_median"))
    return out


def _finite(value: Any) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


# recording ----------------------------------------------------------------------------


def _same_inputs(a: dict[str, Any], b: dict[str, Any]) -> bool:
    return sorted((a.get("config") or {}).get("inputs") or []) == sorted(
        (b.get("config") or {}).get("inputs") or []
    )


def _diagnosis_effects(store: JobStore, job: dict[str, Any]) -> list[str] | None:
    """Return the effects named by the latest succeeded diagnosis of the job's observation."""
    if job.get("night") is None:
        return None
    diagnoses = [
        d
        for d in store.list(
            night=job["night"], kind="diagnose", state=JobState.succeeded.value, limit=10**6
        )
        if _same_inputs(d, job)
    ]
    if not diagnoses:
        return None
    latest = max(diagnoses, key=lambda d: d.get("finished_at") or "")
    return [str(e) for e in (latest.get("result") or {}).get("effects") or []]


def _record_effects(store: JobStore, job: dict[str, Any]) -> int:
    """Attach a succeeded diagnosis's effects to the history rows of its observation."""
    effects = [str(e) for e in (job.get("result") or {}).get("effects") or []]
    calibrations = [
        c
        for c in store.list(
            night=job.get("night"), kind="calibrate", state=JobState.succeeded.value, limit=10**6
        )
        if job.get("night") is not None and _same_inputs(c, job)
    ]
    ids = [c["id"] for c in calibrations]
    if not ids:
        return 0
    with store.session() as s:
        rows = list(s.scalars(select(AntennaNight).where(AntennaNight.job_id.in_(ids))))
        for row in rows:
            row.effects = effects
        return len(rows)


def record_job(store: JobStore, job_id: str) -> int:
    """Record a succeeded job in the history (replacing any rows it already has).

    A ``calibrate`` job adds one row per antenna and polarisation of its solution product
    (``hdf5``); a ``diagnose`` job attaches its effects to the rows of the calibrations of
    the same observation (same inputs). Other jobs, and jobs not succeeded, add nothing.

    Parameters
    ----------
    store
        The job store.
    job_id
        The job.

    Returns
    -------
    int
        The number of rows written or updated.

    Raises
    ------
    autocal.io.products.ProductFormatError
        If the job's solution product is missing or unreadable.
    """
    ensure_table(store)
    job = store.get(job_id)
    if job is None or job["state"] != JobState.succeeded.value:
        return 0
    if job["kind"] == "diagnose":
        return _record_effects(store, job)
    path = (job.get("products") or {}).get("hdf5")
    if job["kind"] != "calibrate" or path is None:
        return 0
    from autocal.io.products import read_solution  # the science stack, on first use only

    rows = solution_rows(read_solution(path))
    ratios = comparison_ratios(job.get("result"))
    effects = _diagnosis_effects(store, job)
    config = job.get("config") or {}
    common = {
        "job_id": job_id,
        "observation": observation_name(config),
        "config_hash": config_hash(config),
        "recorded_at": datetime.now(UTC),
        "effects": effects,
    }
    with store.session() as s:
        s.execute(delete(AntennaNight).where(AntennaNight.job_id == job_id))
        for row in rows:
            night = job.get("night")
            if night is None and row["jd"] is not None:
                night = int(row["jd"])
            ratio, sigma_ratio = ratios.get((row["antenna"], row["pol"]), (None, None))
            s.add(
                AntennaNight(
                    **common,
                    **row,
                    night=night if night is not None else 0,
                    ratio=_finite(ratio),
                    sigma_ratio=_finite(sigma_ratio),
                )
            )
    logger.info("history: recorded %d antenna-pol(s) of job %s", len(rows), job_id)
    return len(rows)


def record_job_safely(store: JobStore, job_id: str) -> int:
    """:func:`record_job`, logging (not raising) a failure: the job itself succeeded."""
    try:
        return record_job(store, job_id)
    except Exception as err:
        logger.warning("history: could not record job %s: %s", job_id, err)
        return 0


def backfill(store: JobStore, *, force: bool = False) -> dict[str, int]:
    """Record every succeeded job of the store (calibrations first, then diagnoses).

    Parameters
    ----------
    store
        The job store.
    force
        Record again jobs that already have rows.

    Returns
    -------
    dict
        ``recorded`` (jobs), ``rows`` (antenna-pols), ``skipped`` (already recorded) and
        ``failed`` (unreadable products; each is logged).
    """
    ensure_table(store)
    with store.session() as s:
        done = set(s.scalars(select(AntennaNight.job_id).distinct()))
    counts = {"recorded": 0, "rows": 0, "skipped": 0, "failed": 0}
    for kind in ("calibrate", "diagnose"):
        for job in store.list(state=JobState.succeeded.value, kind=kind, limit=10**9):
            if kind == "calibrate" and job["id"] in done and not force:
                counts["skipped"] += 1
                continue
            try:
                counts["rows"] += record_job(store, job["id"])
                counts["recorded"] += 1
            except Exception as err:
                logger.warning("history backfill: job %s: %s", job["id"], err)
                counts["failed"] += 1
    return counts


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m autocal.service.history``: backfill the history from the job store."""
    parser = argparse.ArgumentParser(
        prog="python -m autocal.service.history",
        description="Record the per-antenna history of every succeeded job already in the "
        "job store (AUTOCAL_DATABASE_URL / AUTOCAL_STATE_DIR); workers record new jobs "
        "themselves.",
    )
    parser.add_argument("--force", action="store_true", help="record again recorded jobs")
    args = parser.parse_args(argv)
    from autocal.service.settings import get_settings

    store = JobStore(get_settings().resolved_database_url())
    try:
        counts = backfill(store, force=args.force)
    finally:
        store.engine.dispose()
    logging.getLogger(__name__).info("history backfill: %s", counts)
    return 0 if counts["failed"] == 0 else 1


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
