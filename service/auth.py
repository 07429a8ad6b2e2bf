"""The REST API's bearer token: where it comes from, how it is checked, and the limit on failed attempts.

No default token exists: :func:`resolve_token` refuses a real device without one
and gives the twin a random one (printed once). A token is compared in
constant time. Failed authentications are logged with the client address and
counted per client; after ``burst`` failures within ``window_s`` that client's
changing requests get 429 with ``Retry-After`` until the window has passed.
"""

from __future__ import annotations

import logging
import math
import secrets
import sys
import threading
import time
from collections import deque
from typing import TextIO

from .settings import Settings, SettingsError

__all__ = ["resolve_token", "check_bearer", "FailureLimiter", "MIN_TOKEN_CHARS"]

log = logging.getLogger(__name__)

MIN_TOKEN_CHARS = 16


def resolve_token(settings: Settings, *, out: TextIO | None = None) -> str:
    """The token the API requires: ``api.token``, or on the twin a random one printed once to ``out`` (stderr)."""
    token = settings.api.token
    if token:
        if len(token) < MIN_TOKEN_CHARS:  # settings check this too; a token set after loading must not slip by
            raise SettingsError(f"api.token is {len(token)} characters: at least {MIN_TOKEN_CHARS} are required")
        return token
    if not settings.twin:
        raise SettingsError(f"api.token is not set: a real device needs a bearer token of at least {MIN_TOKEN_CHARS} characters ([api] token, or DRILLNAV_API__TOKEN)")
    token = secrets.token_urlsafe(24)
    print(f"drillnav twin: no api.token set; this run's API token is {token}", file=out or sys.stderr, flush=True)
    return token


def check_bearer(authorization: str | None, token: str) -> int:
    """0 when ``authorization`` carries ``token``; else the HTTP status: 401 (none given) or 403 (wrong)."""
    if not authorization or not authorization.startswith("Bearer "):
        return 401
    return 0 if secrets.compare_digest(authorization[7:].encode(), token.encode()) else 403


class FailureLimiter:
    """Failed authentications per client: ``retry_after_s(client)`` > 0 while that client is over the burst."""

    def __init__(self, *, burst: int = 10, window_s: float = 10.0, max_clients: int = 10_000) -> None:
        if burst < 1 or window_s <= 0:
            raise ValueError(f"burst must be >= 1 and window_s > 0, got {burst}, {window_s}")
        self.burst, self.window_s, self.max_clients = burst, window_s, max_clients
        self._failures: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def _prune(self, client: str, now: float) -> deque[float] | None:
        q = self._failures.get(client)
        if q is not None:
            while q and now - q[0] >= self.window_s:
                q.popleft()
            if not q:
                del self._failures[client]
                return None
        return q

    def retry_after_s(self, client: str, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        with self._lock:
            q = self._prune(client, now)
            if q is None or len(q) < self.burst:
                return 0.0
            return max(q[0] + self.window_s - now, 0.001)

    def fail(self, client: str, now: float | None = None) -> int:
        """Count one failure; returns the failures of ``client`` within the window."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if client not in self._failures and len(self._failures) >= self.max_clients:
                for c in list(self._failures):  # many clients at once: forget those whose window has passed
                    self._prune(c, now)
                if len(self._failures) >= self.max_clients:
                    self._failures.pop(next(iter(self._failures)))
            q = self._failures.setdefault(client, deque())
            q.append(now)
            return len(q)

    @staticmethod
    def retry_after_header(seconds: float) -> str:
        return str(max(1, math.ceil(seconds)))
