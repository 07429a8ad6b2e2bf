"""``drillnav serve`` as a process: one-line start-up failures, SIGTERM at any moment, a closed stdout, sd_notify.

Every daemon runs in a subprocess on real devices (an MJPG file stands in for the camera device, as in
test_service's unplug test) or on the twin, with ports the OS handed out; every one is killed in a ``finally``.
"""

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
from mcap.reader import make_reader

from drillnav.schemas.topics import key
from drillnav.service import sd_notify
from drillnav.service.bus import open_session
from drillnav.service.replay import iter_recording

from conftest import free_endpoint, free_port
from file_camera import camera_file

RECORDING = Path(__file__).resolve().parents[1] / "recordings" / "twin-seed21.mcap"
EXIT_WITHIN_S = 5.0
# Python's imports before the first line take seconds on a loaded 2-core machine; the bars count from the first line.
FIRST_LINE_WITHIN_S = 90.0


def config(folder: Path, *, twin: bool = False, **sections: str) -> Path:
    """A drillnav.toml with free ports; ``sections`` replace whole sections (``api='port = 1'``)."""
    folder.mkdir(parents=True, exist_ok=True)
    base = {
        "zenoh": f'listen = ["{free_endpoint()}"]',
        "api": f'port = {free_port()}\ntoken = "test-token-1-of-16-chars"',
        "camera": f'device = "{camera_file(folder)}"' if not twin else "",
        "dicom": f'watch_folder = "{folder / "in"}"\nscp_port = {free_port()}',
        "recording": f'folder = "{folder / "rec"}"',
        "calibration": f'folder = "{folder / "cal"}"',
    }
    base.update(sections)
    path = folder / "drillnav.toml"
    path.write_text(("twin = true\n" if twin else "") + "".join(f"[{name}]\n{body}\n" for name, body in base.items()))
    return path


def settings_of(cfg: Path):
    from drillnav.service.settings import load_settings

    return load_settings(cfg)


class Served:
    """A ``drillnav serve`` subprocess whose output lines are read (and stamped) by threads."""

    def __init__(self, cfg: Path, *, env: dict | None = None, close_stdout_after: int | None = None):
        self.started = time.monotonic()
        self.proc = subprocess.Popen([sys.executable, "-m", "drillnav.service.cli", "serve", "--config", str(cfg)], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})})
        self.out: list[tuple[float, str]] = []
        self.err: list[str] = []
        self.close_stdout_after = close_stdout_after
        self._threads = [threading.Thread(target=self._read_out, daemon=True), threading.Thread(target=self._read_err, daemon=True)]
        for t in self._threads:
            t.start()

    def _read_out(self):
        for line in self.proc.stdout:
            self.out.append((time.monotonic(), line.rstrip("\n")))
            if self.close_stdout_after is not None and len(self.out) >= self.close_stdout_after:
                self.proc.stdout.close()  # like `| head -1`: the reader is gone
                return

    def _read_err(self):
        for line in self.proc.stderr:
            self.err.append(line.rstrip("\n"))

    def wait_line(self, text: str, timeout_s: float) -> float:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for t, line in list(self.out):
                if text in line:
                    return t
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        raise AssertionError(f"no line with '{text}' (rc {self.proc.poll()}): {[l for _, l in self.out]} {self.err}")

    def stop(self, sig=signal.SIGTERM) -> float:
        """Signal it; seconds until it exited."""
        t0 = time.monotonic()
        self.proc.send_signal(sig)
        try:
            self.proc.wait(timeout=30)
        finally:
            elapsed = time.monotonic() - t0
        for t in self._threads:
            t.join(2)
        return elapsed

    def kill(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@contextlib.contextmanager
def served(cfg: Path, **kwargs):
    s = Served(cfg, **kwargs)
    try:
        yield s
    finally:
        s.kill()


@contextlib.contextmanager
def taken_tcp(port: int):
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", port))
        sock.listen()
        yield


def _port_of(cfg: Path, what: str) -> int:
    s = settings_of(cfg)
    return {"api": s.api.port, "dicom": s.dicom.scp_port, "zenoh": int(s.zenoh.listen[0].rsplit(":", 1)[1])}[what]


NOT_A_TCP_PORT = 1 << 16  # one past the last TCP port: the settings refuse it, so nothing ever binds it

FAILURES = {
    # name: (sections, port to hold taken, words the one line must hold)
    "REST port taken": ({}, "api", ["REST API", "Address already in use"]),
    "zenoh port taken": ({}, "zenoh", ["zenoh", "Address already in use"]),
    "DICOM port taken": ({}, "dicom", ["DICOM", "Address already in use"]),
    "invalid zenoh endpoint": ({"zenoh": 'listen = ["tcp/not a host:port"]'}, None, ["zenoh", "tcp/not a host:port"]),
    "camera device missing": ({"camera": 'device = "/dev/video-drillnav-none"'}, None, ["camera.device", "/dev/video-drillnav-none"]),
    "bad config": ({"api": f"port = {NOT_A_TCP_PORT}"}, None, ["api.port"]),
    "calibration file missing": ({"camera": 'device = "{cam}"\ncalibration = "{missing}"\ndrill_calibration = "{missing}"'}, None, ["calibration", "missing.json"]),
}


def test_start_up_failures_are_one_line_and_a_non_zero_exit(tmp_path):
    """All cases at once (parallel processes, to keep the suite short): each ends with rc 1 and one line on stderr,
    within 5 s of its first line (bad config fails before any)."""
    runs, ended = {}, {}
    with contextlib.ExitStack() as held:
        for i, (name, (sections, taken, _)) in enumerate(FAILURES.items()):
            folder = tmp_path / f"case{i}"
            sections = {k: v.format(cam=folder / "video0.avi", missing=folder / "missing.json") for k, v in sections.items()}
            cfg = config(folder, **sections)
            if taken:
                held.enter_context(taken_tcp(_port_of(cfg, taken)))
            runs[name] = held.enter_context(served(cfg))
        deadline = time.monotonic() + FIRST_LINE_WITHIN_S + 30
        while len(ended) < len(runs) and time.monotonic() < deadline:
            for name, run in runs.items():
                if name not in ended and run.proc.poll() is not None:
                    ended[name] = time.monotonic()
            time.sleep(0.02)
        assert set(ended) == set(runs), f"still running: {set(runs) - set(ended)}"
        for name, run in runs.items():
            for t in run._threads:
                t.join(2)
            assert run.proc.returncode == 1, (name, run.out, run.err)
            assert len(run.err) == 1 and run.err[0].startswith("drillnav serve: error: "), (name, run.err)
            for word in FAILURES[name][2]:
                assert word in run.err[0], (name, run.err[0])
            if name not in ("bad config", "invalid zenoh endpoint"):  # refused when the settings are read, before the first line
                assert run.out[0][1] == "drillnav: starting on real devices ...", (name, run.out)
                took = ended[name] - run.out[0][0]
                assert took < EXIT_WITHIN_S, f"{name}: {took:.1f} s from the first line to the exit"


def test_sigterm_while_streaming_registering_and_calibrating_with_stdout_closed(tmp_path):
    """A closed stdout (like `| head -1`), sd_notify on a real socket, shots being registered and a calibration job
    busy when SIGTERM comes: the process ends within 5 s, rc 0, the recording finalised (summary and index)."""
    notify_path = tmp_path / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.settimeout(0.1)
    got: list[str] = []
    cfg = config(tmp_path / "d")
    s = settings_of(cfg)
    base = f"http://127.0.0.1:{s.api.port}"
    env = {"NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "1000000"}

    def until(cond, timeout_s):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not cond():
            with contextlib.suppress(socket.timeout):
                got.append(notify.recv(4096).decode())
        return cond()

    try:
        with served(cfg, env=env, close_stdout_after=1) as run:
            assert until(lambda: any("READY=1" in m for m in got), FIRST_LINE_WITHIN_S + 30), (got, run.out, run.err)
            assert until(lambda: sum(m == "WATCHDOG=1" for m in got) >= 2, 5), got  # every 0.5 s while healthy
            assert httpx.get(f"{base}/health", timeout=5).json() == {"status": "ok"}
            st = httpx.get(f"{base}/status", timeout=5).json()
            assert st["state"] == "uncalibrated" and st["calibrated"] is False and st["frames_received"] > 0
            # A calibration job that computes for a while (many board views that show no board: each is searched). On a
            # fast machine OpenCV (.ci/constraints.txt's) gives up on a blank 1280x720 view in ~15 ms, so 40 of them (as
            # here before) were done in 0.5 s, before the signal came; 400 keep the job busy for 6 s or more (1 MB of PNG).
            blank = cv2.imencode(".png", np.full((720, 1280), 128, np.uint8))[1].tobytes()
            files = [("files", (f"v{i}.png", blank, "image/png")) for i in range(400)]
            r = httpx.post(f"{base}/calibration/jobs", data={"kind": "camera", "board": "checkerboard:9x6:25mm"}, files=files,
                           headers={"Authorization": "Bearer test-token-1-of-16-chars"}, timeout=30)
            assert r.status_code == 202, r.text
            job_url = f"{base}/calibration/jobs/{r.json()['id']}"
            deadline = time.monotonic() + 10
            while (job := httpx.get(job_url, timeout=5).json())["state"] == "queued" and time.monotonic() < deadline:
                time.sleep(0.05)
            # Shots on the bus: the node registers them while SIGTERM comes.
            shots = [data for topic, _, data in iter_recording(RECORDING) if topic.endswith("fluoro/shot")]
            with open_session(connect=s.zenoh.listen) as pub:
                time.sleep(0.3)
                for shot in shots:
                    pub.put(key("drillnav", "fluoro_shot"), shot)
                time.sleep(0.2)
            job = httpx.get(job_url, timeout=5).json()
            assert job["state"] == "running", job  # busy when the signal comes
            elapsed = run.stop()
            assert run.proc.returncode == 0, (run.out, run.err)
            assert elapsed < EXIT_WITHIN_S, f"took {elapsed:.1f} s to stop"
            assert len(run.out) == 1  # the reader went away after the first line; the daemon did not mind
            assert until(lambda: any("STOPPING=1" in m for m in got), 1), got
    finally:
        notify.close()
    (rec,) = list((tmp_path / "d" / "rec").glob("session-*.mcap"))
    with open(rec, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and "drillnav/camera/image" in {c.topic for c in summary.channels.values()}
    assert summary.statistics.message_count > 10


def test_sigterm_during_twin_start_up_ends_it_within_5_s(tmp_path):
    cfg = config(tmp_path / "t", twin=True)
    with served(cfg) as run:
        run.wait_line("building the digital twin", FIRST_LINE_WITHIN_S + 30)
        time.sleep(0.5)
        elapsed = run.stop()
        assert run.proc.returncode == 0 and elapsed < EXIT_WITHIN_S, (elapsed, run.out, run.err)
        assert any("SIGTERM during start-up: stopped" in line for _, line in run.out), run.out


def test_sd_notify_over_a_real_datagram_socket(tmp_path, monkeypatch):
    path = tmp_path / "n.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(path))
        assert sd_notify.notify("READY=1\nSTATUS=running", socket_path=str(path))
        assert sock.recv(100) == b"READY=1\nSTATUS=running"
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        assert sd_notify.notify("WATCHDOG=1") and sock.recv(100) == b"WATCHDOG=1"
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert not sd_notify.notify("READY=1")  # outside systemd: nothing, no error
    assert not sd_notify.notify("READY=1", socket_path=str(tmp_path / "gone.sock"))  # a vanished socket is not an error
    monkeypatch.setenv("WATCHDOG_USEC", "30000000")
    assert sd_notify.watchdog_period_s() == 15.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert sd_notify.watchdog_period_s() is None  # meant for another process
    monkeypatch.delenv("WATCHDOG_PID")
    monkeypatch.setenv("WATCHDOG_USEC", "0")
    assert sd_notify.watchdog_period_s() is None
