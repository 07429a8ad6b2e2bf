"""The twin's drill camera unplugged and plugged back, like a USB cable: the daemon's real reconnection path.

The device raises the webcam driver's ``CameraUnavailable`` (on read and on open) while unplugged; a twin daemon with a
scheduled unplug reports the loss (an error event naming the camera, ``/health`` 503 with the reason), reopens the camera
once it is back and the axis stream resumes, on the same camera thread and with no worker restarted.
"""

import json
import threading
import time

import httpx
import pytest

from drillnav.drivers.sim.devices import TwinDrillCamera
from drillnav.drivers.sim.scene import make_scene
from drillnav.drivers.webcam import CameraUnavailable
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.daemon import Daemon
from drillnav.service.settings import SettingsError, load_settings

from conftest import wait_for
from test_serve_lifecycle import config, settings_of

UNPLUG_EVERY_S, UNPLUG_S, RETRY_S = 8.0, 2.0, 0.5


def test_unplug_and_plug_raise_the_webcam_error_on_read_and_on_open():
    cam = TwinDrillCamera(scene=make_scene(seed=3, render=False), fps=30.0, loop_frames=2)
    with cam:
        assert cam.read().frame_id == 1
        cam.unplug()
        with pytest.raises(CameraUnavailable, match="camera twin stopped delivering frames"):
            cam.read()
    with pytest.raises(CameraUnavailable, match="camera twin cannot be opened"):
        cam.__enter__()
    cam.plug()
    with cam:
        assert cam.read().frame_id == 2  # the same device, numbering on


def test_an_unplug_longer_than_its_period_is_refused():
    with pytest.raises(SettingsError, match="camera_unplug_s"):
        load_settings(twin_scene={"camera_unplug_every_s": 2.0, "camera_unplug_s": 2.0})
    with pytest.raises(ValueError, match="unplug_s"):
        TwinDrillCamera(scene=make_scene(seed=3, render=False), unplug_every_s=1.0, unplug_s=1.5)


def test_a_scheduled_unplug_is_reported_and_the_axis_resumes_without_a_restart(tmp_path):
    cfg = config(tmp_path / "d", twin=True, recording="record_on_start = false",
                 camera=f"retry_s = {RETRY_S}",
                 twin_scene=f"camera_unplug_every_s = {UNPLUG_EVERY_S}\ncamera_unplug_s = {UNPLUG_S}")
    settings = settings_of(cfg)
    axes: list[float] = []
    events: list[tuple[float, dict]] = []
    lock = threading.Lock()

    def on_axis(_sample) -> None:
        with lock:
            axes.append(time.monotonic())

    def on_event(sample) -> None:
        with lock:
            events.append((time.monotonic(), json.loads(sample.payload.to_bytes())))

    def event_time(level: str, text: str, after: float) -> float | None:
        with lock:
            return next((t for t, e in events if t > after and e["level"] == level and text in e["message"]), None)

    with open_session(connect=list(settings.zenoh.listen)) as session:
        session.declare_subscriber(key("drillnav", "axis_carm"), on_axis)
        session.declare_subscriber(key("drillnav", "events"), on_event)
        with Daemon(settings) as d, httpx.Client(base_url=f"http://127.0.0.1:{settings.api.port}", timeout=10) as client:
            camera_thread = next(t for t in d._threads if t.name == "camera")
            # On a loaded machine the first axis may come after the first unplug: the window that counts is the first
            # one that begins while the axis streams.
            assert wait_for(lambda: d.camera_device.plugged and len([t for t in axes if t > time.monotonic() - 0.5]) >= 5, 120), "no axis stream"
            t_ready, losses_before = time.monotonic(), d.pump.losses

            assert wait_for(lambda: event_time("error", "camera twin", t_ready) is not None, UNPLUG_EVERY_S + 5), events
            t_lost = event_time("error", "camera twin", t_ready)
            r = client.get("/health")
            assert r.status_code == 503 and "camera twin" in r.json()["detail"] and "unplugged" in r.json()["detail"], r.text
            assert d.wedged() is None  # the pump mends it by itself: not a reason for the watchdog to restart the daemon
            time.sleep(1.0)
            with lock:
                assert not [t for t in axes if t > t_lost + 0.5], "axes went on while the camera was unplugged"

            assert wait_for(lambda: event_time("info", "camera twin is back", t_lost) is not None, UNPLUG_S + 5), events
            t_back = event_time("info", "camera twin is back", t_lost)
            assert t_back - t_lost >= UNPLUG_S - 0.5  # back only once plugged in again
            assert wait_for(lambda: len([t for t in axes if t > t_back]) >= 10, 15), "the axis stream did not resume"
            assert wait_for(lambda: client.get("/health").status_code == 200, 5), client.get("/health").text
            assert camera_thread.is_alive() and d.pump.losses == losses_before + 1 and d.node.counters.thread_restarts == 0
            rendered, loop = client.get("/status").json()["twin_camera_rendered"]  # what the soak waits on before its RSS baseline
            assert 1 <= rendered <= loop == len(d.camera_device.poses)
            with lock:  # reported once per unplug, not once per retry
                assert sum(t > t_ready and e["level"] == "error" and "camera twin" in e["message"] for t, e in events) == 1
