"""HTTP routers of the job service, one per resource (jobs, uploads, nightly, health).

Shared here: the store dependency and the translation of the library's input errors into
HTTP answers with a message (:func:`as_api_error`).
"""

from __future__ import annotations

from typing import Any

from fastapi import Request
from pydantic import ValidationError

from autocal.pipeline.config import CalibrationConfig
from autocal.service.nightly import NightlyError
from autocal.service.paths import InputPathError
from autocal.service.schemas import ApiError
from autocal.service.store import JobStore
from autocal.service.submission_checks import SubmissionError

#: Problems listed in the message of a 422 (all are in ``errors``, up to MAX_ERRORS).
MAX_LISTED = 10
MAX_ERRORS = 100


def app_store(request: Request) -> JobStore:
    """Return the job store of the application serving ``request`` (a dependency)."""
    return request.app.state.store


def describe_problem(error: dict[str, Any], prefix: tuple[Any, ...] = ()) -> dict[str, str]:
    """Turn one pydantic error into ``{field, message, type}`` (no echo of the input).

    Parameters
    ----------
    error
        An item of ``ValidationError.errors()``.
    prefix
        Location prefix (e.g. ``("body",)``).

    Returns
    -------
    dict
        ``field`` (dotted location), ``message``, ``type``.
    """
    loc = (*prefix, *error.get("loc", ()))
    field = ".".join(str(x) for x in loc) or "body"
    kind = str(error.get("type", "value_error"))
    message = str(error.get("msg", "invalid value"))
    if kind == "extra_forbidden":
        message = f"unknown field {str(loc[-1]) if loc else field!r}: not accepted here (see /docs)"
    elif kind == "missing":
        message = "required field missing"
    elif message.startswith(("Value error, ", "Assertion failed, ")):
        message = message.split(", ", 1)[1]
    return {"field": field, "message": message, "type": kind}


def problems_message(what: str, problems: list[dict[str, str]]) -> str:
    """Return ``"<what>: field: why; field: why"`` listing the first problems."""
    listed = "; ".join(f"{p['field']}: {p['message']}" for p in problems[:MAX_LISTED])
    more = f" (and {len(problems) - MAX_LISTED} more)" if len(problems) > MAX_LISTED else ""
    return f"{what}: {listed}{more}"


def as_api_error(err: Exception) -> ApiError:
    """Translate an input error of the submission helpers into an HTTP error.

    Parameters
    ----------
    err
        A pydantic ``ValidationError`` (422), :class:`InputPathError` or
        :class:`NightlyError` (their status), a sky-model or pipeline error (422).

    Returns
    -------
    ApiError
        The error to raise.
    """
    if isinstance(err, ValidationError):
        problems = []
        for error in err.errors()[:MAX_ERRORS]:
            problem = describe_problem(error, ("body",))
            if not error.get("loc"):  # a model-level check: name the field it talks about
                named = [f for f in CalibrationConfig.model_fields if f in problem["message"]]
                problem["field"] = f"body.{named[0]}" if named else "body"
            problems.append(problem)
        return ApiError(
            422, problems_message("invalid calibration settings", problems), errors=problems
        )
    if isinstance(err, (InputPathError, NightlyError)):
        return ApiError(err.status_code, str(err))
    if isinstance(err, SubmissionError):
        problem = {"field": f"body.{err.field}", "message": str(err), "type": "submission_check"}
        return ApiError(422, str(err), errors=[problem])
    return ApiError(422, str(err))
