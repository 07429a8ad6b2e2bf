"""Replays an MCAP recording onto zenoh at the recorded timing (times a rate)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import zenoh
from mcap.exceptions import McapError
from mcap.reader import make_reader

from drillnav.registration.errors import DrillnavError

__all__ = ["RecordingUnreadable", "iter_recording", "replay"]


class RecordingUnreadable(DrillnavError):
    """The MCAP file is missing, not MCAP, or damaged beyond its index."""


def iter_recording(path: str | Path) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log_time_ns, payload) in log-time order."""
    p = Path(path)
    if not p.is_file():
        raise RecordingUnreadable(f"{p}: no such file")
    with open(p, "rb") as f:
        try:
            for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
                yield channel.topic, message.log_time, message.data
        except (McapError, ValueError, EOFError) as exc:
            raise RecordingUnreadable(f"{p}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None


def replay(path: str | Path, session: zenoh.Session, *, rate: float = 1.0, stop: threading.Event | None = None) -> int:
    """Publish every message at its recorded time offset divided by ``rate``; returns the count."""
    if rate <= 0:
        raise ValueError(f"rate must be positive, got {rate}")
    start_wall, start_log, n = time.monotonic(), None, 0
    for topic, log_time, data in iter_recording(path):
        if stop is not None and stop.is_set():
            break
        if start_log is None:
            start_log = log_time
        due = start_wall + (log_time - start_log) / 1e9 / rate
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        session.put(topic, data)
        n += 1
    return n
