"""Authentication of API clients by named tokens (``Authorization: Bearer <token>``).

Tokens and their names are configured by ``AUTOCAL_API_TOKENS``, ``AUTOCAL_API_TOKENS_FILE``
and ``AUTOCAL_API_TOKEN`` (:mod:`autocal.service.tokens`). Without any token the service is
read-only: write endpoints answer 503 with a message telling the operator to set one. A
missing or wrong token on an endpoint that needs one is a 401 with a
``WWW-Authenticate: Bearer`` challenge; a client with too many failures in the window is
answered 429 with ``Retry-After`` before its token is compared. Tokens are compared in
constant time, against every configured token.

Reads (``GET``) are anonymous unless ``AUTOCAL_READ_AUTH=1``; an anonymous reader sees jobs
without server paths, worker names or logs (:mod:`autocal.service.job_views`). A read that
carries a token has it checked (a wrong token is a 401, never silently anonymous).
"""

from __future__ import annotations

import hmac
import logging

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from autocal.service.schemas import ApiError
from autocal.service.settings import Settings
from autocal.service.tokens import FailedAuthLimiter

logger = logging.getLogger(__name__)

_bearer = HTTPBearer(
    auto_error=False,
    scheme_name="APIToken",
    description="one of the service's named API tokens (AUTOCAL_API_TOKENS, "
    "AUTOCAL_API_TOKEN), as `Authorization: Bearer <token>`",
)
_CHALLENGE = 'Bearer realm="autocal"'


def app_settings(request: Request) -> Settings:
    """Return the settings of the application serving ``request`` (a dependency)."""
    return request.app.state.settings


def token_matches(given: str, expected: str) -> bool:
    """Compare a token with the configured one in constant time.

    Parameters
    ----------
    given
        The token sent by the client.
    expected
        The configured token (non-empty).

    Returns
    -------
    bool
        Whether they are equal.
    """
    return hmac.compare_digest(given.encode("utf-8"), expected.encode("utf-8"))


def token_name(given: str, tokens: dict[str, str]) -> str | None:
    """Return the name of the configured token equal to ``given``, or ``None``.

    Every token is compared (in constant time), so the time taken does not tell which
    token, if any, was close.
    """
    found = None
    for name, expected in tokens.items():
        if token_matches(given, expected):
            found = name
    return found


def _client(request: Request) -> str:
    return request.client.host if request.client else "?"


def _check(request: Request, credentials: HTTPAuthorizationCredentials | None) -> str:
    """Return the caller's token name; raise 429 or 401 (and count the failure)."""
    limiter: FailedAuthLimiter = request.app.state.auth_limiter
    client = _client(request)
    wait = limiter.retry_after(client)
    if wait is not None:
        raise ApiError(
            429,
            f"too many failed authentications from this address; retry in {wait} s",
            headers={"Retry-After": str(wait)},
        )
    if credentials is None or credentials.scheme.lower() != "bearer":
        limiter.failed(client)
        raise ApiError(
            401,
            "this endpoint needs an API token: send 'Authorization: Bearer <token>'",
            headers={"WWW-Authenticate": _CHALLENGE},
        )
    name = token_name(credentials.credentials, request.app.state.tokens)
    if name is None:
        limiter.failed(client)
        logger.warning("rejected a wrong API token from %s for %s", client, request.url.path)
        raise ApiError(
            401,
            "the API token is wrong",
            headers={"WWW-Authenticate": f'{_CHALLENGE}, error="invalid_token"'},
        )
    return name


def require_token(
    request: Request,
    credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),  # noqa: B008
) -> str:
    """Refuse the request unless it carries a configured API token (a dependency).

    Parameters
    ----------
    request
        The request (for the tokens and the failure counts).
    credentials
        The parsed ``Authorization`` header, if any.

    Returns
    -------
    str
        The name of the caller's token (recorded with the jobs it submits).

    Raises
    ------
    ApiError
        503 if no token is configured; 429 after too many failures from the client's
        address; 401 if the token is missing or wrong.
    """
    if not request.app.state.tokens:
        raise ApiError(
            503,
            "write endpoints are disabled because no API token is configured; the operator "
            "must set AUTOCAL_API_TOKENS (or AUTOCAL_API_TOKEN) and restart the service",
        )
    return _check(request, credentials)


def read_access(
    request: Request,
    credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),  # noqa: B008
) -> str | None:
    """Return the reader's token name, or ``None`` for an anonymous reader (a dependency).

    Raises
    ------
    ApiError
        With ``AUTOCAL_READ_AUTH=1``, as :func:`require_token`; otherwise only for a token
        that is sent and wrong (401) or a client over the failure limit (429).
    """
    if credentials is None and not app_settings(request).read_auth:
        return None
    return _check(request, credentials)
