"""The DICOM intake as one part the daemon owns: the C-STORE SCP (with TLS from settings), the watched folder and its retention.

    with DicomIntake(settings=s.dicom, on_error=report) as intake:
        for path in intake.wait(0.5):
            ...                       # read and publish the shot
            intake.mark_processed(path)

Images received by C-STORE land in the watched folder; the folder watcher
offers each complete file once, and again after a restart until it is marked
processed. Retention runs from :meth:`DicomIntake.wait` every
``retention_every_s`` (the loop that waits is the one that owns the folder, so
no thread of its own is needed).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from drillnav.drivers.dicom_scp import StoreScp, server_tls_context
from drillnav.drivers.folder_watch import FolderWatcher

from .settings import DicomSettings

__all__ = ["DicomIntake"]


class DicomIntake:
    """See the module docstring. ``on_error(path, message)`` hears of files that cannot be used."""

    def __init__(self, *, settings: DicomSettings, on_error: Callable[[Path, str], None] | None = None, poll_s: float = 0.2) -> None:
        self.settings, self.on_error, self.poll_s = settings, on_error, poll_s
        self.watcher: FolderWatcher | None = None
        self.scp: StoreScp | None = None
        self.removed: list[Path] = []  # what retention deleted, for status and tests
        self._next_retention = 0.0

    def __enter__(self) -> DicomIntake:
        s = self.settings
        self.watcher = FolderWatcher(folder=s.watch_folder, poll_s=self.poll_s, on_error=self.on_error)
        self.apply_retention()
        if s.scp_enabled:
            tls = server_tls_context(cert=s.tls_cert, key=s.tls_key, ca=s.tls_ca) if s.tls_cert is not None else None
            # Received images land in the watched folder, fsynced before they are acknowledged.
            self.scp = StoreScp(ae_title=s.ae_title, port=s.scp_port, host=s.scp_host, storage_dir=s.watch_folder,
                                allowed_calling_aes=s.allowed_calling_aes, ssl_context=tls).__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.scp is not None:
            self.scp.__exit__(None, None, None)
            self.scp = None

    def apply_retention(self) -> list[Path]:
        assert self.watcher is not None, "DicomIntake is not entered"
        s = self.settings
        removed = self.watcher.apply_retention(max_age_s=s.retention_max_age_h * 3600.0, max_total_bytes=int(s.retention_max_mb * 1024 * 1024))
        self.removed += removed
        self._next_retention = time.monotonic() + s.retention_every_s
        return removed

    def wait(self, timeout_s: float) -> list[Path]:
        """New complete DICOM files (each once until marked processed), applying the retention when it is due."""
        assert self.watcher is not None, "DicomIntake is not entered"
        if time.monotonic() >= self._next_retention:
            self.apply_retention()
        return self.watcher.wait(timeout_s)

    def mark_processed(self, path: str | Path) -> None:
        assert self.watcher is not None, "DicomIntake is not entered"
        self.watcher.mark_processed(path)

    def failed(self, path: str | Path, message: str) -> None:
        assert self.watcher is not None, "DicomIntake is not entered"
        self.watcher.failed(path, message)
