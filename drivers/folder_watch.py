"""A watched folder for C-arms that export DICOM files (and for the C-STORE SCP's store): yields each complete file once.

What counts is the content, not the name: any regular file whose bytes 128-131
are ``DICM`` (the DICOM preamble), whatever its name or case. Hidden names
(a leading dot: partial writes, the journal) are skipped.

A file is offered when its size and modification time held still over two
polls and it is whole (the pixel data its header declares is all there). A
file that is still being written, or is truncated, waits and is retried at
each poll; if it stays incomplete for ``give_up_s`` a clear error naming it is
reported once, and it is offered again as soon as it changes.

What was processed is persistent: the caller calls :meth:`FolderWatcher.mark_processed`
after a file has been handled, which appends it to a journal
(``.drillnav-processed``, 0600) with its size and modification time. On start,
every DICOM file in the folder that the journal does not name, such as an image
acknowledged just before a crash, is offered again.

:func:`apply_retention` deletes old incoming images (age, then a byte budget,
oldest first): incoming images carry patient names and are kept no longer than needed.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from drillnav.registration.errors import DrillnavError

from .private_files import make_private_dir, open_private

__all__ = ["FolderWatcher", "IncompleteDicom", "has_dicom_preamble", "dicom_is_complete", "apply_retention", "JOURNAL_NAME"]

log = logging.getLogger(__name__)

JOURNAL_NAME = ".drillnav-processed"
_PREAMBLE_END = 132
_SEQUENCE_DELIMITER = b"\xfe\xff\xdd\xe0\x00\x00\x00\x00"  # (FFFE,E0DD), length 0: the end of encapsulated pixel data


class IncompleteDicom(DrillnavError):
    """A DICOM file that stopped before its pixel data ends (still being written, or truncated)."""


def has_dicom_preamble(path: str | Path) -> bool:
    try:
        with open(path, "rb") as f:
            head = f.read(_PREAMBLE_END)
    except OSError:
        return False
    return len(head) == _PREAMBLE_END and head[128:132] == b"DICM"


def dicom_is_complete(path: str | Path) -> None:
    """Raise :class:`IncompleteDicom` naming ``path`` if its pixel data is shorter than its header declares.

    pydicom reads a truncated file without complaint (a short value is just
    short), so the check is explicit: native pixel data must hold rows x
    columns x frames x samples x bits; encapsulated pixel data must end with its
    sequence delimiter.
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    p = Path(path)
    try:
        ds = pydicom.dcmread(str(p))
    except (InvalidDicomError, EOFError, OSError, ValueError, KeyError) as exc:
        raise IncompleteDicom(f"{p.name}: not readable as DICOM yet ({type(exc).__name__}: {exc})") from None
    if "PixelData" not in ds:
        raise IncompleteDicom(f"{p.name}: no pixel data (7FE0,0010) yet")
    if ds.file_meta.TransferSyntaxUID.is_encapsulated:
        later = [t for t in ds.keys() if t > 0x7FE00010]
        if not later:  # elements after the pixel data mean the parser went past its delimiter
            with open(p, "rb") as f:
                f.seek(-len(_SEQUENCE_DELIMITER), os.SEEK_END)
                if f.read() != _SEQUENCE_DELIMITER:
                    raise IncompleteDicom(f"{p.name}: compressed pixel data has no end delimiter (still being written, or truncated)")
        return
    try:
        frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
        want = int(ds.Rows) * int(ds.Columns) * frames * int(getattr(ds, "SamplesPerPixel", 1)) * int(ds.BitsAllocated) // 8
    except (AttributeError, TypeError, ValueError) as exc:
        raise IncompleteDicom(f"{p.name}: image size attributes missing ({exc})") from None
    got = len(ds.PixelData)
    if got < want:
        raise IncompleteDicom(f"{p.name}: pixel data holds {got} of {want} bytes (still being written, or truncated)")


@dataclass
class _Pending:
    stamp: tuple[int, int]  # (size, mtime_ns) at the last poll
    since: float  # monotonic time the stamp was first seen
    reported: bool = False


class FolderWatcher:
    """Polls ``folder`` for complete DICOM files; see the module docstring.

    Parameters
    ----------
    folder : Path
        Created if missing, and made 0700.
    poll_s : float
        The interval of :meth:`wait`.
    give_up_s : float
        An incomplete file that stays unchanged this long is reported (once) through ``on_error`` and the log.
    on_error : callable or None
        ``(path, message)`` for files that cannot be used: incomplete, or not DICOM.
    """

    def __init__(self, *, folder: str | Path, poll_s: float = 0.2, give_up_s: float = 10.0, on_error: Callable[[Path, str], None] | None = None) -> None:
        self.folder = make_private_dir(folder)
        self.poll_s, self.give_up_s, self.on_error = poll_s, give_up_s, on_error
        self.journal = self.folder / JOURNAL_NAME
        self._processed: dict[str, tuple[int, int]] = self._read_journal()
        self._offered: dict[Path, tuple[int, int]] = {}  # offered and not yet marked processed
        self._pending: dict[Path, _Pending] = {}
        self._refused: dict[Path, tuple[int, int]] = {}  # reported unusable at this stamp; offered again when it changes
        self._compact_journal()

    # -- the journal ------------------------------------------------------------------------
    def _read_journal(self) -> dict[str, tuple[int, int]]:
        out: dict[str, tuple[int, int]] = {}
        try:
            lines = self.journal.read_text().splitlines()
        except FileNotFoundError:
            return out
        for line in lines:
            parts = line.split("\t")
            if len(parts) == 3 and parts[1].isdigit() and parts[2].isdigit():  # a line cut by a crash is ignored
                out[parts[0]] = (int(parts[1]), int(parts[2]))
        return out

    def _compact_journal(self) -> None:
        """Drop entries for files that are gone (retention), atomically."""
        present = {n: st for n, st in self._processed.items() if (self.folder / n).is_file()}
        self._processed = present
        tmp = self.folder / f"{JOURNAL_NAME}.tmp"
        with open_private(tmp, "wb") as f:
            f.write("".join(f"{n}\t{s}\t{m}\n" for n, (s, m) in present.items()).encode())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.journal)

    def mark_processed(self, path: str | Path) -> None:
        """Record ``path`` as handled (fsynced): it is not offered again, even after a restart."""
        p = Path(path)
        stamp = self._offered.pop(p, None) or _stamp(p)
        if stamp is None:
            return  # gone already (retention, or the C-arm took it back): nothing to remember
        self._processed[p.name] = stamp
        with open_private(self.journal, "ab") as f:
            f.write(f"{p.name}\t{stamp[0]}\t{stamp[1]}\n".encode())
            f.flush()
            os.fsync(f.fileno())

    def is_processed(self, path: str | Path) -> bool:
        p = Path(path)
        return self._processed.get(p.name) == _stamp(p)

    # -- polling ----------------------------------------------------------------------------
    def _candidates(self) -> Iterable[Path]:
        with os.scandir(self.folder) as it:
            for e in it:
                if not e.name.startswith(".") and e.is_file(follow_symlinks=False):
                    yield Path(e.path)

    def _refuse(self, p: Path, stamp: tuple[int, int], message: str) -> None:
        self._refused[p] = stamp
        self._pending.pop(p, None)
        log.error("%s", message)
        if self.on_error is not None:
            self.on_error(p, message)

    def poll(self) -> list[Path]:
        """Complete DICOM files not yet offered (each once; again only if it changes), oldest first."""
        ready: list[tuple[int, Path]] = []
        now = time.monotonic()
        for p in self._candidates():
            stamp = _stamp(p)
            if stamp is None or stamp[0] == 0:
                continue
            if self._processed.get(p.name) == stamp or self._offered.get(p) == stamp or self._refused.get(p) == stamp:
                continue
            pending = self._pending.get(p)
            if pending is None or pending.stamp != stamp:
                self._pending[p] = _Pending(stamp=stamp, since=now)  # new or still changing: look again next poll
                continue
            if not has_dicom_preamble(p):
                if stamp[0] >= _PREAMBLE_END or now - pending.since >= self.give_up_s:
                    self._refuse(p, stamp, f"{p}: not a DICOM file (no 'DICM' at byte 128): ignored")
                continue
            try:
                dicom_is_complete(p)
            except IncompleteDicom as exc:
                if now - pending.since >= self.give_up_s and not pending.reported:
                    pending.reported = True  # reported once; still retried at each poll, and offered once whole
                    log.error("%s: %s (unchanged for %.0f s; will be read once it is whole)", p, exc, self.give_up_s)
                    if self.on_error is not None:
                        self.on_error(p, f"{p}: {exc}")
                continue
            del self._pending[p]
            self._offered[p] = stamp
            ready.append((stamp[1], p))
        for p in [p for p in self._pending if not p.exists()]:
            del self._pending[p]
        return [p for _, p in sorted(ready)]

    def failed(self, path: str | Path, message: str) -> None:
        """The caller could not read an offered file: reported, and offered again if the file changes."""
        p = Path(path)
        stamp = self._offered.pop(p, None) or _stamp(p)
        if stamp is not None:
            self._refuse(p, stamp, message if str(p.name) in message else f"{p}: {message}")

    def wait(self, timeout_s: float) -> list[Path]:
        end = time.monotonic() + timeout_s
        while True:
            got = self.poll()
            if got or time.monotonic() >= end:
                return got
            time.sleep(self.poll_s)

    def apply_retention(self, *, max_age_s: float, max_total_bytes: int, now_s: float | None = None) -> list[Path]:
        """:func:`apply_retention` on this folder, sparing files not yet processed unless they are past ``max_age_s``."""
        spare = {p for p in self._candidates() if not self.is_processed(p)}
        removed = apply_retention(self.folder, max_age_s=max_age_s, max_total_bytes=max_total_bytes, now_s=now_s, spare=spare)
        if removed:
            self._compact_journal()
        return removed


def _stamp(p: Path) -> tuple[int, int] | None:
    try:
        st = p.stat()
    except FileNotFoundError:
        return None
    return st.st_size, st.st_mtime_ns


def apply_retention(folder: str | Path, *, max_age_s: float, max_total_bytes: int, now_s: float | None = None, spare: set[Path] | frozenset[Path] = frozenset()) -> list[Path]:
    """Delete incoming images older than ``max_age_s``, then the oldest until the rest fit ``max_total_bytes``.

    Only regular, non-hidden files directly in ``folder`` count, plus hidden
    ``*.part`` leftovers older than ``max_age_s``. Files in ``spare`` (not yet
    processed) are kept by the byte budget, never past the age. Returns what was deleted, oldest first.
    """
    if max_age_s <= 0 or max_total_bytes < 0:
        raise ValueError(f"retention needs max_age_s > 0 and max_total_bytes >= 0, got {max_age_s}, {max_total_bytes}")
    folder = Path(folder)
    now = time.time() if now_s is None else now_s
    files = []
    with os.scandir(folder) as it:
        for e in it:
            if not e.is_file(follow_symlinks=False) or (e.name.startswith(".") and not e.name.endswith(".part")):
                continue
            st = e.stat(follow_symlinks=False)
            files.append((st.st_mtime, st.st_size, Path(e.path)))
    files.sort()
    removed: list[Path] = []
    total = sum(size for _, size, p in files if not p.name.startswith("."))
    for mtime, size, p in files:
        too_old = now - mtime > max_age_s
        over = total > max_total_bytes and p not in spare and not p.name.startswith(".")
        if not (too_old or over):
            continue
        try:
            p.unlink()
        except FileNotFoundError:
            pass
        if not p.name.startswith("."):
            total -= size
        removed.append(p)
        log.info("retention: deleted %s (%s)", p.name, "older than %.0f h" % (max_age_s / 3600) if too_old else "over the disk budget")
    return removed
