"""The recorder on real zenoh: the camera budget, state carried into every file, permissions, retention, a full disk."""

import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import zenoh
import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from conftest import free_endpoint
from drillnav.drivers.sim.scene import make_scene
from drillnav.schemas import messages as msg
from drillnav.schemas.calibration_message import calibration_message_from_models, decode_calibration_message
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.recorder import CarriedState, Recorder, apply_retention
from drillnav.service.replay import RecordingReader
from drillnav.service.settings import load_settings

P = "drillnav"


def _wait(cond, timeout_s: float = 30.0) -> None:
    # A deadline, not a sleep (it returns when cond holds): on a loaded shared machine the recorder's re-encoding of
    # 45 720p frames was seen to take over 10 s.
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("timed out waiting")
        time.sleep(0.02)


def _frame(i: int) -> bytes:
    rng = np.random.default_rng(i)
    img = np.clip(np.add.outer(np.arange(720), np.arange(1280)) % 256 + rng.normal(0, 12, (720, 1280)), 0, 255).astype(np.uint8)
    return msg.compressed_image(np.dstack([img] * 3), stamp_ns=1_000 + i, frame_id="drill_camera", quality=92)


def _both_readers(path: Path) -> int:
    """Message count, read by the indexed reader and the stream reader; both must read the file to its end."""
    with open(path, "rb") as f:
        indexed = sum(1 for _ in make_reader(f).iter_messages())
    with open(path, "rb") as f:
        streamed = sum(1 for r in StreamReader(f, skip_magic=False).records if type(r).__name__ == "Message")
    assert indexed == streamed
    return indexed


def test_camera_frames_at_the_set_rate_and_quality_everything_else_in_full(tmp_path):
    settings = load_settings(recording={"folder": str(tmp_path), "camera_fps": 10, "camera_jpeg_quality": 75})
    frames = [_frame(i) for i in range(45)]
    ep = free_endpoint()
    with open_session(listen=[ep]) as a, open_session(connect=[ep]) as b:
        rec = Recorder.from_settings(settings.recording, session=b, prefix=P, name="budget")
        time.sleep(0.5)
        t0 = time.monotonic()
        for i, f in enumerate(frames):  # 30 frames/s for 1.5 s
            # Blocking puts: zenoh drops under congestion by default (a loaded CI machine lost frames that way), and this
            # test counts what the recorder decides, not what the transport loses.
            a.put(key(P, "camera_image"), f, congestion_control=zenoh.CongestionControl.BLOCK)
            a.put(key(P, "axis_carm"), msg.encode_json({"stamp_ns": i}), congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(max(0.0, t0 + (i + 1) / 30 - time.monotonic()))
        _wait(lambda: rec.messages + rec.camera_frames_skipped + rec.dropped >= 90)
        (path,) = rec.close()
    recorded = [m for m in RecordingReader(path)]
    images = [m for m in recorded if m.topic == key(P, "camera_image")]
    axes = [m for m in recorded if m.topic == key(P, "axis_carm")]
    assert len(axes) == 45
    assert 13 <= len(images) <= 17, len(images)  # 10 of 30 per second over 1.5 s
    assert rec.status().camera_frames_skipped == 45 - len(images) and rec.status().dropped == 0
    img, stamp, frame_id = msg.decode_compressed_image(images[0].data)
    assert img.shape == (720, 1280, 3) and frame_id == "drill_camera" and 1_000 <= stamp < 1_045  # the capture stamp kept
    assert np.mean([len(m.data) for m in images]) < 0.6 * np.mean([len(f) for f in frames])
    assert stat.S_IMODE(os.stat(tmp_path).st_mode) == 0o700 and stat.S_IMODE(os.stat(path).st_mode) == 0o600


def test_every_new_file_starts_with_the_state_to_replay_it_alone(tmp_path):
    scene = make_scene(seed=3, render=False)
    shot = {v: msg.FluoroShot.build(np.full((scene.views[v].rows, scene.views[v].columns), 0.5, np.float32), scene.views[v], stamp_ns=i, view_name=v).to_bytes() for i, v in enumerate(scene.views)}
    cal = calibration_message_from_models(camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill, stamp_ns=1, marker_set=scene.marker_set, source="twin")
    ep = free_endpoint()
    with open_session(listen=[ep]) as a, open_session(connect=[ep]) as b:
        rec = Recorder(session=b, prefix=P, folder=tmp_path, name="state", rotate_bytes=20_000, chunk_size=8_000)
        time.sleep(0.5)
        a.put(key(P, "calibration"), cal)
        for v in scene.views:
            a.put(key(P, "fluoro_shot"), shot[v])
        a.put(key(P, "fluoro_markers"), msg.encode_json({"stamp_ns": 5, "registration_id": 1, "markers": []}))
        a.put(key(P, "status"), msg.encode_json({"stamp_ns": 6, "state": "registered"}))
        for i in range(300):  # ~60 kB of axes: at least two rotations
            a.put(key(P, "axis_carm"), msg.encode_json({"stamp_ns": i, "pad": "x" * 200}))
            time.sleep(0.002)
        _wait(lambda: rec.messages >= 305)
        files = rec.close()
    assert len(files) >= 3
    views = sorted(scene.views)
    for path in files[1:]:
        carried = [m for m in RecordingReader(path) if m.carried_state]
        topics = [m.topic for m in carried]
        assert topics == [key(P, "calibration"), key(P, "fluoro_shot"), key(P, "fluoro_shot"), key(P, "fluoro_markers"), key(P, "status")]
        assert sorted(msg.decode_json(m.data)["view"] for m in carried[1:3]) == views
        assert decode_calibration_message(carried[0].data).marker_set.ids == scene.marker_set.ids
        assert all(m.publish_time_ns < m.log_time_ns for m in carried)  # first recorded earlier, logged into this file at its start
    # Every axis recorded exactly once, and every file is finished and indexed.
    stamps = [msg.decode_json(m.data)["stamp_ns"] for p in files for m in RecordingReader(p) if m.topic == key(P, "axis_carm")]
    assert stamps == list(range(300))
    assert sum(_both_readers(p) for p in files) == 305 + 5 * (len(files) - 1)


def test_retention_removes_the_oldest_finished_files_first(tmp_path):
    now = time.time()
    for i, age_days in enumerate([40, 20, 10, 5, 1]):
        p = tmp_path / f"old{i}.mcap"
        p.write_bytes(b"x" * 1000)
        os.utime(p, (now - age_days * 86400, now - age_days * 86400))
    ep = free_endpoint()
    with open_session(listen=[ep]) as a:
        events = []
        rec = Recorder(session=a, prefix=P, folder=tmp_path, name="live", max_age_s=30 * 86400, max_total_bytes=100_000,
                       on_event=lambda lvl, m: events.append((lvl, m)))
        # At start: only the one older than 30 days goes.
        assert sorted(p.name for p in tmp_path.glob("old*.mcap")) == ["old1.mcap", "old2.mcap", "old3.mcap", "old4.mcap"]
        assert events and "old0.mcap" in events[0][1]
        # A byte budget smaller than the folder: oldest first, and the file being written is never removed.
        live = rec.files[0]
        os.utime(live, (now - 90 * 86400, now - 90 * 86400))
        removed = apply_retention(tmp_path, max_age_s=None, max_total_bytes=1_500, now_s=now)
        assert [p.name for p in removed] == ["old1.mcap", "old2.mcap", "old3.mcap"]
        assert live.exists() and (tmp_path / "old4.mcap").exists()
        rec.close()
    os.utime(live, (now - 90 * 86400, now - 90 * 86400))
    removed = apply_retention(tmp_path, max_age_s=60 * 86400, max_total_bytes=None, now_s=now)
    assert removed == [live]  # once finished, it may go


def _tmpfs(path: Path, size: str):
    path.mkdir()
    try:
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], check=True, capture_output=True)
    except (OSError, subprocess.CalledProcessError) as exc:
        if os.environ.get("CI"):
            raise
        pytest.skip(f"a full disk needs a tmpfs of our own: mount is not allowed here ({exc}); in CI this test must run")


def test_full_disk_pauses_with_an_event_keeps_every_file_readable_and_resumes_in_a_new_file(tmp_path):
    disk = tmp_path / "disk"
    _tmpfs(disk, "4m")
    rec = None
    try:
        folder = disk / "rec"
        events = []
        ep = free_endpoint()
        rng = np.random.default_rng(0)
        with open_session(listen=[ep]) as a, open_session(connect=[ep]) as b:
            rec = Recorder(session=b, prefix=P, folder=folder, name="full", chunk_size=64 * 1024, resume_free_bytes=1 << 20, resume_check_s=0.2,
                           on_event=lambda lvl, m: events.append((lvl, m)))
            heard = []
            b.declare_subscriber(key(P, "axis_carm"), lambda s: heard.append(1))
            time.sleep(0.5)
            ballast = disk / "ballast"
            with open(ballast, "wb") as f:  # leave ~600 kB
                f.write(b"\0" * (disk_free(disk) - 600_000))
            sent = 0

            def send(n):
                nonlocal sent
                for _ in range(n):
                    a.put(key(P, "twin_truth"), rng.bytes(30_000))  # incompressible, each different
                    a.put(key(P, "axis_carm"), msg.encode_json({"stamp_ns": sent}))
                    sent += 1
                    time.sleep(0.005)

            send(40)  # ~1.2 MB: the disk fills
            _wait(lambda: rec.paused)
            assert [lvl for lvl, _ in events] == ["error"] and "paused" in events[0][1] and "No space left" in events[0][1]
            assert rec.status().paused and "No space left" in rec.status().pause_reason
            first = rec.files[0]
            n_first = _both_readers(first)  # closed at its last complete chunk: both readers read it whole
            assert n_first > 10
            send(10)  # while paused: lost and counted, nothing raised
            _wait(lambda: rec.status().lost_while_paused >= 10)
            with open(disk / "ballast2", "wb", buffering=0) as f:  # the cut freed a little: fill it to the last byte
                try:
                    while True:
                        f.write(b"\0" * 4096)
                except OSError:
                    pass
            late = Recorder(session=b, prefix=P, folder=folder, name="late", resume_free_bytes=1 << 20, resume_check_s=0.2)
            assert late.paused and late.files == []  # started on a full disk: paused, not refused
            ballast.unlink()  # space returns: the recorders find it on their own
            (disk / "ballast2").unlink()
            _wait(lambda: not rec.paused and len(rec.files) == 2 and len(late.files) == 1)
            late.close()
            resumed_at = rec.messages
            send(20)
            _wait(lambda: rec.messages >= resumed_at + 40)
            assert events[-1][0] == "info" and "resumed" in events[-1][1]
            files = rec.close()
            assert len(heard) == sent  # the bus and its other subscribers never stopped
        assert files[0] == first and len(files) == 2
        assert _both_readers(files[0]) == n_first
        assert _both_readers(files[1]) == 40  # every message after the resume
        assert rec.status().write_errors >= 1
    finally:
        if rec is not None:
            rec.close()  # on a failure above: the recorder's open file would keep the mount busy
        subprocess.run(["umount", "-l", str(disk)], check=False)


def disk_free(path: Path) -> int:
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def test_a_recording_started_mid_case_carries_what_came_before_it(tmp_path):
    scene = make_scene(seed=3, render=False)
    cal = calibration_message_from_models(camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill, stamp_ns=1, source="twin")
    ep = free_endpoint()
    with open_session(listen=[ep]) as a, open_session(connect=[ep]) as b:
        carried = CarriedState(prefix=P)  # the daemon's, kept from start-up
        subs = carried.subscribe(b)
        time.sleep(0.5)
        a.put(key(P, "calibration"), cal)
        a.put(key(P, "fluoro_shot"), msg.FluoroShot.build(np.full((scene.views["inlet"].rows, scene.views["inlet"].columns), 0.5, np.float32), scene.views["inlet"], stamp_ns=2, view_name="inlet").to_bytes())
        a.put(key(P, "fluoro_image", "inlet"), msg.compressed_image(np.zeros((8, 8), np.uint8), stamp_ns=2, frame_id="carm/inlet", fmt="png"))
        a.put(key(P, "axis_carm"), msg.encode_json({"stamp_ns": 3}))  # not state
        _wait(lambda: len(carried.messages()) == 3)
        rec = Recorder(session=b, prefix=P, folder=tmp_path, name="late", carried_state=carried)
        (path,) = rec.close()
        for s in subs:
            s.undeclare()
    got = [(m.topic, m.carried_state) for m in RecordingReader(path)]
    assert got == [(key(P, "calibration"), True), (key(P, "fluoro_shot"), True), (key(P, "fluoro_image", "inlet"), True)]


FSIZE_CHILD = r"""
import json, resource, sys, threading, time
from drillnav.service.bus import open_session
from drillnav.service.recorder import Recorder
ep, folder, limit = sys.argv[1], sys.argv[2], int(sys.argv[3])
hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1]
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))  # a write past `limit` bytes fails with EFBIG (Python ignores SIGXFSZ)
events = []
with open_session(connect=[ep]) as s:
    rec = Recorder(session=s, prefix="drillnav", folder=folder, name="quota", chunk_size=32 * 1024, resume_free_bytes=1, resume_check_s=0.2,
                   on_event=lambda lvl, m: events.append([lvl, m]))
    stop = threading.Event()
    def commands():
        for line in sys.stdin:
            if line.strip() == "room":
                resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
            elif line.strip() == "close":
                rec.close()
                stop.set()
                return
    threading.Thread(target=commands, daemon=True).start()
    while True:
        st = rec.status()
        print(json.dumps({"paused": st.paused, "files": list(st.files), "messages": st.messages, "lost": st.lost_while_paused, "events": events}), flush=True)
        if stop.is_set():
            break
        time.sleep(0.05)
"""


def test_a_file_size_limit_pauses_and_resumes_without_root(tmp_path):
    """The same failed-write path as a full disk, where no tmpfs can be mounted: RLIMIT_FSIZE in a child process."""
    ep = free_endpoint()
    rng = np.random.default_rng(1)
    with open_session(listen=[ep]) as a:
        child = subprocess.Popen([sys.executable, "-c", FSIZE_CHILD, ep, str(tmp_path), str(400_000)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            state = json.loads(child.stdout.readline())
            time.sleep(0.5)

            def until(cond):
                nonlocal state
                deadline = time.monotonic() + 15
                while not cond(state):
                    assert time.monotonic() < deadline, state
                    state = json.loads(child.stdout.readline())

            for i in range(30):  # 900 kB of incompressible payload against a 400 kB limit
                a.put(key(P, "twin_truth"), rng.bytes(30_000))
                time.sleep(0.005)
            until(lambda s: s["paused"])
            assert "File too large" in state["events"][0][1]
            child.stdin.write("room\n")
            child.stdin.flush()
            until(lambda s: not s["paused"] and len(s["files"]) == 2)
            resumed_at = state["messages"]
            for i in range(10):
                a.put(key(P, "axis_carm"), msg.encode_json({"stamp_ns": i}))
                time.sleep(0.005)
            until(lambda s: s["messages"] >= resumed_at + 10)
            child.stdin.write("close\n")
            child.stdin.flush()
            assert child.wait(10) == 0
        finally:
            child.kill()
            child.wait()
    first, second = (Path(p) for p in state["files"])
    assert 5 <= _both_readers(first) <= 13 and first.stat().st_size <= 400_000  # cut at its last complete chunk, with a footer
    assert _both_readers(second) == 10


def test_the_calibration_message_carries_the_files_as_they_are(tmp_path):
    from drillnav.registration.axis_uncertainty import AxisUncertainty
    from drillnav.schemas.calibration import write_camera_calibration
    from drillnav.schemas.calibration_message import active_calibration_message

    scene = make_scene(seed=3, render=False)
    cam_file = tmp_path / "camera.json"
    write_camera_calibration(cam_file, scene.calibrated_camera, rms_px=0.31, per_view_errors_px=[0.3, 0.32], label="OR 2")
    held = AxisUncertainty(sigma_mm=0.3, rms_tilt_deg=0.4)
    data = active_calibration_message(camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill, stamp_ns=7,
                                      camera_file=cam_file, drill_file=tmp_path / "none.json", axis_uncertainty=held)
    doc = msg.decode_json(data)
    assert doc["camera"] == json.loads(cam_file.read_text()) and doc["source"] == str(cam_file)
    assert doc["drill"]["label"] == "in use (no file)"  # no drill file: the axis in use
    cal = decode_calibration_message(data)
    assert np.allclose(cal.camera.camera_matrix, scene.calibrated_camera.camera_matrix) and np.allclose(cal.axis_drill.point_mm, scene.calibrated_axis_drill.point_mm)
    assert cal.axis_uncertainty == held  # the axis in use with its stated uncertainty: a replay's bound is the live one's
    with pytest.raises(ValueError, match="camera"):
        decode_calibration_message(msg.encode_json({"stamp_ns": 1, "camera": {"schema": "x"}, "drill": doc["drill"]}))


def test_a_writer_behind_drops_counts_and_reports_never_blocking_the_bus(tmp_path):
    frame = _frame(0)
    events = []
    ep = free_endpoint()
    with open_session(listen=[ep]) as a, open_session(connect=[ep]) as b:
        # Re-encoding 720p frames takes the writer ~10 ms each; 60 arrive at once into a queue of 2.
        rec = Recorder(session=b, prefix=P, folder=tmp_path, name="behind", camera_jpeg_quality=75, queue_size=2, on_event=lambda lvl, m: events.append((lvl, m)))
        time.sleep(0.5)
        for _ in range(60):
            # Blocking puts: zenoh itself drops under congestion by default, and this test counts the recorder's drops alone.
            a.put(key(P, "camera_image"), frame, congestion_control=zenoh.CongestionControl.BLOCK)
        _wait(lambda: rec.messages + rec.dropped >= 60)
        (path,) = rec.close()
    st = rec.status()
    assert st.dropped > 0 and st.messages + st.dropped == 60
    assert events and events[0][0] == "warning" and "dropped" in events[0][1]
    assert sum(1 for _ in RecordingReader(path)) == st.messages
