"""The REST API's gate, an ASGI middleware that runs before any request body is read.

In order, for every HTTP request:

1. A changing request (POST, PUT, PATCH, DELETE) from a client over its burst
   of failed authentications gets 429 with ``Retry-After``.
2. A changing request without the right bearer token gets 401/403 (logged with
   the client address, counted, audited), its body unread.
3. A body is limited per endpoint: a ``Content-Length`` over the limit gets 413
   at once; a streamed (chunked) body is counted as the application reads it and
   stopped with 413 at the limit.

Every early answer closes the connection, so the server never reads the rest
of a body nobody will use. :func:`check_image_pixels` refuses an upload whose
header declares too many pixels before anything decodes it.
"""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass

from starlette.exceptions import HTTPException

from .audit import AuditAction, AuditLog
from .auth import FailureLimiter, check_bearer

__all__ = ["BodyLimits", "RequestGuard", "BodyTooLarge", "check_image_pixels", "ImageTooLarge"]

log = logging.getLogger(__name__)

CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})


@dataclass(frozen=True, kw_only=True)
class BodyLimits:
    """Largest request bodies in bytes: ``upload_bytes`` on the upload routes, ``default_bytes`` everywhere else."""

    default_bytes: int = 64 * 1024
    upload_bytes: int = 64 * 1024 * 1024
    upload_paths: tuple[str, ...] = ("/calibration/jobs",)  # POST here takes image files

    def for_request(self, method: str, path: str) -> int:
        return self.upload_bytes if method == "POST" and path.rstrip("/") in self.upload_paths else self.default_bytes


class BodyTooLarge(HTTPException):
    """Raised from ``receive`` when a streamed body passes its limit (an HTTPException so FastAPI passes it on as 413)."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body larger than {limit} bytes")


class ImageTooLarge(ValueError):
    pass


def check_image_pixels(name: str, data: bytes, *, max_pixels: float) -> tuple[int, int]:
    """(width, height) from the image header alone; :class:`ImageTooLarge` above ``max_pixels``, ValueError if unknown.

    Pillow's ``Image.open`` parses the header lazily and decodes nothing, so a
    380 KiB PNG that declares 30000x30000 pixels costs microseconds, not 900 MB.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as im:
            width, height = im.size
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise ValueError(f"upload '{name}': not a readable image (corrupt or unsupported format: {type(exc).__name__} on its header)") from None
    except Image.DecompressionBombError as exc:  # Pillow's own guard on open, for the very largest declarations
        raise ImageTooLarge(f"upload '{name}': above the limit of {max_pixels / 1e6:g} Mpixel (api.max_image_mpixel): {exc}") from None
    if width * height > max_pixels:
        raise ImageTooLarge(f"upload '{name}': {width}x{height} px is {width * height / 1e6:.0f} Mpixel, above the limit of {max_pixels / 1e6:g} Mpixel (api.max_image_mpixel)")
    return width, height


def _client(scope) -> str:
    client = scope.get("client")
    return client[0] if client else "unknown"


def _header(scope, name: bytes) -> str | None:
    for k, v in scope.get("headers", ()):
        if k == name:
            return v.decode("latin-1")
    return None


class RequestGuard:
    """ASGI middleware: ``app.add_middleware(RequestGuard, token=..., limits=..., limiter=..., audit=...)``.

    ``token`` is a string or a callable returning it (read per request, so a token set later is honoured).
    """

    def __init__(self, app, *, token: str | Callable[[], str], limits: BodyLimits, limiter: FailureLimiter, audit: AuditLog | None = None) -> None:
        self.app, self.limits, self.limiter, self.audit = app, limits, limiter, audit
        self._token = token if callable(token) else (lambda: token)
        self._blocked_logged: set[str] = set()

    async def _answer(self, send, status: int, detail: str, headers: list[tuple[bytes, bytes]] = ()) -> None:
        body = json.dumps({"detail": detail}).encode()
        await send({"type": "http.response.start", "status": status, "headers": [
            (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()), (b"connection", b"close"), *headers]})
        await send({"type": "http.response.body", "body": body})

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        method, path, client = scope["method"], scope["path"], _client(scope)
        if method in CHANGING:
            wait_s = self.limiter.retry_after_s(client)
            if wait_s > 0:
                if client not in self._blocked_logged:  # once per block, or the log itself becomes the flood
                    self._blocked_logged.add(client)
                    log.warning("REST: client %s blocked for %.0f s after %d failed authentications", client, wait_s, self.limiter.burst)
                    if self.audit is not None:
                        self.audit.record(AuditAction.AUTH_RATE_LIMITED, actor=client, detail={"retry_after_s": round(wait_s, 1)})
                return await self._answer(send, 429, f"too many failed authentications: retry after {wait_s:.0f} s",
                                          [(b"retry-after", FailureLimiter.retry_after_header(wait_s).encode())])
            self._blocked_logged.discard(client)
            code = check_bearer(_header(scope, b"authorization"), self._token())
            if code:
                n = self.limiter.fail(client)
                log.warning("REST: failed authentication (%s) from %s: %s %s (%d in %.0f s)", "no token" if code == 401 else "wrong token",
                            client, method, path, n, self.limiter.window_s)
                if self.audit is not None:
                    self.audit.record(AuditAction.AUTH_FAILED, actor=client, detail={"method": method, "path": path, "status": code})
                extra = [(b"www-authenticate", b"Bearer")] if code == 401 else []
                return await self._answer(send, code, "missing bearer token" if code == 401 else "wrong token", extra)
        limit = self.limits.for_request(method, path)
        length = _header(scope, b"content-length")
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                return await self._answer(send, 400, "Content-Length is not a number")
            if declared > limit:
                return await self._answer(send, 413, f"request body of {declared} bytes is larger than the {limit} bytes {method} {path} accepts")
        seen = 0
        started = False
        body_done = length == "0" or (length is None and _header(scope, b"transfer-encoding") is None)

        async def counted_receive():
            nonlocal seen, body_done
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise BodyTooLarge(limit)
                body_done = body_done or not message.get("more_body", False)
            return message

        async def watched_send(message):
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                if not body_done:  # answered before the body ended: close rather than read the rest to keep the connection
                    message = {**message, "headers": [*message.get("headers", []), (b"connection", b"close")]}
            await send(message)

        try:
            await self.app(scope, counted_receive, watched_send)
        except BodyTooLarge:
            if started:
                raise
            await self._answer(send, 413, f"request body larger than the {limit} bytes {method} {path} accepts")
