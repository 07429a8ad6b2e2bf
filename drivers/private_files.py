"""Folders and files that hold patient data: owner-only (0700 folders, 0600 files), whatever the umask."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["make_private_dir", "open_private"]


def make_private_dir(folder: str | Path) -> Path:
    """Create ``folder`` (and parents) and make it 0700; returns it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    os.chmod(folder, 0o700)  # mkdir's mode is masked by the umask, and an existing folder keeps its own
    return folder


def open_private(path: str | Path, mode: str = "wb"):
    """Open ``path`` for writing ("wb", truncating) or appending ("ab") as a 0600 file; never follows a symlink."""
    flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | (os.O_APPEND if mode == "ab" else os.O_TRUNC)
    fd = os.open(path, flags, 0o600)
    os.fchmod(fd, 0o600)  # an existing file keeps its mode through os.open
    return os.fdopen(fd, mode)
