"""Shared test plumbing: ports the OS hands out, so two suites on one machine never meet."""

import os
import socket
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `drillnav` sets it (service/cli.py): small matrices, threads only spin

sys.path.insert(0, str(Path(__file__).parent))


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bound to 0, read back, released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_endpoint() -> str:
    """A zenoh TCP endpoint on loopback at a free port."""
    return f"tcp/127.0.0.1:{free_port()}"


def wait_for(cond, timeout_s: float) -> bool:
    """Poll ``cond()`` every 20 ms until it holds or ``timeout_s`` passes; its last value."""
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return bool(cond())
