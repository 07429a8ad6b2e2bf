"""REST routes of the calibration jobs: submit, follow, cancel, download, install.

Errors of :mod:`drillnav.service.calibration_jobs` become HTTP problems here:
a request that cannot run -> 422, unknown job -> 404, wrong job state -> 409,
too many jobs (the cap named) -> 429. Uploaded images are checked for their
pixel count from the header before anything decodes them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any

from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, UploadFile, status
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from .calibration_jobs import (
    CalibrationJobError,
    CalibrationJobs,
    InvalidJobRequest,
    JobAlreadyFinished,
    JobInfo,
    JobNotFinished,
    JobNotFound,
    JobNotSucceeded,
    JobKind,
    NoActiveCamera,
    TooManyJobs,
)
from .audit import AuditAction
from .body_limits import ImageTooLarge, check_image_pixels

__all__ = ["calibration_router", "JobPublic", "InstallPublic"]

RESULT_FILE = {JobKind.CAMERA: "camera.json", JobKind.DRILL_AXIS: "drill.json"}


class JobPublic(BaseModel):
    id: str
    kind: str = Field(description="'camera' or 'drill-axis'")
    state: str = Field(description="queued, running, succeeded, failed or cancelled")
    progress: float = Field(ge=0.0, le=1.0)
    message: str
    source: str = Field(description="'upload' or 'live'")
    inputs: int = Field(description="uploaded images, or live frames captured so far")
    created_ns: int
    started_ns: int | None
    finished_ns: int | None
    installed_path: str | None
    installed_ns: int | None

    @classmethod
    def of(cls, info: JobInfo) -> JobPublic:
        return cls(
            id=info.id, kind=info.kind.value, state=info.state.value, progress=info.progress, message=info.message,
            source=info.source, inputs=info.inputs, created_ns=info.created_ns, started_ns=info.started_ns,
            finished_ns=info.finished_ns, installed_path=info.installed_path, installed_ns=info.installed_ns,
        )


class InstallPublic(BaseModel):
    id: str
    kind: str
    installed_path: str


def _problem(exc: CalibrationJobError) -> HTTPException:
    if isinstance(exc, InvalidJobRequest):
        code = 422  # the literal: Starlette renamed its constant between versions
    elif isinstance(exc, JobNotFound):
        code = status.HTTP_404_NOT_FOUND
    elif isinstance(exc, (JobNotFinished, JobNotSucceeded, JobAlreadyFinished, NoActiveCamera)):
        code = status.HTTP_409_CONFLICT
    elif isinstance(exc, TooManyJobs):
        code = status.HTTP_429_TOO_MANY_REQUESTS
    else:  # InstallFailed: the active path or the reload callback failed on our side
        code = status.HTTP_500_INTERNAL_SERVER_ERROR
    return HTTPException(code, str(exc))


def calibration_router(
    jobs: CalibrationJobs,
    require_token: Callable[..., None],
    *,
    audited: Callable[..., None] | None = None,
    max_image_pixels: float = 40e6,
) -> APIRouter:
    """The ``/calibration/jobs`` routes over ``jobs``; changing routes depend on ``require_token``.

    ``audited(request, action, **detail)`` records each change; ``max_image_pixels`` bounds each uploaded image.
    """
    router = APIRouter(prefix="/calibration/jobs", tags=["calibration"])
    authorized = [Depends(require_token)]

    def audit(request: Request, action: AuditAction, **detail: Any) -> None:
        if audited is not None:
            audited(request, action, **detail)

    @router.post(
        "", status_code=status.HTTP_202_ACCEPTED, dependencies=authorized, response_model=JobPublic,
        summary="Start a calibration job from uploaded images or live frames",
    )
    def create_job(
        request: Request,
        kind: Annotated[str, Form(description="'camera' or 'drill-axis'")],
        board: Annotated[str | None, Form(description="camera jobs: checkerboard:9x6:25mm or charuco:5x7:40mm:30mm[:DICT]")] = None,
        files: Annotated[list[UploadFile] | None, File(description="the views (any format OpenCV decodes)")] = None,
        live_seconds: Annotated[float | None, Form(description="capture from the drill camera for this many seconds instead of uploads")] = None,
        live_fps: Annotated[float | None, Form(description="live capture rate, frames per second")] = None,
        label: Annotated[str | None, Form(max_length=200)] = None,
    ) -> JobPublic:
        uploads = []
        for i, f in enumerate(files or []):
            name, data = f.filename or f"file {i + 1}", f.file.read()
            try:
                check_image_pixels(name, data, max_pixels=max_image_pixels)
            except ImageTooLarge as exc:
                raise HTTPException(413, str(exc)) from None  # the literal: Starlette renamed its constant between versions
            except ValueError as exc:
                raise HTTPException(422, str(exc)) from None
            uploads.append((name, data))
        try:
            info = jobs.submit(kind=kind, board=board, uploads=uploads, live_seconds=live_seconds, live_fps=live_fps, label=label)
        except CalibrationJobError as exc:
            raise _problem(exc) from None
        audit(request, AuditAction.CALIBRATION_JOB_SUBMITTED, job=info.id, kind=info.kind.value, inputs=info.inputs, source=info.source)
        return JobPublic.of(info)

    @router.get("", summary="List calibration jobs, oldest first")
    def list_jobs() -> list[JobPublic]:
        return [JobPublic.of(i) for i in jobs.list_jobs()]

    @router.get("/{job_id}", summary="A calibration job's state and progress")
    def get_job(job_id: str) -> JobPublic:
        try:
            return JobPublic.of(jobs.get(job_id))
        except CalibrationJobError as exc:
            raise _problem(exc) from None

    @router.delete("/{job_id}", dependencies=authorized, summary="Cancel a queued or running calibration job")
    def cancel_job(job_id: str, request: Request) -> JobPublic:
        try:
            out = JobPublic.of(jobs.cancel(job_id))
        except CalibrationJobError as exc:
            raise _problem(exc) from None
        audit(request, AuditAction.CALIBRATION_JOB_CANCELLED, job=job_id)
        return out

    @router.get(
        "/{job_id}/result", summary="Download a succeeded job's calibration file (camera.json or drill.json)",
        response_class=JSONResponse, responses={404: {"description": "unknown job"}, 409: {"description": "not finished, failed or cancelled"}},
    )
    def get_result(job_id: str) -> JSONResponse:
        try:
            info = jobs.get(job_id)
            doc: dict[str, Any] = jobs.result(job_id)
        except CalibrationJobError as exc:
            raise _problem(exc) from None
        return JSONResponse(doc, headers={"Content-Disposition": f'attachment; filename="{RESULT_FILE[info.kind]}"'})

    @router.post("/{job_id}/install", dependencies=authorized, summary="Make a succeeded job's result the active calibration")
    def install_job(job_id: str, request: Request) -> InstallPublic:
        try:
            info = jobs.get(job_id)
            path = jobs.install(job_id)
        except CalibrationJobError as exc:
            raise _problem(exc) from None
        audit(request, AuditAction.CALIBRATION_INSTALLED, job=job_id, kind=info.kind.value, path=str(path))
        return InstallPublic(id=job_id, kind=info.kind.value, installed_path=str(path))

    return router
