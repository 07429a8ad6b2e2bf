"""Shared plumbing for benchmarks that run ``drillnav serve`` as a subprocess: free ports, a sure stop."""

from __future__ import annotations

import signal
import socket
import subprocess
from pathlib import Path


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bound to 0, read back, released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop(proc: subprocess.Popen, *, grace_s: float = 30.0) -> None:
    """SIGTERM (the daemon finalises its recordings), then SIGKILL if it is still there after ``grace_s``."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def daemon_config(folder: Path, *, token: str, top: str = "", **sections: str) -> tuple[Path, str, int, int]:
    """``folder/drillnav.toml`` on free ports with its folders inside ``folder``; ``top`` goes before the sections,
    ``sections`` add or replace whole ones (``twin_scene="seed = 3"``). Returns (path, zenoh endpoint, REST port, DICOM port)."""
    ep, api_port, dicom_port = f"tcp/127.0.0.1:{free_port()}", free_port(), free_port()
    body = {"zenoh": f'listen = ["{ep}"]', "api": f'port = {api_port}\ntoken = "{token}"',
            "dicom": f'watch_folder = "{folder / "in"}"\nscp_port = {dicom_port}', "recording": f'folder = "{folder / "rec"}"',
            "calibration": f'folder = "{folder / "cal"}"', **sections}
    path = folder / "drillnav.toml"
    path.write_text(top + "".join(f"[{name}]\n{text}\n" for name, text in body.items()))
    return path, ep, api_port, dicom_port
