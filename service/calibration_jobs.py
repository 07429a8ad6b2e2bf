"""Camera and drill-axis calibrations run as background jobs (for the REST API).

A job takes uploaded images (decoded on submission, so a bad upload is refused
at once) or live frames captured by the job itself for a given time at a given
rate. It runs the same pure functions as ``drillnav calibrate`` and, on success,
saves the same document the CLI writes (camera.json / drill.json content) as
``work_dir/jobs/<id>/result.json``. Nothing becomes active until
:meth:`CalibrationJobs.install` is called: a calibration changes every overlay
the surgeon sees, so a person has to accept it.

Times are integer nanoseconds (``time.time_ns``).
"""

from __future__ import annotations

import enum
import json
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.camera_calibration import BoardSpec, calibrate_camera, detect_board, parse_board
from drillnav.registration.drill_axis import MIN_JIG_POSES, find_jig_poses, fit_axis_screw
from drillnav.registration.errors import DegenerateInput, DrillnavError
from drillnav.schemas.calibration import read_camera_calibration, write_camera_calibration, write_drill_calibration

__all__ = [
    "CalibrationJobs",
    "JobKind",
    "JobState",
    "JobInfo",
    "GrabFrame",
    "CalibrationJobError",
    "InvalidJobRequest",
    "JobNotFound",
    "JobNotFinished",
    "JobNotSucceeded",
    "JobAlreadyFinished",
    "NoActiveCamera",
    "InstallFailed",
    "TooManyJobs",
]

log = logging.getLogger(__name__)

GrabFrame = Callable[[], tuple[int, NDArray[np.uint8]]]
"""Returns (stamp_ns, image) of the newest camera frame; raises if the camera is gone."""

MAX_LIVE_SECONDS = 120.0
MAX_LIVE_FPS = 30.0
MIN_POSES = MIN_JIG_POSES  # the screw fit needs at least two relative rotations


class CalibrationJobError(DrillnavError):
    """Base of the calibration-job errors."""


class InvalidJobRequest(CalibrationJobError, ValueError):
    """A submission that cannot run: unknown kind, bad board string, no or non-image uploads, no live camera."""


class JobNotFound(CalibrationJobError, KeyError):
    """No job with that id."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class JobNotFinished(CalibrationJobError):
    """The job is still queued or running."""


class JobNotSucceeded(CalibrationJobError):
    """The job ended failed or cancelled: it has no result to download or install."""


class JobAlreadyFinished(CalibrationJobError):
    """Cancel requested for a job that has already ended."""


class NoActiveCamera(CalibrationJobError):
    """A drill-axis job needs an installed, valid camera calibration."""


class InstallFailed(CalibrationJobError):
    """The result could not be written to the active path, or the install callback failed."""


class TooManyJobs(CalibrationJobError):
    """The cap on jobs queued or running (or kept) is reached; the message names the cap."""


class JobKind(str, enum.Enum):
    CAMERA = "camera"
    DRILL_AXIS = "drill-axis"


class JobState(str, enum.Enum):
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    @property
    def finished(self) -> bool:
        return self in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)


@dataclass(frozen=True, kw_only=True)
class JobInfo:
    """A snapshot of one job, safe to hand to another thread."""

    id: str
    kind: JobKind
    state: JobState
    progress: float  # 0..1 while it runs; 1 on success, 0 once it has ended failed or cancelled (no result)
    message: str
    source: str  # "upload" or "live"
    inputs: int  # uploaded images, or frames captured so far
    created_ns: int
    started_ns: int | None
    finished_ns: int | None
    installed_path: str | None
    installed_ns: int | None


@dataclass(frozen=True, kw_only=True)
class _LiveCapture:
    seconds: float
    fps: float


@dataclass(kw_only=True)
class _Job:
    id: str
    kind: JobKind
    label: str
    board: BoardSpec | None
    camera: PinholeCamera | None
    images: list[tuple[str, NDArray[np.uint8]]]  # (name, grey image)
    live: _LiveCapture | None
    created_ns: int
    n_inputs: int = 0
    state: JobState = JobState.QUEUED
    progress: float = 0.0
    message: str = "queued"
    started_ns: int | None = None
    finished_ns: int | None = None
    installed_path: str | None = None
    installed_ns: int | None = None
    cancel: threading.Event = field(default_factory=threading.Event)

    def info(self) -> JobInfo:
        return JobInfo(
            id=self.id, kind=self.kind, state=self.state, progress=self.progress, message=self.message,
            source="live" if self.live else "upload", inputs=self.n_inputs, created_ns=self.created_ns,
            started_ns=self.started_ns, finished_ns=self.finished_ns, installed_path=self.installed_path, installed_ns=self.installed_ns,
        )


class _Cancelled(Exception):
    pass


def decode_upload(name: str, data: bytes) -> NDArray[np.uint8]:
    """Grey image from an uploaded file's bytes; :class:`InvalidJobRequest` naming the file otherwise."""
    if not data:
        raise InvalidJobRequest(f"upload '{name}': file is empty")
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InvalidJobRequest(f"upload '{name}': not a readable image (corrupt or unsupported format)")
    return img


def _grey(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


class CalibrationJobs:
    """Background calibration jobs in a thread pool.

    Parameters
    ----------
    work_dir : Path
        Job results go to ``work_dir/jobs/<id>/result.json``.
    max_workers : int
        Jobs run at most this many at a time; the rest wait queued.
    active_camera_path, active_drill_path : Path or None
        Where :meth:`install` puts camera.json / drill.json; the drill-axis job
        reads its camera from ``active_camera_path``. None: install (and the
        drill-axis job) are refused.
    grab_frame : callable or None
        ``() -> (stamp_ns, image)`` of the live drill camera; None: live capture is refused.
    on_install : callable or None
        ``(kind, path)`` called after a result was installed, e.g. to reload it.
    max_active : int
        Jobs queued or running at once; one more is refused with :class:`TooManyJobs` (api.max_jobs_running).
    max_stored : int
        Jobs kept in all; at the cap the oldest finished job is forgotten, and with none finished the
        submission is refused (api.max_jobs_stored).
    expiry_s : float
        A finished job (and its result folder) is forgotten this long after it ended (api.job_expiry_s).
    """

    def __init__(
        self,
        *,
        work_dir: Path,
        max_workers: int = 1,
        active_camera_path: Path | None = None,
        active_drill_path: Path | None = None,
        grab_frame: GrabFrame | None = None,
        on_install: Callable[[str, Path], None] | None = None,
        max_active: int = 4,
        max_stored: int = 50,
        expiry_s: float = 3600.0,
    ) -> None:
        if max_workers < 1:
            raise ValueError(f"max_workers must be >= 1, got {max_workers}")
        if max_active < 1 or max_stored < max_active or expiry_s <= 0:
            raise ValueError(f"need max_active >= 1, max_stored >= max_active and expiry_s > 0, got {max_active}, {max_stored}, {expiry_s}")
        self.max_active, self.max_stored, self.expiry_s = max_active, max_stored, expiry_s
        self.work_dir = Path(work_dir)
        self.active_paths: dict[JobKind, Path | None] = {
            JobKind.CAMERA: Path(active_camera_path) if active_camera_path else None,
            JobKind.DRILL_AXIS: Path(active_drill_path) if active_drill_path else None,
        }
        self.grab_frame = grab_frame
        self.on_install = on_install
        self._jobs: dict[str, _Job] = {}
        self._lock = threading.Lock()
        self._install_lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=max_workers, thread_name_prefix="calibration-job")

    # -- lifecycle ---------------------------------------------------------------

    def close(self) -> None:
        """Cancel every unfinished job and wait for the workers."""
        with self._lock:
            jobs = list(self._jobs.values())
        for job in jobs:
            job.cancel.set()
        # A job busy computing (a calibration solve) cannot see its cancel flag: it is not waited for beyond
        # a short grace, so a stopping daemon finalises its recordings in time (the CLI then ends the process).
        self._pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + 1.0
        for thread in list(getattr(self._pool, "_threads", ())):
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
        with self._lock:
            for job in jobs:
                if not job.state.finished:
                    self._finish(job, JobState.CANCELLED, "cancelled: service shutting down")

    def __enter__(self) -> CalibrationJobs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- submission --------------------------------------------------------------

    def submit(
        self,
        *,
        kind: str,
        board: str | None = None,
        uploads: Sequence[tuple[str, bytes]] = (),
        live_seconds: float | None = None,
        live_fps: float | None = None,
        label: str | None = None,
    ) -> JobInfo:
        """Validate a request and queue the job; :class:`InvalidJobRequest` / :class:`NoActiveCamera` / :class:`TooManyJobs` say why not."""
        with self._lock:
            self._make_room()  # refused before any upload is decoded
        try:
            job_kind = JobKind(kind)
        except ValueError:
            raise InvalidJobRequest(f"unknown kind '{kind}': use one of {[k.value for k in JobKind]}") from None
        spec = camera = None
        if job_kind is JobKind.CAMERA:
            if not board:
                raise InvalidJobRequest("a camera job needs a board, e.g. 'checkerboard:9x6:25mm'")
            try:
                spec = parse_board(board)
            except ValueError as exc:
                raise InvalidJobRequest(str(exc)) from None
        else:
            camera = self._active_camera()
        live = None
        if live_seconds is not None or live_fps is not None:
            if uploads:
                raise InvalidJobRequest("give either uploaded files or live_seconds + live_fps, not both")
            live = self._live_request(live_seconds, live_fps)
            images: list[tuple[str, NDArray[np.uint8]]] = []
        else:
            if not uploads:
                raise InvalidJobRequest("no files uploaded (or give live_seconds + live_fps to capture from the camera)")
            images = [(name, decode_upload(name, data)) for name, data in uploads]
            self._check_sizes(images, camera)
        job = _Job(
            id=uuid.uuid4().hex, kind=job_kind, label=label or ("drill camera" if job_kind is JobKind.CAMERA else "drill"),
            board=spec, camera=camera, images=images, live=live, created_ns=time.time_ns(), n_inputs=len(images),
        )
        with self._lock:
            self._make_room()  # again: another submission may have come in while this one decoded
            self._jobs[job.id] = job
            info = job.info()
        self._pool.submit(self._run, job)
        return info

    def _expire(self) -> None:
        """Forget finished jobs older than ``expiry_s`` (with their result folders); under ``_lock``."""
        now = time.time_ns()
        for job_id in [i for i, j in self._jobs.items() if j.state.finished and j.finished_ns is not None and now - j.finished_ns > self.expiry_s * 1e9]:
            self._forget(job_id)

    def _forget(self, job_id: str) -> None:
        self._jobs.pop(job_id, None)
        folder = self.result_path(job_id).parent
        for f in folder.glob("*") if folder.is_dir() else ():
            f.unlink(missing_ok=True)
        if folder.is_dir():
            folder.rmdir()

    def _make_room(self) -> None:
        """Expire, apply the caps, and free a stored slot for one more job; under ``_lock``."""
        self._expire()
        active = sum(1 for j in self._jobs.values() if not j.state.finished)
        if active >= self.max_active:
            raise TooManyJobs(f"{active} calibration jobs are queued or running, the cap (api.max_jobs_running) is {self.max_active}: wait or cancel one")
        if len(self._jobs) >= self.max_stored:
            finished = sorted((j for j in self._jobs.values() if j.state.finished), key=lambda j: j.finished_ns or 0)
            if not finished:
                raise TooManyJobs(f"{len(self._jobs)} calibration jobs are kept, the cap (api.max_jobs_stored) is {self.max_stored}")
            self._forget(finished[0].id)

    def _active_camera(self) -> PinholeCamera:
        path = self.active_paths[JobKind.CAMERA]
        if path is None:
            raise NoActiveCamera("drill-axis calibration needs the active camera calibration, but no camera calibration path is configured")
        if not path.is_file():
            raise NoActiveCamera(f"drill-axis calibration needs the active camera calibration: {path} does not exist (run and install a camera job first)")
        try:
            return read_camera_calibration(path)
        except ValueError as exc:
            raise NoActiveCamera(f"the active camera calibration is unusable: {exc}") from None

    def _live_request(self, seconds: float | None, fps: float | None) -> _LiveCapture:
        if seconds is None or fps is None:
            raise InvalidJobRequest("live capture needs both live_seconds and live_fps")
        if not (0 < seconds <= MAX_LIVE_SECONDS):
            raise InvalidJobRequest(f"live_seconds must be in (0, {MAX_LIVE_SECONDS:g}], got {seconds:g}")
        if not (0 < fps <= MAX_LIVE_FPS):
            raise InvalidJobRequest(f"live_fps must be in (0, {MAX_LIVE_FPS:g}], got {fps:g}")
        if self.grab_frame is None:
            raise InvalidJobRequest("live capture requested but no camera is available (upload images instead)")
        return _LiveCapture(seconds=float(seconds), fps=float(fps))

    @staticmethod
    def _check_sizes(images: list[tuple[str, NDArray[np.uint8]]], camera: PinholeCamera | None) -> None:
        if camera is not None:
            want = (camera.height, camera.width)
            for name, im in images:
                if im.shape[:2] != want:
                    raise InvalidJobRequest(f"'{name}' is {im.shape[1]}x{im.shape[0]} px but the active camera calibration is for {want[1]}x{want[0]} px")
        elif images:
            first_name, first = images[0]
            for name, im in images[1:]:
                if im.shape[:2] != first.shape[:2]:
                    raise InvalidJobRequest(f"views differ in size: '{first_name}' is {first.shape[1]}x{first.shape[0]} px, '{name}' is {im.shape[1]}x{im.shape[0]} px")

    # -- queries -----------------------------------------------------------------

    def get(self, job_id: str) -> JobInfo:
        with self._lock:
            self._expire()
            return self._job(job_id).info()

    def list_jobs(self) -> list[JobInfo]:
        """Every job, oldest first."""
        with self._lock:
            self._expire()
            return [j.info() for j in sorted(self._jobs.values(), key=lambda j: j.created_ns)]

    def result_path(self, job_id: str) -> Path:
        return self.work_dir / "jobs" / job_id / "result.json"

    def result(self, job_id: str) -> dict[str, Any]:
        """The result document (camera.json / drill.json content) of a succeeded job."""
        self._require_succeeded(job_id)
        return json.loads(self.result_path(job_id).read_text())

    def _job(self, job_id: str) -> _Job:
        try:
            return self._jobs[job_id]
        except KeyError:
            raise JobNotFound(f"no calibration job '{job_id}'") from None

    def _require_succeeded(self, job_id: str) -> JobInfo:
        info = self.get(job_id)
        if not info.state.finished:
            raise JobNotFinished(f"job {job_id} is {info.state.value} ({info.progress:.0%}): no result yet")
        if info.state is not JobState.SUCCEEDED:
            raise JobNotSucceeded(f"job {job_id} ended {info.state.value}: {info.message}")
        return info

    # -- control -----------------------------------------------------------------

    def cancel(self, job_id: str) -> JobInfo:
        """Ask a job to stop; a queued job is cancelled at once, a running one at its next image."""
        with self._lock:
            job = self._job(job_id)
            if job.state.finished:
                raise JobAlreadyFinished(f"job {job_id} has already ended {job.state.value}")
            job.cancel.set()
            if job.state is JobState.QUEUED:
                self._finish(job, JobState.CANCELLED, "cancelled before it started")
            else:
                job.message = "cancelling"
            return job.info()

    def install(self, job_id: str) -> Path:
        """Make a succeeded job's result the active calibration (atomic replace); returns the active path."""
        info = self._require_succeeded(job_id)
        dest = self.active_paths[info.kind]
        if dest is None:
            raise InstallFailed(f"no active {info.kind.value} calibration path is configured: cannot install job {job_id}")
        data = self.result_path(job_id).read_bytes()
        with self._install_lock:
            tmp = dest.with_name(f".{dest.name}.{job_id}.tmp")
            try:
                with open(tmp, "wb") as f:
                    f.write(data)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, dest)
            except OSError as exc:
                tmp.unlink(missing_ok=True)
                raise InstallFailed(f"could not install job {job_id} as {dest}: {exc}") from None
            with self._lock:
                job = self._jobs[job_id]
                job.installed_path, job.installed_ns = str(dest), time.time_ns()
            if self.on_install is not None:
                try:
                    self.on_install(info.kind.value, dest)
                except Exception as exc:  # the file is in place; say so rather than pretend nothing happened
                    raise InstallFailed(f"{dest} was written but applying it failed: {type(exc).__name__}: {exc}") from exc
        return dest

    # -- the worker --------------------------------------------------------------

    def _finish(self, job: _Job, state: JobState, message: str) -> None:
        job.state, job.message, job.finished_ns = state, message, time.time_ns()
        # Progress is the way towards a result: whole for a result, none for a job that ended without one, so a
        # failed job never reads as nearly done (its state and message say what happened).
        job.progress = 1.0 if state is JobState.SUCCEEDED else 0.0
        job.images = []  # free the pixels; the result is on disk

    def _update(self, job: _Job, progress: float, message: str) -> None:
        if job.cancel.is_set():
            raise _Cancelled
        with self._lock:
            job.progress, job.message = min(max(progress, 0.0), 1.0), message

    def _run(self, job: _Job) -> None:
        with self._lock:
            if job.state is not JobState.QUEUED:
                return
            job.state, job.started_ns, job.message = JobState.RUNNING, time.time_ns(), "running"
        try:
            images = self._capture(job) if job.live else list(job.images)
            # Detection is per image, so it carries the progress; the final solve is the last step.
            lo = 0.5 if job.live else 0.0
            message = self._camera(job, images, lo) if job.kind is JobKind.CAMERA else self._drill_axis(job, images, lo)
        except _Cancelled:
            with self._lock:
                self._finish(job, JobState.CANCELLED, "cancelled")
        except (DrillnavError, ValueError) as exc:
            with self._lock:
                self._finish(job, JobState.FAILED, str(exc))
        except Exception as exc:
            log.exception("calibration job %s crashed", job.id)
            with self._lock:
                self._finish(job, JobState.FAILED, f"internal error: {type(exc).__name__}: {exc}")
        else:
            with self._lock:
                self._finish(job, JobState.SUCCEEDED, message)

    def _capture(self, job: _Job) -> list[tuple[str, NDArray[np.uint8]]]:
        """Grab frames for ``live.seconds`` at ``live.fps``; progress 0..0.5."""
        assert job.live is not None and self.grab_frame is not None
        period = 1.0 / job.live.fps
        t0 = time.monotonic()
        frames: list[tuple[str, NDArray[np.uint8]]] = []
        while (elapsed := time.monotonic() - t0) < job.live.seconds:
            stamp_ns, image = self.grab_frame()
            frames.append((f"frame@{int(stamp_ns)}", _grey(np.asarray(image))))
            with self._lock:
                job.n_inputs = len(frames)
            self._update(job, 0.5 * elapsed / job.live.seconds, f"captured {len(frames)} frame(s)")
            next_t = t0 + len(frames) * period
            if job.cancel.wait(max(next_t - time.monotonic(), 0.0)):
                raise _Cancelled
        if not frames:
            raise DegenerateInput("no frame was captured")
        self._check_sizes(frames, job.camera)
        return frames

    def _camera(self, job: _Job, images: list[tuple[str, NDArray[np.uint8]]], lo: float) -> str:
        assert job.board is not None
        n = len(images)
        found, missing = [], []
        for i, (name, im) in enumerate(images):
            self._update(job, lo + (0.95 - lo) * i / n, f"detecting the board in {name} ({i + 1}/{n})")
            (found if detect_board(im, job.board) is not None else missing).append(i)
        self._update(job, 0.95, f"board found in {len(found)} of {n} views; solving")
        if not found:
            raise DegenerateInput(f"the board {job.board.kind} {job.board.cols}x{job.board.rows} was not found in any of the {n} views")
        if len(found) < 3:
            raise DegenerateInput(f"the board was found in only {len(found)} view(s) ({[images[i][0] for i in found]}); at least 3 are needed")
        # Only the views with a board go to the solver, so it does not search the others again.
        cal = calibrate_camera([images[i][1] for i in found], job.board)
        used = [images[found[k]][0] for k in cal.used_views]
        rejected = [images[found[k]][0] for k in cal.rejected_views]
        out = self._result_tmp(job)
        write_camera_calibration(out, cal.camera, rms_px=cal.rms_px, per_view_errors_px=list(cal.per_view_errors_px), label=job.label)
        self._commit_result(job, out)
        fx, fy = cal.camera.focal_px
        return (f"calibrated from {len(used)} views (rejected {rejected}, board not found in {[images[i][0] for i in missing]}): "
                f"fx {fx:.1f} fy {fy:.1f} px, RMS {cal.rms_px:.3f} px")

    def _drill_axis(self, job: _Job, images: list[tuple[str, NDArray[np.uint8]]], lo: float) -> str:
        assert job.camera is not None
        n = len(images)
        # The same search as ``drillnav calibrate drill-axis``: a frame without the jig is named in the failure.
        poses = find_jig_poses(images, job.camera, min_poses=MIN_POSES,
                               before_each=lambda i, name: self._update(job, lo + (0.95 - lo) * i / n, f"finding the jig in {name} ({i + 1}/{n})"))
        self._update(job, 0.95, f"jig found in {len(poses)} of {n} frames; fitting the axis")
        screw = fit_axis_screw(poses)
        out = self._result_tmp(job)
        write_drill_calibration(out, screw.axis, method="screw (common rotation axis, refined)", residual_mm=screw.residual_mm, residual_deg=screw.residual_deg, label=job.label)
        self._commit_result(job, out)
        return (f"drill axis from {len(poses)} jig poses over {screw.rotation_range_deg:.0f} deg: "
                f"residual {screw.residual_mm:.3f} mm / {screw.residual_deg:.3f} deg")

    def _result_tmp(self, job: _Job) -> Path:
        path = self.result_path(job.id)
        path.parent.mkdir(parents=True, exist_ok=True)
        return path.with_name("result.json.tmp")

    def _commit_result(self, job: _Job, tmp: Path) -> None:
        if job.cancel.is_set():  # a cancel during the solve still wins: no result appears
            tmp.unlink(missing_ok=True)
            raise _Cancelled
        os.replace(tmp, self.result_path(job.id))
