"""Checks on output paths, done before any work so a bad path fails in one clear line."""

from __future__ import annotations

import os
from pathlib import Path

from .cli import CliError

__all__ = ["check_output_path", "check_output_dir"]


def check_output_path(path: str | Path, *, suffixes: tuple[str, ...] | None = None) -> Path:
    p = Path(path)
    if suffixes and p.suffix.lower() not in suffixes:
        raise CliError(f"output {p} must end in one of {', '.join(suffixes)}")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise CliError(f"output folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise CliError(f"output folder {parent} is not writable")
    return p


def check_output_dir(path: str | Path) -> Path:
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"cannot create output folder {p}: {exc.strerror}") from None
    if not os.access(p, os.W_OK):
        raise CliError(f"output folder {p} is not writable")
    return p
