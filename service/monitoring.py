"""Queries of the per-antenna history: latest state, series over nights, nights and outliers.

The values of an antenna-pol on a night (:func:`night_values`) are those of its
observations that night with one configuration: the median over the observations of each
value, with the median of their sigmas (the observations of a night share the same
systematics, so the sigma is not divided down). Every function raises
:class:`UnknownAntennaError` or :class:`UnknownNightError` naming what exists.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from typing import Any

import numpy as np
from sqlalchemy import func, select

from autocal.errors import AutocalError
from autocal.service.history import AntennaNight, ensure_table
from autocal.service.outliers import night_outliers
from autocal.service.store import Job, JobStore

logger = logging.getLogger(__name__)

#: Earlier nights an antenna's history test looks back over.
HISTORY_NIGHTS = 30
#: Values combined over a night's observations (median; sigmas: median too).
VALUE_FIELDS = (
    "G",
    "sigma_G",
    "abs_g",
    "sigma_abs_g",
    "Trxr",
    "sigma_Trxr",
    "reduced_chi2",
    "flagged_fraction",
    "ratio",
    "sigma_ratio",
)
#: At most this many existing names are listed in a 404 message.
LISTED = 50


class MonitoringError(AutocalError):
    """A monitoring query names something the history does not hold (HTTP 404)."""

    status_code = 404


class UnknownAntennaError(MonitoringError):
    """No history for this antenna (or polarisation)."""


class UnknownNightError(MonitoringError):
    """No job and no history on this night."""


def _listed(values: list[Any]) -> str:
    shown = ", ".join(str(v) for v in values[:LISTED])
    more = f" (and {len(values) - LISTED} more)" if len(values) > LISTED else ""
    return (shown + more) or "none yet"


def history_rows(
    store: JobStore,
    *,
    antenna: int | None = None,
    pol: str | None = None,
    nights: tuple[int | None, int | None] = (None, None),
) -> list[dict[str, Any]]:
    """Return history rows (one per job, antenna and pol), by night then JD."""
    ensure_table(store)
    query = select(AntennaNight).order_by(AntennaNight.night, AntennaNight.jd, AntennaNight.id)
    if antenna is not None:
        query = query.where(AntennaNight.antenna == antenna)
    if pol is not None:
        query = query.where(AntennaNight.pol == pol)
    if nights[0] is not None:
        query = query.where(AntennaNight.night >= nights[0])
    if nights[1] is not None:
        query = query.where(AntennaNight.night <= nights[1])
    with store.session() as s:
        return [r.to_dict() for r in s.scalars(query)]


def _combine(rows: list[dict[str, Any]]) -> dict[str, Any]:
    latest = max(rows, key=lambda r: r["recorded_at"])
    out = {k: latest[k] for k in ("antenna", "pol", "night", "config_hash", "job_id")}
    for name in VALUE_FIELDS:
        values = [r[name] for r in rows if r[name] is not None]
        out[name] = float(np.median(values)) if values else None
    out["observations"] = sorted({r["observation"] for r in rows})
    out["jobs"] = sorted({r["job_id"] for r in rows})
    out["bands"] = latest["bands"]
    out["effects"] = latest["effects"]
    return out


def night_values(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Combine history rows into one value per night, antenna, pol and configuration."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = defaultdict(list)
    for row in rows:
        groups[(row["night"], row["antenna"], row["pol"], row["config_hash"])].append(row)
    return [_combine(g) for _, g in sorted(groups.items(), key=lambda kv: kv[0][:3])]


def known_antennas(store: JobStore) -> list[int]:
    """Return the antennas with history."""
    ensure_table(store)
    with store.session() as s:
        return sorted(s.scalars(select(AntennaNight.antenna).distinct()))


def known_nights(store: JobStore) -> list[int]:
    """Return the nights with a job or history (sorted)."""
    ensure_table(store)
    with store.session() as s:
        nights = set(s.scalars(select(AntennaNight.night).distinct()))
        nights |= set(s.scalars(select(Job.night).where(Job.night.is_not(None)).distinct()))
    return sorted(int(n) for n in nights)


def outliers_of_night(store: JobStore, night: int, **thresholds: float) -> list[dict[str, Any]]:
    """Return the outliers of a night (:func:`autocal.service.outliers.night_outliers`)."""
    tonight = night_values(history_rows(store, nights=(night, night)))
    if not tonight:
        return []
    with store.session() as s:
        earlier_nights = sorted(
            s.scalars(select(AntennaNight.night).where(AntennaNight.night < night).distinct()),
            reverse=True,
        )[:HISTORY_NIGHTS]
    earlier: list[dict[str, Any]] = []
    if earlier_nights:
        rows = history_rows(store, nights=(min(earlier_nights), night - 1))
        earlier = night_values(rows)
    return night_outliers(tonight, earlier, **thresholds)


def antenna_history(
    store: JobStore,
    antenna: int,
    *,
    pol: str | None = None,
    nights: tuple[int | None, int | None] = (None, None),
) -> list[dict[str, Any]]:
    """Return an antenna's values night by night (with sigmas, bands and effects).

    Raises
    ------
    UnknownAntennaError
        If the antenna (or the polarisation) has no history at all.
    """
    everything = history_rows(store, antenna=antenna)
    if not everything:
        raise UnknownAntennaError(
            f"no history for antenna {antenna}; antennas with history: "
            f"{_listed(known_antennas(store))}"
        )
    pols = sorted({r["pol"] for r in everything})
    if pol is not None and pol not in pols:
        raise UnknownAntennaError(f"antenna {antenna} has no history in pol {pol!r} (pols: {pols})")
    rows = [
        r
        for r in everything
        if (pol is None or r["pol"] == pol)
        and (nights[0] is None or r["night"] >= nights[0])
        and (nights[1] is None or r["night"] <= nights[1])
    ]
    return night_values(rows)


def latest_state(store: JobStore) -> list[dict[str, Any]]:
    """Return each antenna-pol's values on the latest night it was calibrated.

    Each entry carries ``outliers``: the reasons it is an outlier that night.
    """
    values = night_values(history_rows(store))
    latest: dict[tuple[int, str], dict[str, Any]] = {}
    for entry in values:  # sorted by night: the last one wins
        latest[(entry["antenna"], entry["pol"])] = entry
    flagged: dict[tuple[int, str, int], list[str]] = defaultdict(list)
    for night in sorted({e["night"] for e in latest.values()}):
        for outlier in outliers_of_night(store, night):
            flagged[(outlier["antenna"], outlier["pol"], night)].append(outlier["reason"])
    return [
        {**e, "outliers": flagged.get((e["antenna"], e["pol"], e["night"]), [])}
        for _, e in sorted(latest.items())
    ]


def _job_counts(store: JobStore) -> dict[int, dict[str, int]]:
    with store.session() as s:
        rows = s.execute(
            select(Job.night, Job.state, func.count())
            .where(Job.night.is_not(None))
            .group_by(Job.night, Job.state)
        ).all()
    counts: dict[int, dict[str, int]] = defaultdict(dict)
    for night, state, n in rows:
        counts[int(night)][str(state)] = int(n)
    return counts


def nights_overview(store: JobStore) -> list[dict[str, Any]]:
    """Return every night, newest first: antennas and observations recorded, jobs by state."""
    ensure_table(store)
    with store.session() as s:
        recorded = s.execute(
            select(
                AntennaNight.night,
                func.count(func.distinct(AntennaNight.antenna)),
                func.count(func.distinct(AntennaNight.observation)),
            ).group_by(AntennaNight.night)
        ).all()
    per_night = {int(n): (int(a), int(o)) for n, a, o in recorded}
    jobs = _job_counts(store)
    out = []
    for night in sorted(set(per_night) | set(jobs), reverse=True):
        antennas, observations = per_night.get(night, (0, 0))
        out.append(
            {
                "night": night,
                "antennas": antennas,
                "observations": observations,
                "jobs": jobs.get(night, {}),
            }
        )
    return out


def night_detail(store: JobStore, night: int) -> dict[str, Any]:
    """Return a night: the antennas calibrated, the outliers, and the failed jobs with reasons.

    Raises
    ------
    UnknownNightError
        If no job ran on this night and nothing was recorded.
    """
    values = night_values(history_rows(store, nights=(night, night)))
    jobs = store.list(night=night, limit=10**6)
    if not values and not jobs:
        raise UnknownNightError(
            f"nothing recorded on night {night}; nights: {_listed(known_nights(store))}"
        )
    failed = [
        {
            "job_id": j["id"],
            "kind": j["kind"],
            "error": j.get("error") or j.get("message") or "",
            "inputs": [str(p) for p in (j.get("config") or {}).get("inputs") or []],
            "finished": j.get("finished_at"),
        }
        for j in jobs
        if j["state"] == "failed"
    ]
    counts: dict[str, int] = defaultdict(int)
    for j in jobs:
        counts[j["state"]] += 1
    return {
        "night": night,
        "antennas": values,
        "outliers": outliers_of_night(store, night),
        "failed_jobs": failed,
        "jobs": dict(counts),
    }
