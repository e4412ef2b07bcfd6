"""Job records as the API shows them, to token holders and to anonymous readers.

A client that sent a valid API token sees everything. An anonymous reader (reads are
anonymous unless ``AUTOCAL_READ_AUTH=1``) sees the job without what describes the server:
paths are shown relative to the data root they lie under (``hera/zen.2459122.uvh5``, which
is also how a client names an input), paths under the state folder as ``<state>/...``, any
other absolute path by its file name only (``.../name``); the worker (host name and PID) is
omitted, as are worker names inside messages; the log tail is empty (``log_hidden`` says so).
"""

from __future__ import annotations

import re
from datetime import datetime
from pathlib import Path
from typing import Any

from autocal.service.paths import allowed_roots
from autocal.service.schemas import JobDetail, JobLinks, JobSummary, JobTimings, json_safe
from autocal.service.settings import Settings

#: An absolute POSIX path inside a text (a slash after a start, space, quote or bracket).
_ABSOLUTE = re.compile(r"(?<![\w.~/>])/(?:[^\s'\"(),;:\[\]{}]+/)*([^\s'\"(),;:\[\]{}/]*)")
#: A worker id (``host:pid:tag``), alone (provenance) or after "worker " (store messages).
_WORKER = re.compile(r"(?:\bworker )?\b[\w.-]+:\d+:[0-9a-f]{6}\b")


class Redactor:
    """Rewrite texts and values for an anonymous reader (see the module docstring).

    Parameters
    ----------
    settings
        The service settings (data roots, state folder).
    """

    def __init__(self, settings: Settings) -> None:
        state = settings.state_dir.expanduser().resolve()
        prefixes = [(f"{root}/", "") for root in allowed_roots(settings) if root != state]
        prefixes.append((f"{state}/", "<state>/"))
        # the longest prefix first, so a root inside another is replaced by its own name
        self._prefixes = sorted(prefixes, key=lambda p: -len(p[0]))

    def text(self, value: str) -> str:
        """Return ``value`` with server paths made relative and worker names removed."""
        for prefix, replacement in self._prefixes:
            value = value.replace(prefix, replacement)
        value = _WORKER.sub("a worker", value)
        return _ABSOLUTE.sub(lambda m: f".../{m.group(1)}" if m.group(1) else "...", value)

    def value(self, value: Any) -> Any:
        """Return a JSON-like value with every string (keys too) passed through :meth:`text`."""
        if isinstance(value, str):
            return self.text(value)
        if isinstance(value, dict):
            return {self.value(key): self.value(item) for key, item in value.items()}
        if isinstance(value, (list, tuple)):
            return [self.value(item) for item in value]
        if isinstance(value, Path):
            return self.text(str(value))
        return value


def job_links(job_id: str) -> JobLinks:
    """Return the URLs of the operations on a job."""
    base = f"/jobs/{job_id}"
    return JobLinks(
        self=base, cancel=f"{base}/cancel", results=f"{base}/results", products=f"{base}/products"
    )


def _timings(job: dict[str, Any]) -> JobTimings:
    started, finished = job.get("started_at"), job.get("finished_at")
    duration = None
    if started and finished:
        duration = (
            datetime.fromisoformat(finished) - datetime.fromisoformat(started)
        ).total_seconds()
    return JobTimings(
        created=job.get("created_at"),
        started=started,
        finished=finished,
        heartbeat=job.get("heartbeat_at"),
        duration_s=duration,
    )


def _summary_fields(job: dict[str, Any], redactor: Redactor | None) -> dict[str, Any]:
    message = job.get("message") or ""
    return {
        "id": job["id"],
        "kind": job["kind"],
        "state": job["state"],
        "progress": float(job.get("progress") or 0.0),
        "message": redactor.text(message) if redactor else message,
        "night": job.get("night"),
        "antennas": job.get("antennas"),
        "attempts": int(job.get("attempts") or 0),
        "timings": _timings(job),
        "links": job_links(job["id"]),
    }


def job_summary(job: dict[str, Any], redactor: Redactor | None = None) -> JobSummary:
    """Return the listing view of a job record (``redactor``: for an anonymous reader)."""
    return JobSummary(**_summary_fields(job, redactor))


def job_detail(
    job: dict[str, Any], log_lines: int = 50, redactor: Redactor | None = None
) -> JobDetail:
    """Return the full view of a job record.

    Parameters
    ----------
    job
        The store's record.
    log_lines
        Lines of the log tail returned.
    redactor
        ``None`` for a token holder (everything); a :class:`Redactor` for an anonymous
        reader (relative paths, no worker, no log).

    Returns
    -------
    JobDetail
        The response model.
    """
    log = (job.get("log") or "").splitlines()
    products = job.get("products") or {}
    fields = {
        "config": json_safe(job.get("config") or {}),
        "provenance": json_safe(job.get("provenance")),
        "result": json_safe(job.get("result")),
        "error": job.get("error"),
    }
    if redactor is not None:
        fields = {name: redactor.value(value) for name, value in fields.items()}
    return JobDetail(
        **_summary_fields(job, redactor),
        **fields,
        max_attempts=int(job.get("max_attempts") or 0),
        worker=None if redactor else job.get("worker"),
        submitted_by=None if redactor else job.get("submitted_by"),
        cancel_requested=bool(job.get("cancel_requested")),
        log_tail=[] if redactor or not log_lines else log[-log_lines:],
        log_hidden=redactor is not None,
        products={name: f"/jobs/{job['id']}/products/{name}" for name in sorted(products)},
    )
