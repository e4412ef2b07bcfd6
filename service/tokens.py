"""The API's named tokens, checked when the service starts, and failed-attempt limiting.

Tokens come from three settings, merged:

- ``AUTOCAL_API_TOKENS``: ``name=token`` pairs separated by commas or new lines
  (``alice=...,nightly=...``);
- ``AUTOCAL_API_TOKENS_FILE``: a file of ``name=token`` lines (``#`` starts a comment), so
  tokens need not sit in the environment;
- ``AUTOCAL_API_TOKEN``: one token, named ``default`` (the older single-token setting).

Every token must be at least ``AUTOCAL_MIN_TOKEN_LENGTH`` characters (32 by default:
``python3 -c 'import secrets; print(secrets.token_urlsafe(32))'`` gives 43), names are
``[A-Za-z0-9_.-]{1,64}`` and unique, and two names cannot share a token.
:func:`named_tokens` raises :class:`TokenConfigError` with a one-line message otherwise;
``autocal serve`` and the application refuse to start on it.

:class:`FailedAuthLimiter` counts wrong or missing tokens per client address; past
``AUTOCAL_AUTH_FAILURES`` within ``AUTOCAL_AUTH_WINDOW_S`` seconds the client is answered
429 with ``Retry-After`` until the window has passed, before its token is even compared.
The counts live in the API process (each uvicorn worker process counts on its own).
"""

from __future__ import annotations

import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable

from autocal.errors import AutocalError
from autocal.service.settings import Settings

#: The name of the token given by ``AUTOCAL_API_TOKEN``.
DEFAULT_NAME = "default"
_NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")


class TokenConfigError(AutocalError):
    """The token settings are unusable (the message is one line naming the setting)."""


def _pairs(text: str, source: str) -> list[tuple[str, str]]:
    pairs = []
    for number, raw in enumerate(re.split(r"[,\n]", text), 1):
        item = raw.split("#", 1)[0].strip() if source.endswith("FILE") else raw.strip()
        if not item:
            continue
        name, sep, token = item.partition("=")
        if not sep:
            raise TokenConfigError(
                f"{source}: entry {number} is not name=token (e.g. alice=<token>)"
            )
        pairs.append((name.strip(), token.strip()))
    return pairs


def named_tokens(settings: Settings) -> dict[str, str]:
    """Return the configured tokens by name, after checking them.

    Parameters
    ----------
    settings
        The service settings.

    Returns
    -------
    dict
        ``name -> token``; empty when no token is configured (writes are then refused).

    Raises
    ------
    TokenConfigError
        A malformed entry, a bad or repeated name, a repeated token, a token shorter than
        ``min_token_length``, or an unreadable tokens file.
    """
    pairs = _pairs(settings.api_tokens, "AUTOCAL_API_TOKENS")
    if settings.api_tokens_file is not None:
        try:
            text = settings.api_tokens_file.expanduser().read_text()
        except (OSError, UnicodeDecodeError) as err:
            raise TokenConfigError(
                f"AUTOCAL_API_TOKENS_FILE {settings.api_tokens_file}: cannot read it ({err})"
            ) from None
        pairs += _pairs(text, "AUTOCAL_API_TOKENS_FILE")
    if settings.api_token:
        pairs.append((DEFAULT_NAME, settings.api_token))
    tokens: dict[str, str] = {}
    for name, token in pairs:
        if not _NAME.fullmatch(name):
            raise TokenConfigError(
                f"token name {name!r}: use 1-64 letters, digits, '_', '.' or '-'"
            )
        if name in tokens:
            raise TokenConfigError(f"token name {name!r} is given twice")
        if len(token) < settings.min_token_length:
            raise TokenConfigError(
                f"the token named {name!r} has {len(token)} characters; tokens need at least "
                f"{settings.min_token_length} (AUTOCAL_MIN_TOKEN_LENGTH): make one with "
                "python3 -c 'import secrets; print(secrets.token_urlsafe(32))'"
            )
        if token in tokens.values():
            raise TokenConfigError(f"the token named {name!r} is also given another name")
        tokens[name] = token
    return tokens


def checked_tokens(settings: Settings) -> dict[str, str]:
    """Return :func:`named_tokens`, also refusing read authentication without a token.

    Raises
    ------
    TokenConfigError
        As :func:`named_tokens`, or ``AUTOCAL_READ_AUTH=1`` with no token configured.
    """
    tokens = named_tokens(settings)
    if settings.read_auth and not tokens:
        raise TokenConfigError(
            "AUTOCAL_READ_AUTH=1 needs at least one token (AUTOCAL_API_TOKENS or "
            "AUTOCAL_API_TOKEN); without one nobody could read"
        )
    return tokens


class FailedAuthLimiter:
    """Count failed authentications per client; refuse a client past the limit.

    Parameters
    ----------
    max_failures
        Failures allowed within ``window_s``.
    window_s
        The sliding window, in seconds.
    clock
        Monotonic time source (tests pass their own).
    """

    def __init__(
        self, max_failures: int, window_s: float, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.max_failures = max_failures
        self.window_s = window_s
        self._clock = clock
        self._failures: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def _recent(self, client: str, now: float) -> deque[float]:
        times = self._failures.setdefault(client, deque())
        while times and times[0] <= now - self.window_s:
            times.popleft()
        return times

    def retry_after(self, client: str) -> int | None:
        """Return the seconds ``client`` must wait, or ``None`` if it may try."""
        with self._lock:
            now = self._clock()
            times = self._recent(client, now)
            if len(times) < self.max_failures:
                if not times:
                    self._failures.pop(client, None)
                return None
            return max(1, math.ceil(times[-self.max_failures] + self.window_s - now))

    def failed(self, client: str) -> None:
        """Record a failed authentication of ``client``."""
        with self._lock:
            now = self._clock()
            times = self._recent(client, now)
            times.append(now)
            while len(times) > self.max_failures:
                times.popleft()
