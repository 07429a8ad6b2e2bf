"""The service on real components: zenoh on loopback, MCAP files, uvicorn + httpx, the daemon on the twin."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import uvicorn
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from drillnav.drivers.sim.anatomy import CORRIDORS
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.transforms import apply
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key, topic_for_key
from drillnav.service.api import create_app
from drillnav.service.bus import open_session
from drillnav.service.recorder import Recorder
from drillnav.service.settings import SettingsError, load_settings

from conftest import free_endpoint, free_port


def endpoints():
    return free_endpoint()


def test_messages_round_trip():
    img = (np.arange(64 * 48) % 251).astype(np.uint8).reshape(48, 64)
    back, stamp, frame = msg.decode_compressed_image(msg.compressed_image(img, stamp_ns=1_700_000_000_123_456_789, frame_id="drill_camera", fmt="png"))
    np.testing.assert_array_equal(back, img)
    assert stamp == 1_700_000_000_123_456_789 and frame == "drill_camera"
    with pytest.raises(ValueError, match="malformed JSON"):
        msg.decode_json(b"{not json")
    with pytest.raises(ValueError, match=r"FluoroShot\.projection: Field required"):
        msg.FluoroShot.from_bytes(msg.encode_json({"stamp_ns": 1, "view": "ap", "png16_base64": "AAAA"}))
    assert topic_for_key("drillnav", "drillnav/overlay/inlet").schema_name == "foxglove.CompressedImage"


def test_zenoh_peers_on_loopback():
    ep = endpoints()
    got = []
    with open_session(listen=[ep]) as a, open_session(connect=[ep]) as b:
        b.declare_subscriber(key("drillnav", "axis_carm"), lambda s: got.append(msg.decode_json(s.payload.to_bytes())))
        time.sleep(0.5)
        for i in range(5):
            a.put(key("drillnav", "axis_carm"), msg.encode_json({"stamp_ns": i}))
            time.sleep(0.02)
        time.sleep(0.5)
    assert [g["stamp_ns"] for g in got] == list(range(5))


def test_recorder_writes_indexed_mcap_with_schemas(tmp_path):
    ep = endpoints()
    with open_session(listen=[ep]) as a, open_session(connect=[ep]) as b:
        rec = Recorder(session=b, prefix="drillnav", folder=tmp_path, name="t1")
        time.sleep(0.5)
        img = np.zeros((32, 32), np.uint8)
        for i in range(20):
            a.put(key("drillnav", "camera_image"), msg.compressed_image(img, stamp_ns=i, frame_id="d", fmt="png"))
            a.put(key("drillnav", "axis_carm"), msg.encode_json({"stamp_ns": i}))
            time.sleep(0.01)
        time.sleep(0.5)
        (path,) = rec.close()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
        assert schemas == {"foxglove.CompressedImage": "protobuf", "drillnav.DrillAxis": "jsonschema"}
        counts = {}
        for _, channel, _ in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert counts == {"drillnav/camera/image": 20, "drillnav/axis/carm": 20}


RECORD_CHILD = r"""
import sys, time, numpy as np
from drillnav.service.bus import open_session
from drillnav.service.recorder import Recorder
from drillnav.drivers.sim.anatomy import CORRIDORS
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.transforms import apply
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key
ep, folder = sys.argv[1], sys.argv[2]
with open_session(listen=[ep]) as a:
    rec = Recorder(session=a, prefix="drillnav", folder=folder, name="crash", chunk_size=4096)
    noise = np.random.default_rng(0).integers(0, 255, (64, 64), dtype=np.uint8)
    for i in range(400):
        a.put(key("drillnav", "camera_image"), msg.compressed_image(noise, stamp_ns=i, frame_id="d", fmt="png"))
        print(i, flush=True)
        time.sleep(0.002)
    time.sleep(60)
"""


def test_recorder_rotates_by_time(tmp_path):
    ep = endpoints()
    with open_session(listen=[ep]) as a, open_session(connect=[ep]) as b:
        rec = Recorder(session=b, prefix="drillnav", folder=tmp_path, name="rot", rotate_seconds=0.4)
        time.sleep(0.5)
        for i in range(30):
            a.put(key("drillnav", "axis_carm"), msg.encode_json({"stamp_ns": i}))
            time.sleep(0.05)
        time.sleep(0.3)
        files = rec.close()
    assert len(files) >= 3 and len(set(files)) == len(files)
    total = 0
    for path in files:  # every rotated file is finished: summary and index written
        with open(path, "rb") as f:
            reader = make_reader(f)
            assert reader.get_summary() is not None
            total += sum(1 for _ in reader.iter_messages())
    assert total == 30


def test_sigkilled_recorder_leaves_a_readable_file(tmp_path):
    ep = endpoints()
    child = subprocess.Popen([sys.executable, "-c", RECORD_CHILD, ep, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    last = None
    for line in child.stdout:
        last = int(line)
        if last == 399:
            break
    time.sleep(0.5)
    child.send_signal(signal.SIGKILL)
    child.wait()
    (path,) = list(tmp_path.glob("crash-*.mcap"))
    messages = 0
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                if type(record).__name__ == "Message":
                    messages += 1
        except Exception:  # the unfinished tail chunk; everything before it was read
            pass
    # Every complete chunk survived: at most one 4 KiB chunk (a few ~4 KiB images) is lost.
    assert messages >= 400 - 3


class FakeState:
    token = "secret-token"

    def __init__(self):
        self.refreshed = 0
        self.recs = {}
        self.unhealthy = None

    def status(self):
        return {"state": "registered"}

    def health(self):
        return self.unhealthy

    def registration(self):
        return None

    def request_registration(self):
        self.refreshed += 1

    def start_recording(self, name):
        if name in self.recs:
            raise KeyError(f"recording '{name}' is already running")
        self.recs[name] = [f"{name}.mcap"]
        return self.recs[name]

    def stop_recording(self, name):
        if name not in self.recs:
            raise KeyError(f"no running recording named '{name}'")
        return self.recs.pop(name)

    def recordings(self):
        return dict(self.recs)

    def shoot(self, view):
        raise ValueError(f"unknown view '{view}'")


@pytest.fixture()
def http_server():
    state = FakeState()
    port = free_port()
    config = uvicorn.Config(create_app(state=state), host="127.0.0.1", port=port, log_level="warning")
    server = uvicorn.Server(config)
    t = threading.Thread(target=server.run, daemon=True)
    t.start()
    for _ in range(100):
        if server.started:
            break
        time.sleep(0.05)
    yield state, f"http://127.0.0.1:{port}"
    server.should_exit = True
    t.join(5)


def test_rest_api_over_http(http_server):
    state, base = http_server
    auth = {"Authorization": "Bearer secret-token"}
    with httpx.Client(base_url=base, timeout=5) as c:
        assert c.get("/health").json() == {"status": "ok"}
        state.unhealthy = "camera stalled: no frame for 3.0 s"
        r = c.get("/health")
        assert r.status_code == 503 and r.json()["detail"] == "camera stalled: no frame for 3.0 s"
        state.unhealthy = None
        assert c.get("/registration").status_code == 404
        assert c.post("/registration/refresh").status_code == 401
        assert c.post("/registration/refresh", headers={"Authorization": "Bearer wrong-token"}).status_code == 403
        assert c.post("/registration/refresh", headers=auth).status_code == 202 and state.refreshed == 1
        assert c.post("/recordings", json={"name": "case 7!"}, headers=auth).status_code == 422
        assert c.post("/recordings", json={"name": "case7"}, headers=auth).status_code == 201
        assert c.post("/recordings", json={"name": "case7"}, headers=auth).status_code == 409
        assert c.delete("/recordings/case7", headers=auth).json()["files"] == ["case7.mcap"]
        assert c.delete("/recordings/case7", headers=auth).status_code == 404
        assert "unknown view" in c.post("/carm/shots", json={"view": "zz"}, headers=auth).json()["detail"]
        assert "/recordings" in c.get("/openapi.json").json()["paths"]


def test_settings_refuse_bad_values(tmp_path, monkeypatch):
    cfg = tmp_path / "d.toml"
    cfg.write_text(f"[api]\nport = {65535 + 1}\n")  # past the last TCP port: refused by the settings, never bound
    with pytest.raises(SettingsError, match="api.port"):
        load_settings(cfg)
    cfg.write_text('[api]\nprot = 8080\n')
    with pytest.raises(SettingsError, match="api.prot"):
        load_settings(cfg)
    monkeypatch.setenv("DRILLNAV_API__PORT", "8123")
    assert load_settings(None).api.port == 8123
    with pytest.raises(SettingsError, match="does not exist"):
        load_settings(tmp_path / "none.toml")


def test_unplugged_camera_is_a_clear_error():
    from drillnav.drivers.webcam import CameraUnavailable, Webcam

    with pytest.raises(CameraUnavailable, match="/dev/video99"):
        with Webcam(device="/dev/video99", reconnect_attempts=0):
            pass


def test_camera_unplugged_and_replugged_comes_back(tmp_path):
    """A real OpenCV capture on a file that stands in for the device node: it vanishes (unplug) and returns (re-plug)."""
    from drillnav.drivers.webcam import Webcam
    from drillnav.service.camera_pump import CameraPump
    from file_camera import camera_file

    device = camera_file(tmp_path, frames=10)
    frames, events, stop = [], [], threading.Event()
    pump = CameraPump(device=Webcam(device=str(device), reconnect_attempts=1, reconnect_interval_s=0.05), name=str(device),
                      on_frame=frames.append, on_event=lambda level, m: events.append((level, m)), stop=stop, retry_s=0.1)
    t = threading.Thread(target=pump.run, daemon=True)
    t.start()

    def wait_for(cond, timeout=10.0):
        t0 = time.monotonic()
        while not cond() and time.monotonic() - t0 < timeout:
            time.sleep(0.02)
        return cond()

    try:
        assert wait_for(lambda: len(frames) >= 5) and frames[0].image.shape == (240, 320, 3) and frames[0].stamp_ns > 0
        device.rename(tmp_path / "unplugged.avi")
        assert wait_for(lambda: any(level == "error" for level, _ in events)), events
        (level, message), = events
        assert str(device) in message and "retrying every 0.1 s" in message and not pump.connected
        n = len(frames)
        time.sleep(0.5)
        assert len(frames) == n  # nothing while unplugged, and the loop is still alive
        assert t.is_alive()
        (tmp_path / "unplugged.avi").rename(device)
        assert wait_for(lambda: ("info", f"camera {device} is back") in events), events
        assert wait_for(lambda: len(frames) > n + 5)
        assert pump.losses == 1 and pump.errors == [message]
    finally:
        stop.set()
        t.join(timeout=5)
    assert not t.is_alive()


def _page_shows_the_breach(base: str) -> None:
    """The daemon's page in video-CT mode shows the breach verdict and its alert (skipped outside CI without Chromium)."""
    from display_browser import launch, require_chromium

    exe = require_chromium()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = launch(pw, exe)
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 1000}, bypass_csp=True)  # the test's own probes are evaluated
            page.goto(f"{base}/?mode=ct")
            # One check in one evaluation: the twin's loop moves in and out of bone, so the next axis (10 a second) can turn
            # the verdict back to CLEAR between a wait and a separate read (seen once: "CLEAR (AIIS-PSIS): min clearance 1.8 mm").
            page.wait_for_function("window.drillnav.ctDrawn && window.drillnav.ctDrawn.breach === true && !window.drillnav.ctDrawn.stale"
                                   " && window.drillnav.alerts.some(a => a[1].startsWith('BREACH'))"
                                   " && document.querySelector('#verdict').innerText.startsWith('BREACH (AIIS-PSIS)')", timeout=30000)
        finally:
            browser.close()


@pytest.mark.timeout(600)  # the twin's up-front build (scene and CT) takes minutes on a loaded machine
def test_daemon_on_the_twin_streams_the_axis(tmp_path):
    """The whole daemon in a subprocess: twin camera, C-arm shots through the watched folder, axis on zenoh, SIGTERM."""
    ep = endpoints()
    api_port, scp_port = free_port(), free_port()
    base = f"http://127.0.0.1:{api_port}"
    cfg = tmp_path / "drillnav.toml"
    cfg.write_text(
        f'twin = true\n[zenoh]\nlisten = ["{ep}"]\n[api]\nport = {api_port}\ntoken = "test-token-1-of-16-chars"\n'
        f'[dicom]\nwatch_folder = "{tmp_path / "in"}"\nscp_port = {scp_port}\n[recording]\nfolder = "{tmp_path / "rec"}"\n[twin_scene]\nseed = 5\nct_voxel_mm = 2.0\naim_off_mm = 20\n'
        f'[calibration]\nfolder = "{tmp_path / "cal"}"\n'
        # 10 frames a second are plenty for what this checks (10 axes in sequence, a 5 fps live calibration capture) and
        # leave the CPU to the CT registration worker this test waits on (at 30 fps the frame path takes most of a core).
        '[camera]\nfps = 10\n'
    )
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "drillnav.service.cli", "serve", "--config", str(cfg)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        axes, axes_ct = [], []
        with open_session(connect=[ep]) as s:
            s.declare_subscriber(key("drillnav", "axis_carm"), lambda smp: axes.append(msg.decode_json(smp.payload.to_bytes())))
            s.declare_subscriber(key("drillnav", "axis_ct"), lambda smp: axes_ct.append(msg.decode_json(smp.payload.to_bytes())))
            # The twin builds its scene and CT up front: minutes on a loaded 2-core machine (faster start-up is another change).
            deadline = time.monotonic() + 420
            while time.monotonic() < deadline and len(axes) < 10 and proc.poll() is None:
                time.sleep(0.2)
            assert len(axes) >= 10, "no drill axis streamed"
            a = axes[-1]
            assert [x["sequence"] for x in axes[-5:]] == list(range(axes[-5]["sequence"], axes[-5]["sequence"] + 5)) and a["reliable"] is True
            assert a["frame_id"] == "carm" and abs(np.linalg.norm(a["direction"]) - 1) < 1e-6 and a["predicted_error"]["position_mm"] > 0
            status = httpx.get(f"{base}/status", timeout=5).json()
            assert status["state"] == "registered" and status["axes_published"] >= 10
            # The calibration job and the corrupt file do not need the CT and have deadlines of tens of seconds: they run
            # while the CT registers in its worker (tens of seconds). The C-STORE shot's 5 s bound is checked after it.
            # A live calibration job captures the daemon's own camera frames; the twin's field holds no board, so it fails and says why.
            auth = {"Authorization": "Bearer test-token-1-of-16-chars"}
            r = httpx.post(f"{base}/calibration/jobs", data={"kind": "camera", "board": "checkerboard:9x6:25mm", "live_seconds": "1", "live_fps": "5"}, headers=auth, timeout=10)
            assert r.status_code == 202, r.text
            job_url = f"{base}/calibration/jobs/{r.json()['id']}"
            t0 = time.monotonic()
            while time.monotonic() - t0 < 30 and (job := httpx.get(job_url, timeout=5).json())["state"] not in ("succeeded", "failed", "cancelled"):
                time.sleep(0.2)
            assert job["state"] == "failed" and job["inputs"] >= 3 and "not found in any" in job["message"], job
            assert httpx.post(job_url + "/install", headers=auth, timeout=5).status_code == 409
            # A corrupt DICOM dropped in the watched folder is refused with an event, and nothing stops. It is longer than a
            # DICOM preamble (132 bytes), so it is refused once it holds still; a shorter one might still be being written and
            # waits 10 s first (that wait is tests/test_folder_watch.py's, through the same watcher).
            (tmp_path / "in" / "broken.dcm").write_bytes(b"garbage" * 40)
            t0 = time.monotonic()
            errors: list[str] = []
            while time.monotonic() - t0 < 20 and not any("broken.dcm" in e for e in errors):
                time.sleep(0.5)
                errors = httpx.get(f"{base}/status", timeout=5).json()["device_errors"]
            assert any("broken.dcm" in e for e in errors), errors
            # Live video-CT: the twin's CT registered to the shots, every axis carried into V with conformance to the nearest plan.
            while time.monotonic() < deadline and len(axes_ct) < 5 and proc.poll() is None:
                time.sleep(0.2)
            # The twin aims 20 mm beside the planned corridor ([twin_scene] aim_off_mm). The AIIS-PSIS corridor's bone is
            # wide: over the loop (9 s at 10 frames/s) some frames stay in bone, so a breach is awaited within three loops.
            t0 = time.monotonic()
            while time.monotonic() - t0 < 30 and axes_ct and not any(x["conformance"]["breach"] for x in list(axes_ct)):
                time.sleep(0.2)
        assert len(axes_ct) >= 5, "no drill axis in the CT frame streamed"
        c = axes_ct[-1]
        truth = make_scene(seed=5, render=False)
        entry_ct = np.asarray(CORRIDORS[0].entry_mm)
        assert np.linalg.norm(apply(np.asarray(c["carm_from_ct"]), entry_ct) - apply(truth.carm_from_ct, entry_ct)) < 1.0
        assert c["frame_id"] == "ct" and c["conformance"]["trajectory"] == "AIIS-PSIS" and isinstance(c["conformance"]["breach"], bool)
        # Aimed beside the corridor, the verdict is a breach, on the bus and on the surgeon's page (headless Chromium on the
        # daemon's own page, video-CT mode).
        breaches = [x["conformance"] for x in list(axes_ct) if x["conformance"]["breach"]]
        assert breaches, [x["conformance"]["min_clearance_mm"] for x in axes_ct[-20:]]
        assert all(b["axis_to_planned_entry_mm"] > 15.0 for b in breaches)
        _page_shows_the_breach(base)
        # A shot sent by C-STORE from this (separate) process leads to a new registration within 5 s.
        from drillnav.drivers.dicom_scp import send_files

        # Both of the twin's own shots registered first, so the registration counted next is the C-STORE shot's own.
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120 and not (len((status := httpx.get(f"{base}/status", timeout=5).json())["views"]) == 2
                                                   and status["shots"]["pending"] == 0):
            time.sleep(0.2)
        assert len(status["views"]) == 2 and status["shots"]["pending"] == 0, status
        before = status["registration_id"]
        # A new shot (a new SOP instance, as a C-arm sends each exposure) from this separate process.
        import pydicom
        from pydicom.uid import generate_uid

        ds = pydicom.dcmread(next(p for p in sorted((tmp_path / "in").glob("*.dcm")) if p.name != "broken.dcm"))  # a twin shot
        ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
        shot = tmp_path / "new-shot.dcm"
        ds.save_as(shot, enforce_file_format=True)
        t0 = time.monotonic()
        assert send_files(host="127.0.0.1", port=scp_port, called_ae="DRILLNAV", paths=[shot]) == [0]
        while time.monotonic() - t0 < 5.0 and httpx.get(f"{base}/status", timeout=5).json()["registration_id"] == before:
            time.sleep(0.1)
        assert httpx.get(f"{base}/status", timeout=5).json()["registration_id"] > before
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            out, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    assert proc.returncode == 0, out
    recs = sorted((tmp_path / "rec").glob("session-*.mcap"))  # more than one when a slow start-up made it rotate (512 MB)
    assert recs
    topics = set()
    for rec in recs:
        with open(rec, "rb") as f:
            topics |= {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert {"drillnav/camera/image", "drillnav/axis/carm", "drillnav/axis/ct", "drillnav/fluoro/shot"} <= topics, topics
    assert sum(t.startswith("drillnav/overlay/") for t in topics) >= 2, topics
