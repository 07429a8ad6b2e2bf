"""The daemon on real devices (an MJPG file as the camera) starts uncalibrated, and camera calibrations installed through
the REST API reach the node as one new bundle: the marker locator uses the new intrinsics (the stale-locator bug).
/health turns 503 while the camera is unplugged and 200 once it is back."""

import time

import cv2
import httpx
import numpy as np

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.line import Line3D
from drillnav.schemas.calibration import write_drill_calibration
from drillnav.service.daemon import Daemon

from test_serve_lifecycle import config, settings_of
from twin_images import board_views

AUTH = {"Authorization": "Bearer test-token-1-of-16-chars"}
BOARD = "checkerboard:9x6:25mm"


def camera(fx: float) -> PinholeCamera:
    return PinholeCamera(width=640, height=480, camera_matrix=np.array([[fx, 0, 322.0], [0, fx, 238.0], [0, 0, 1]]))


def install_camera_job(client: httpx.Client, fx: float) -> dict:
    """A camera calibration job on board views rendered through a camera of focal length ``fx``, then installed."""
    views = board_views(camera(fx), 8, spin_deg=15.0, offset_mm=(20.0, 15.0), distance_mm=(430.0, 480.0))
    files = [("files", (f"v{i}.png", cv2.imencode(".png", v)[1].tobytes(), "image/png")) for i, v in enumerate(views)]
    r = client.post("/calibration/jobs", data={"kind": "camera", "board": BOARD}, files=files, headers=AUTH)
    assert r.status_code == 202, r.text
    url = f"/calibration/jobs/{r.json()['id']}"
    deadline = time.monotonic() + 60
    while (job := client.get(url).json())["state"] not in ("succeeded", "failed", "cancelled") and time.monotonic() < deadline:
        time.sleep(0.1)
    assert job["state"] == "succeeded", job
    r = client.post(url + "/install", headers=AUTH)
    assert r.status_code == 200, r.text
    return job


def test_starts_uncalibrated_then_rest_installs_reach_the_locator(tmp_path):
    drill = tmp_path / "drill.json"
    write_drill_calibration(drill, Line3D(point_mm=[10.0, 15.0, 0.0], direction=[0.05, -0.03, 1.0]), method="test", residual_mm=0.3, residual_deg=0.4, label="test")
    cfg = config(tmp_path / "d", camera=f'device = "{tmp_path / "d" / "video0.avi"}"\ndrill_calibration = "{drill}"',
                 recording="record_on_start = false")
    settings = settings_of(cfg)
    with Daemon(settings) as d, httpx.Client(base_url=f"http://127.0.0.1:{settings.api.port}", timeout=30) as client:
        deadline = time.monotonic() + 20
        while client.get("/status").json()["frames_received"] < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        st = client.get("/status").json()
        assert st["state"] == "uncalibrated" and not st["calibrated"] and st["frames_received"] >= 3, st  # the camera streams
        assert d.node.calibration is None and client.get("/health").status_code == 200

        install_camera_job(client, 560.0)
        bundle = d.node.calibration
        assert bundle is not None and client.get("/status").json()["state"] == "waiting for fluoroscopy"
        assert bundle.locator.camera is bundle.camera and abs(bundle.camera.camera_matrix[0, 0] / 560.0 - 1) < 0.01
        assert np.allclose(bundle.axis_drill.direction, Line3D(point_mm=[0, 0, 0], direction=[0.05, -0.03, 1.0]).direction)
        # The drill file's stated uncertainty came with its axis (held while the camera was missing): the bound's.
        assert (bundle.axis_uncertainty.sigma_mm, bundle.axis_uncertainty.rms_tilt_deg) == (0.3, 0.4)

        install_camera_job(client, 620.0)  # a new camera calibration replaces the bundle whole
        new = d.node.calibration
        assert new is not bundle and new.locator is not bundle.locator
        assert new.locator.camera is new.camera and abs(new.locator.camera.camera_matrix[0, 0] / 620.0 - 1) < 0.01
        assert bundle.locator.camera.camera_matrix[0, 0] < 600  # the old bundle was not mutated under a frame that holds it
        assert new.axis_uncertainty == bundle.axis_uncertainty  # a camera install keeps the drill's

        # Health reflects what a client sees: the camera unplugged is a 503 naming it (but not a wedge that the watchdog
        # would restart the daemon for); re-plugged, 200 again.
        device = tmp_path / "d" / "video0.avi"
        device.rename(tmp_path / "d" / "unplugged.avi")
        deadline = time.monotonic() + 15
        while (r := client.get("/health")).status_code == 200 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert r.status_code == 503 and "camera stalled" in r.json()["detail"], r.text
        assert d.wedged() is None
        (tmp_path / "d" / "unplugged.avi").rename(device)
        deadline = time.monotonic() + 15
        while (r := client.get("/health")).status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert r.status_code == 200, r.text
