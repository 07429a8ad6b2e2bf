"""A watched folder for C-arms that export DICOM files: yields each new complete file once."""

from __future__ import annotations

import time
from pathlib import Path

__all__ = ["FolderWatcher"]


class FolderWatcher:
    """Polls ``folder`` for ``*.dcm`` files whose size is stable over two polls; ignores hidden/partial names."""

    def __init__(self, *, folder: str | Path, poll_s: float = 0.2, include_existing: bool = False) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise FileNotFoundError(f"watched DICOM folder {self.folder} does not exist")
        self.poll_s = poll_s
        self._seen: set[Path] = set() if include_existing else set(self.folder.glob("*.dcm"))
        self._sizes: dict[Path, int] = {}

    def poll(self) -> list[Path]:
        ready = []
        for p in sorted(self.folder.glob("*.dcm")):
            if p in self._seen or p.name.startswith("."):
                continue
            try:
                size = p.stat().st_size
            except FileNotFoundError:
                continue
            if self._sizes.get(p) == size and size > 0:
                ready.append(p)
                self._seen.add(p)
                self._sizes.pop(p, None)
            else:
                self._sizes[p] = size
        return ready

    def wait(self, timeout_s: float) -> list[Path]:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            got = self.poll()
            if got:
                return got
            time.sleep(self.poll_s)
        return []
