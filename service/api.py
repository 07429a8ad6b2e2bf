"""The REST API (FastAPI): health, status, current registration, recordings, twin C-arm shots, calibration jobs.

Every changing endpoint needs ``Authorization: Bearer <token>``; the check, the
failed-attempt limit and the body limits run in :class:`~.body_limits.RequestGuard`
before any body is read (see docs/security.md, "DICOM and REST"). Changes are
written to the audit log when one is given.
"""

from __future__ import annotations

import ssl
from typing import Annotated, Any, Protocol

from fastapi import Depends, FastAPI, Header, HTTPException, Request, status
from pydantic import BaseModel, Field

from .api_calibration import calibration_router
from .audit import AuditAction, AuditLog
from .auth import FailureLimiter, check_bearer
from .body_limits import BodyLimits, RequestGuard
from .settings import ApiSettings
from .display_routes import display_router, docs_router

__all__ = ["create_app", "ServiceState", "uvicorn_ssl_kwargs", "running_recordings"]


def uvicorn_ssl_kwargs(api: ApiSettings) -> dict[str, Any]:
    """The ``uvicorn.Config`` keyword arguments for HTTPS (and mutual TLS) from ``[api]``; empty for plain HTTP."""
    if api.tls_cert is None:
        return {}
    kwargs: dict[str, Any] = {"ssl_certfile": str(api.tls_cert), "ssl_keyfile": str(api.tls_key)}
    if api.tls_client_ca is not None:
        kwargs.update(ssl_ca_certs=str(api.tls_client_ca), ssl_cert_reqs=ssl.CERT_REQUIRED)
    return kwargs


def running_recordings(state: Any) -> list[str]:
    """Names of the recordings running now: ``state.running_recordings()`` if it has one, else its status's list."""
    if hasattr(state, "running_recordings"):
        return list(state.running_recordings())
    return list(state.status().get("recordings", []))


class ServiceState(Protocol):
    token: str

    def health(self) -> str | None: ...
    def status(self) -> dict[str, Any]: ...
    def registration(self) -> dict[str, Any] | None: ...
    def request_registration(self) -> None: ...
    def start_recording(self, name: str) -> list[str]: ...
    def stop_recording(self, name: str) -> list[str]: ...
    def recordings(self) -> dict[str, list[str]]: ...
    def shoot(self, view: str) -> str: ...


class RecordingCreate(BaseModel):
    name: str = Field(pattern=r"^[A-Za-z0-9_-]{1,64}$", description="letters, digits, '-' and '_'")


class RecordingPublic(BaseModel):
    name: str
    files: list[str]


class ShotCreate(BaseModel):
    view: str = Field(min_length=1, max_length=32)


def create_app(*, state: ServiceState, settings: ApiSettings | None = None, audit: AuditLog | None = None) -> FastAPI:
    """The API over ``state``; ``settings`` gives the limits (defaults: ``ApiSettings()``), ``audit`` the audit log (None: none)."""
    api = settings or ApiSettings()
    if not getattr(state, "token", None):
        raise ValueError("the API needs a token: state.token is empty (see drillnav.service.auth.resolve_token)")
    # /docs and /redoc come from packaged files (display_routes.docs_router): FastAPI's own would load from a CDN.
    app = FastAPI(title="drillnav", version="0.1.0", description="Drill-mounted video guidance: status, registration, recordings.", docs_url=None, redoc_url=None)
    limits = BodyLimits(default_bytes=int(api.max_json_kb * 1024), upload_bytes=int(api.max_upload_mb * 1024 * 1024))
    limiter = FailureLimiter(burst=api.auth_failures_burst, window_s=api.auth_failures_window_s)
    app.add_middleware(RequestGuard, token=lambda: state.token, limits=limits, limiter=limiter, audit=audit)
    # The surgeon's page at /, its WebSocket, the offline API docs (service/display_routes.py): read-only, no token.
    app.include_router(docs_router(app))
    app.include_router(display_router(getattr(state, "display_hub", None)))

    def require_token(authorization: Annotated[str | None, Header()] = None) -> None:
        # RequestGuard has checked already, before the body; this keeps each route safe on its own and documents it.
        code = check_bearer(authorization, state.token)
        if code == 401:
            raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing bearer token", headers={"WWW-Authenticate": "Bearer"})
        if code:
            raise HTTPException(status.HTTP_403_FORBIDDEN, "wrong token")

    def audited(request: Request, action: AuditAction, **detail: Any) -> None:
        if audit is not None:
            audit.record(action, actor=f"{request.client.host if request.client else 'unknown'} (token)", detail=detail)

    authorized = [Depends(require_token)]

    @app.get("/health", responses={503: {"description": "a stream the daemon should produce has stalled; the detail says which"}})
    def health() -> dict[str, str]:
        # What a client sees, not that the process exists: 503 while the axis, camera or recorder stream stalls.
        reason = state.health()
        if reason is not None:
            raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, reason)
        return {"status": "ok"}

    @app.get("/status")
    def get_status() -> dict[str, Any]:
        return state.status()

    @app.get("/registration")
    def get_registration() -> dict[str, Any]:
        reg = state.registration()
        if reg is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, "no registration yet: waiting for fluoroscopy")
        return reg

    @app.post("/registration/refresh", status_code=status.HTTP_202_ACCEPTED, dependencies=authorized)
    def refresh(request: Request) -> dict[str, str]:
        state.request_registration()
        audited(request, AuditAction.REGISTRATION_REFRESHED)
        return {"status": "re-registration requested"}

    @app.get("/recordings")
    def list_recordings() -> list[RecordingPublic]:
        return [RecordingPublic(name=n, files=f) for n, f in state.recordings().items()]

    @app.post("/recordings", status_code=status.HTTP_201_CREATED, dependencies=authorized)
    def start_recording(body: RecordingCreate, request: Request) -> RecordingPublic:
        running = running_recordings(state)
        if len(running) >= api.max_recordings:
            raise HTTPException(status.HTTP_429_TOO_MANY_REQUESTS, f"{len(running)} recordings are running, the cap (api.max_recordings) is {api.max_recordings}: stop one first")
        try:
            out = RecordingPublic(name=body.name, files=state.start_recording(body.name))
        except KeyError as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc.args[0])) from None
        audited(request, AuditAction.RECORDING_STARTED, name=body.name, files=out.files)
        return out

    @app.delete("/recordings/{name}", dependencies=authorized)
    def stop_recording(name: str, request: Request) -> RecordingPublic:
        try:
            out = RecordingPublic(name=name, files=state.stop_recording(name))
        except KeyError as exc:
            raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc.args[0])) from None
        audited(request, AuditAction.RECORDING_STOPPED, name=name, files=out.files)
        return out

    # Optional: only a service that runs calibration jobs offers them.
    calibration_jobs = getattr(state, "calibration_jobs", None)
    if calibration_jobs is not None:
        app.include_router(calibration_router(calibration_jobs, require_token, audited=audited, max_image_pixels=api.max_image_mpixel * 1e6))

    @app.post("/carm/shots", status_code=status.HTTP_201_CREATED, dependencies=authorized)
    def shoot(body: ShotCreate, request: Request) -> dict[str, str]:
        try:
            out = {"file": state.shoot(body.view)}
        except (ValueError, RuntimeError) as exc:
            raise HTTPException(422, str(exc)) from None
        audited(request, AuditAction.SHOT_REQUESTED, view=body.view)
        return out

    return app
