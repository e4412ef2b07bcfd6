"""A request-body size limit enforced before a byte of an oversized body is read.

Every request but an upload (``/uploads``, which has its own limit,
``AUTOCAL_MAX_UPLOAD_BYTES``) may carry at most ``AUTOCAL_MAX_BODY_BYTES`` (4 MiB). A
declared ``Content-Length`` above the limit is answered 413 at once, before the body is read
and before the token is checked, so an anonymous client cannot make the API read 200 MB to
learn it lacks a token; a body sent without a length is counted while it arrives and cut off
with a 413 at the first byte beyond the limit.
"""

from __future__ import annotations

import json

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

#: Paths with their own limit (streamed file uploads).
EXEMPT_PREFIXES = ("/uploads",)


def too_large_message(limit: int) -> str:
    """Return the 413 message for a body over ``limit`` bytes."""
    return (
        f"the request body exceeds the limit of {limit} bytes (AUTOCAL_MAX_BODY_BYTES); "
        "send fewer or shorter values, or upload files with POST /uploads"
    )


class BodyLimitMiddleware:
    """Answer 413 for a request body over ``limit`` bytes (uploads excepted).

    Parameters
    ----------
    app
        The wrapped application.
    limit
        Largest body in bytes.
    """

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = int(limit)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Check the declared length, then count the body as it arrives."""
        if scope["type"] != "http" or str(scope.get("path", "")).startswith(EXEMPT_PREFIXES):
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.strip().isdigit() and int(declared) > self.limit:
            await self._refuse(send)
            return
        received = 0

        async def counted() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    # FastAPI passes an HTTPException raised while reading the body on to
                    # the application's handler, which answers it as JSON
                    raise HTTPException(413, too_large_message(self.limit))
            return message

        await self.app(scope, counted, send)

    async def _refuse(self, send: Send) -> None:
        body = json.dumps({"detail": too_large_message(self.limit)}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
