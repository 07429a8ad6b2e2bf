"""Calibration jobs over the REST API: a real uvicorn server on loopback, an httpx client, twin images with known truth."""

import contextlib
import json
import socket
import threading
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
import uvicorn

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.line import Line3D
from drillnav.schemas.calibration import write_camera_calibration
from drillnav.service.api import create_app
from drillnav.service.calibration_jobs import CalibrationJobs, JobKind, JobNotSucceeded

from twin_images import board_views as shared_board_views  # noqa: E402
from twin_images import field_marker_frame  # noqa: E402
from twin_images import jig_frames as shared_jig_frames  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
TOKEN = "calib-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
BOARD = "checkerboard:9x6:25mm"
K = np.array([[560.0, 0, 322.0], [0, 560.0, 238.0], [0, 0, 1]])
TRUE = PinholeCamera(width=640, height=480, camera_matrix=K)
AXIS_POINT_MM = np.array([10.0, 15.0, 0.0])
AXIS_DIRECTION = np.array([0.05, -0.03, 1.0]) / np.linalg.norm([0.05, -0.03, 1.0])


# -- twin images: through the true (undistorted 640x480) camera ------------------------------------------------


def board_views(n, *, seed=0):
    """Checkerboard 9x6 inner corners, 25 mm squares, one white square of margin; tilted up to 30 deg."""
    return shared_board_views(TRUE, n, spin_deg=15.0, offset_mm=(20.0, 15.0), distance_mm=(430.0, 480.0), seed=seed)


def jig_frames(n=8, span_deg=120.0, seed=0):
    """The ArUco jig turning about the true drill axis, 150 mm in front of the camera."""
    return shared_jig_frames(TRUE, Line3D(point_mm=AXIS_POINT_MM, direction=AXIS_DIRECTION), n, span_deg=span_deg, seed=seed)


def png(image):
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


# -- a real server ------------------------------------------------------------------------------------------


class FakeState:
    """The parts of the daemon the API needs, plus calibration jobs."""

    token = TOKEN

    def __init__(self, jobs):
        self.calibration_jobs = jobs

    def status(self):
        return {"state": "idle"}

    def registration(self):
        return None

    def request_registration(self):
        pass

    def start_recording(self, name):
        return []

    def stop_recording(self, name):
        return []

    def recordings(self):
        return {}

    def shoot(self, view):
        raise ValueError(view)


@contextlib.contextmanager
def serve(app):
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    t = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    t.start()
    try:
        for _ in range(200):
            if server.started:
                break
            time.sleep(0.02)
        assert server.started, "uvicorn did not start"
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as client:
            yield client
    finally:
        server.should_exit = True
        t.join(5)
        sock.close()


class Installs(list):
    def __call__(self, kind, path):
        self.append((kind, Path(path)))


class SlowCamera:
    """A live camera that gives blank frames; counts grabs."""

    def __init__(self, frames=None):
        self.frames = frames or [np.full((480, 640), 128, np.uint8)]
        self.grabs = 0

    def __call__(self):
        self.grabs += 1
        return time.time_ns(), self.frames[(self.grabs - 1) % len(self.frames)]


@pytest.fixture()
def api(tmp_path):
    """(client, jobs, installs, camera) of a server whose jobs have a live camera."""
    (tmp_path / "active").mkdir()
    installs, camera = Installs(), SlowCamera()
    jobs = CalibrationJobs(
        work_dir=tmp_path / "work", max_workers=2, active_camera_path=tmp_path / "active" / "camera.json",
        active_drill_path=tmp_path / "active" / "drill.json", grab_frame=camera, on_install=installs,
    )
    with jobs, serve(create_app(state=FakeState(jobs))) as client:
        yield client, jobs, installs, camera


def wait_finished(client, job_id, timeout_s=15.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        job = client.get(f"/calibration/jobs/{job_id}").json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not finish in {timeout_s} s: {job}")


def submit(client, files, **form):
    return client.post("/calibration/jobs", data=form, files=[("files", f) for f in files], headers=AUTH)


# -- tests --------------------------------------------------------------------------------------------------


def test_camera_job_from_uploads_then_install(api):
    client, jobs, installs, _ = api
    views = board_views(10)
    r = submit(client, [(f"v{i:02d}.png", png(v), "image/png") for i, v in enumerate(views)], kind="camera", board=BOARD, label="twin")
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["kind"] == "camera" and job["state"] in ("queued", "running", "succeeded") and job["inputs"] == 10
    job = wait_finished(client, job["id"])
    assert job["state"] == "succeeded", job["message"]
    assert job["progress"] == 1.0 and job["finished_ns"] >= job["created_ns"] and "fx" in job["message"]
    assert [j["id"] for j in client.get("/calibration/jobs").json()] == [job["id"]]

    r = client.get(f"/calibration/jobs/{job['id']}/result")
    assert r.status_code == 200 and 'filename="camera.json"' in r.headers["content-disposition"]
    doc = r.json()
    assert doc["schema"] == "drillnav.camera/1" and doc["label"] == "twin" and doc["image_size"] == [640, 480]
    k = np.asarray(doc["camera_matrix"])
    assert abs(k[0, 0] / 560 - 1) < 0.01 and abs(k[1, 1] / 560 - 1) < 0.01 and doc["rms_px"] < 0.5
    assert json.loads(jobs.result_path(job["id"]).read_text()) == doc

    # Nothing is active until someone installs it.
    active = jobs.active_paths[JobKind.CAMERA]
    assert not active.exists() and installs == []
    r = client.post(f"/calibration/jobs/{job['id']}/install", headers=AUTH)
    assert r.status_code == 200, r.text
    assert r.json() == {"id": job["id"], "kind": "camera", "installed_path": str(active)}
    assert json.loads(active.read_text()) == doc and installs == [("camera", active)]
    assert client.get(f"/calibration/jobs/{job['id']}").json()["installed_path"] == str(active)
    assert not list(active.parent.glob("*.tmp"))


def test_drill_axis_job_uses_the_active_camera(api):
    client, jobs, installs, _ = api
    frames = [(f"f{i}.png", png(f), "image/png") for i, f in enumerate(jig_frames())]
    r = submit(client, frames, kind="drill-axis")
    assert r.status_code == 409 and "active camera calibration" in r.json()["detail"]
    write_camera_calibration(jobs.active_paths[JobKind.CAMERA], TRUE, rms_px=0.1, per_view_errors_px=[], label="truth")
    r = submit(client, frames, kind="drill-axis")
    assert r.status_code == 202, r.text
    job = wait_finished(client, r.json()["id"])
    assert job["state"] == "succeeded", job["message"]
    doc = client.get(f"/calibration/jobs/{job['id']}/result").json()
    assert doc["schema"] == "drillnav.drill/1"
    d = np.asarray(doc["axis_camera"]["direction"])
    assert np.degrees(np.arccos(min(abs(d @ AXIS_DIRECTION), 1.0))) < 0.5
    p = np.asarray(doc["axis_camera"]["point_mm"]) - AXIS_POINT_MM
    assert np.linalg.norm(p - (p @ AXIS_DIRECTION) * AXIS_DIRECTION) < 0.5  # distance of the fitted point from the true axis
    r = client.post(f"/calibration/jobs/{job['id']}/install", headers=AUTH)
    assert r.status_code == 200 and installs == [("drill-axis", Path(r.json()["installed_path"]))]
    assert json.loads(Path(r.json()["installed_path"]).read_text()) == doc


def test_token_required(api):
    client, jobs, _, _ = api
    files = [("files", ("a.png", png(np.zeros((8, 8), np.uint8)), "image/png"))]
    assert client.post("/calibration/jobs", data={"kind": "camera", "board": BOARD}, files=files).status_code == 401
    wrong = {"Authorization": "Bearer nope"}
    assert client.post("/calibration/jobs", data={"kind": "camera", "board": BOARD}, files=files, headers=wrong).status_code == 403
    assert client.delete("/calibration/jobs/abc").status_code == 401
    assert client.post("/calibration/jobs/abc/install", headers=wrong).status_code == 403
    assert jobs.list_jobs() == []
    assert client.get("/calibration/jobs").status_code == 200  # reading needs no token


def test_request_validation(api):
    client, jobs, _, _ = api
    good = ("good.png", png(board_views(1)[0]), "image/png")
    r = submit(client, [good, ("notes.txt", b"these are not pixels", "text/plain")], kind="camera", board=BOARD)
    assert r.status_code == 422 and "notes.txt" in r.json()["detail"] and "not a readable image" in r.json()["detail"]
    r = submit(client, [good], kind="camera", board="checkerboard:9by6")
    assert r.status_code == 422 and "bad board 'checkerboard:9by6'" in r.json()["detail"]
    r = submit(client, [good], kind="camera")
    assert r.status_code == 422 and "board" in r.json()["detail"]
    r = submit(client, [], kind="camera", board=BOARD)
    assert r.status_code == 422 and "no files" in r.json()["detail"]
    r = submit(client, [good], kind="lens", board=BOARD)
    assert r.status_code == 422 and "unknown kind 'lens'" in r.json()["detail"]
    r = submit(client, [], kind="camera", board=BOARD, live_seconds="5")
    assert r.status_code == 422 and "live_fps" in r.json()["detail"]
    r = submit(client, [], kind="camera", board=BOARD, live_seconds="5", live_fps="500")
    assert r.status_code == 422 and "live_fps" in r.json()["detail"]
    assert jobs.list_jobs() == []


def test_live_capture_without_camera_refused(tmp_path):
    with CalibrationJobs(work_dir=tmp_path) as jobs, serve(create_app(state=FakeState(jobs))) as client:
        r = submit(client, [], kind="camera", board=BOARD, live_seconds="2", live_fps="5")
        assert r.status_code == 422 and "no camera" in r.json()["detail"]


def test_camera_job_from_live_frames(api):
    client, jobs, _, camera = api
    camera.frames = board_views(6, seed=4)
    r = submit(client, [], kind="camera", board=BOARD, live_seconds="0.6", live_fps="10")
    assert r.status_code == 202 and r.json()["source"] == "live"
    job = wait_finished(client, r.json()["id"])
    assert job["state"] == "succeeded", job["message"]
    assert 3 <= job["inputs"] == camera.grabs <= 8


def test_cancel_running_job(api):
    client, jobs, _, camera = api
    r = submit(client, [], kind="camera", board=BOARD, live_seconds="60", live_fps="5")
    job_id = r.json()["id"]
    for _ in range(200):
        job = client.get(f"/calibration/jobs/{job_id}").json()
        if job["state"] == "running" and camera.grabs > 0:
            break
        time.sleep(0.02)
    assert job["state"] == "running"
    t0 = time.monotonic()
    r = client.delete(f"/calibration/jobs/{job_id}", headers=AUTH)
    assert r.status_code == 200 and r.json()["state"] in ("running", "cancelled")
    job = wait_finished(client, job_id, timeout_s=5)
    assert job["state"] == "cancelled" and time.monotonic() - t0 < 2.0
    assert client.get(f"/calibration/jobs/{job_id}/result").status_code == 409
    assert client.delete(f"/calibration/jobs/{job_id}", headers=AUTH).status_code == 409
    assert not jobs.result_path(job_id).exists()


def test_unknown_and_failed_jobs(api):
    client, jobs, installs, _ = api
    assert client.get("/calibration/jobs/0123abcd/result").status_code == 404
    assert client.get("/calibration/jobs/0123abcd").status_code == 404
    assert client.post("/calibration/jobs/0123abcd/install", headers=AUTH).status_code == 404
    blank = ("blank.png", png(np.full((480, 640), 128, np.uint8)), "image/png")
    r = submit(client, [blank, blank, blank], kind="camera", board=BOARD)
    job = wait_finished(client, r.json()["id"])
    assert job["state"] == "failed" and "not found in any of the 3 views" in job["message"]
    assert job["progress"] == 0.0  # ended without a result: not left at the 0.95 it had reached
    r = client.post(f"/calibration/jobs/{job['id']}/install", headers=AUTH)
    assert r.status_code == 409 and "failed" in r.json()["detail"]
    assert client.get(f"/calibration/jobs/{job['id']}/result").status_code == 409
    assert installs == [] and not jobs.active_paths[JobKind.CAMERA].exists()
    with pytest.raises(JobNotSucceeded):
        jobs.install(job["id"])


def test_live_drill_axis_job_over_field_markers_fails_in_one_line_naming_them(api):
    client, jobs, installs, camera = api
    write_camera_calibration(jobs.active_paths[JobKind.CAMERA], TRUE, rms_px=0.1, per_view_errors_px=[], label="truth")
    camera.frames = [field_marker_frame(TRUE)]  # the camera sees the field markers, not the jig
    r = submit(client, [], kind="drill-axis", live_seconds="0.5", live_fps="10")
    assert r.status_code == 202, r.text
    job = wait_finished(client, r.json()["id"])
    assert job["state"] == "failed" and job["progress"] == 0.0, job
    assert "\n" not in job["message"] and "OpenCV" not in job["message"] and "internal error" not in job["message"]
    assert job["message"].startswith(f"the jig board was found in only 0 of {job['inputs']} frames (at least 3 are needed): ")
    assert job["message"].endswith("saw tags 3, 7, 12, 20 (field markers), none of the jig's 16 tags (ids 100-115)")
    assert client.post(f"/calibration/jobs/{job['id']}/install", headers=AUTH).status_code == 409 and installs == []


def test_routes_only_with_calibration_jobs():
    class NoJobs(FakeState):
        def __init__(self):
            pass

    paths = {getattr(r, "path", "") for r in create_app(state=NoJobs()).routes}
    assert "/recordings" in paths and not any(p.startswith("/calibration") for p in paths)


@pytest.mark.skipif(not (DATA / "chessboard-right").is_dir(), reason="../shared/data/chessboard-right is not present")
def test_real_photos(api):
    client, _, _, _ = api
    paths = sorted((DATA / "chessboard-right").glob("*.jpg"))
    r = submit(client, [(p.name, p.read_bytes(), "image/jpeg") for p in paths], kind="camera", board=BOARD)
    assert r.status_code == 202, r.text
    job = wait_finished(client, r.json()["id"])
    assert job["state"] == "succeeded", job["message"]
    doc = client.get(f"/calibration/jobs/{job['id']}/result").json()
    assert doc["image_size"] == [640, 480] and doc["rms_px"] < 1.0
