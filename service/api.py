"""The REST API (FastAPI): health, status, current registration, recordings, twin C-arm shots, calibration jobs.

Every changing endpoint needs ``Authorization: Bearer <token>``.
"""

from __future__ import annotations

import secrets
from typing import Annotated, Any, Protocol

from fastapi import Depends, FastAPI, Header, HTTPException, status
from pydantic import BaseModel, Field

from .api_calibration import calibration_router
from .display_routes import display_router, docs_router

__all__ = ["create_app", "ServiceState"]


class ServiceState(Protocol):
    token: str

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


def create_app(*, state: ServiceState) -> FastAPI:
    # /docs and /redoc come from packaged files (display_routes.docs_router): FastAPI's own would load from a CDN.
    app = FastAPI(title="drillnav", version="0.1.0", description="Drill-mounted video guidance: status, registration, recordings.", docs_url=None, redoc_url=None)
    # -- display (service/display_routes.py): the surgeon's page at /, its WebSocket, offline API docs --
    app.include_router(docs_router(app))
    app.include_router(display_router(getattr(state, "display_hub", None)))
    # -- end display --

    def require_token(authorization: Annotated[str | None, Header()] = None) -> None:
        if not authorization or not authorization.startswith("Bearer "):
            raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing bearer token", headers={"WWW-Authenticate": "Bearer"})
        if not secrets.compare_digest(authorization[7:].encode(), state.token.encode()):
            raise HTTPException(status.HTTP_403_FORBIDDEN, "wrong token")

    authorized = [Depends(require_token)]

    @app.get("/health")
    def health() -> dict[str, str]:
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
    def refresh() -> dict[str, str]:
        state.request_registration()
        return {"status": "re-registration requested"}

    @app.get("/recordings")
    def list_recordings() -> list[RecordingPublic]:
        return [RecordingPublic(name=n, files=f) for n, f in state.recordings().items()]

    @app.post("/recordings", status_code=status.HTTP_201_CREATED, dependencies=authorized)
    def start_recording(body: RecordingCreate) -> RecordingPublic:
        try:
            return RecordingPublic(name=body.name, files=state.start_recording(body.name))
        except KeyError as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc.args[0])) from None

    @app.delete("/recordings/{name}", dependencies=authorized)
    def stop_recording(name: str) -> RecordingPublic:
        try:
            return RecordingPublic(name=name, files=state.stop_recording(name))
        except KeyError as exc:
            raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc.args[0])) from None

    # Optional: only a service that runs calibration jobs offers them.
    calibration_jobs = getattr(state, "calibration_jobs", None)
    if calibration_jobs is not None:
        app.include_router(calibration_router(calibration_jobs, require_token))

    @app.post("/carm/shots", status_code=status.HTTP_201_CREATED, dependencies=authorized)
    def shoot(body: ShotCreate) -> dict[str, str]:
        try:
            return {"file": state.shoot(body.view)}
        except (ValueError, RuntimeError) as exc:
            raise HTTPException(422, str(exc)) from None

    return app
