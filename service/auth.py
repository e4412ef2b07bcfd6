"""The API token required by write endpoints (``Authorization: Bearer <token>``).

Without ``AUTOCAL_API_TOKEN`` the service is read-only: write endpoints answer 503 with a
message telling the operator to set it. A missing or wrong token is a 401 with a
``WWW-Authenticate: Bearer`` challenge. Tokens are compared in constant time.
"""

from __future__ import annotations

import hmac
import logging

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from autocal.service.schemas import ApiError
from autocal.service.settings import Settings

logger = logging.getLogger(__name__)

_bearer = HTTPBearer(
    auto_error=False,
    scheme_name="APIToken",
    description="the service's API token (AUTOCAL_API_TOKEN), as `Authorization: Bearer <token>`",
)


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


def require_token(
    request: Request,
    credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),  # noqa: B008
) -> None:
    """Refuse the request unless it carries the configured API token (a dependency).

    Parameters
    ----------
    request
        The request (for the settings).
    credentials
        The parsed ``Authorization`` header, if any.

    Raises
    ------
    ApiError
        503 if no token is configured; 401 if the token is missing or wrong.
    """
    expected = app_settings(request).api_token
    if not expected:
        raise ApiError(
            503,
            "write endpoints are disabled because no API token is configured; the operator "
            "must set AUTOCAL_API_TOKEN and restart the service",
        )
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise ApiError(
            401,
            "this endpoint needs the API token: send 'Authorization: Bearer <token>'",
            headers={"WWW-Authenticate": 'Bearer realm="autocal"'},
        )
    if not token_matches(credentials.credentials, expected):
        client = request.client.host if request.client else "?"
        logger.warning("rejected a wrong API token from %s for %s", client, request.url.path)
        raise ApiError(
            401,
            "the API token is wrong",
            headers={"WWW-Authenticate": 'Bearer realm="autocal", error="invalid_token"'},
        )
