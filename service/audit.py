"""The audit log: who changed what, as JSON lines in ``<folder>/audit.jsonl`` (0600 in a 0700 folder).

Each entry: ``{"stamp_ns", "actor", "action", "detail"}``. ``actor`` is the
client address (and whether it held the token); ``action`` is an
:class:`AuditAction`. An optional callback receives every entry too, so the
daemon can publish it on the bus and so into recordings.
"""

from __future__ import annotations

import enum
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from drillnav.drivers.private_files import make_private_dir, open_private

__all__ = ["AuditLog", "AuditAction"]

log = logging.getLogger(__name__)


class AuditAction(str, enum.Enum):
    AUTH_FAILED = "auth-failed"
    AUTH_RATE_LIMITED = "auth-rate-limited"
    CALIBRATION_JOB_SUBMITTED = "calibration-job-submitted"
    CALIBRATION_JOB_CANCELLED = "calibration-job-cancelled"
    CALIBRATION_INSTALLED = "calibration-installed"
    RECORDING_STARTED = "recording-started"
    RECORDING_STOPPED = "recording-stopped"
    SHOT_REQUESTED = "shot-requested"
    REGISTRATION_REFRESHED = "registration-refreshed"


class AuditLog:
    """``AuditLog(folder=..., on_entry=...)``; :meth:`record` appends one fsynced line (thread-safe)."""

    def __init__(self, *, folder: str | Path, on_entry: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.folder = make_private_dir(folder)
        self.path = self.folder / "audit.jsonl"
        self.on_entry = on_entry
        self._lock = threading.Lock()
        self._file = open_private(self.path, "ab")

    def record(self, action: AuditAction, *, actor: str, detail: dict[str, Any] | None = None) -> dict[str, Any]:
        entry = {"stamp_ns": time.time_ns(), "actor": actor, "action": AuditAction(action).value, "detail": detail or {}}
        line = (json.dumps(entry, separators=(",", ":"), default=str) + "\n").encode()
        with self._lock:
            self._file.write(line)
            self._file.flush()
            os.fsync(self._file.fileno())
        if self.on_entry is not None:
            try:
                self.on_entry(entry)
            except Exception:  # the file has it; a failing publisher must not fail the request it audits
                log.exception("audit callback failed for %s", entry["action"])
        return entry

    def close(self) -> None:
        with self._lock:
            self._file.close()

    def __enter__(self) -> AuditLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
