"""Records every drillnav stream to MCAP: bounded on disk, self-contained per file, safe on a full disk.

- **Budget.** Camera frames are recorded at ``camera_fps`` (decimated on arrival) and re-encoded at
  ``camera_jpeg_quality``; every other stream is recorded in full. Re-encoding happens on the
  recorder's writer thread, fed by a bounded queue, never on zenoh's callback thread; when the
  writer falls behind, messages are dropped, counted and reported rather than queued without end.
- **Self-contained files.** The recorder keeps the latest of each state message (the active
  calibrations, the latest shot and display image of each view, the latest marker registration,
  the latest status) and writes them first into every new file, with an MCAP metadata record
  ``drillnav.file`` saying how many there are, so any rotated file replays alone.
- **Crash and disk safety.** Files are written through one descriptor whose offset after the last
  complete record is always known. A killed process loses only the open chunk. A failed write
  (disk full) cuts the file back to its last complete chunk, ends it with a footer so indexed and
  streaming readers both read it, pauses the recording with an event, and resumes in a new file
  once space returns. Nothing else stops.
- **Patient data.** The folder is 0700 and files 0600; at start and at every rotation the oldest
  finished files are removed beyond ``max_age_s`` and ``max_total_bytes`` (a file another recorder
  holds open is locked and never removed).
"""

from __future__ import annotations

import datetime as dt
import errno
import fcntl
import os
import queue
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh
from mcap.records import DataEnd, Footer
from mcap.data_stream import RecordBuilder
from mcap.writer import CompressionType, Writer

from drillnav.schemas import messages as msg
from drillnav.schemas.channel_schemas import channel_schema
from drillnav.schemas.topics import TOPICS, key, topic_for_key

from .settings import RecordingSettings

__all__ = ["CarriedState", "Recorder", "RecorderStatus", "apply_retention", "FILE_METADATA"]

FILE_METADATA = "drillnav.file"  # the metadata record before each file's state block
_MAGIC = b"\x89MCAP0\r\n"

# State carried into every new file, in the order it is written (calibrations before the shots that need them).
_STATE_TOPICS = ("calibration", "fluoro_shot", "fluoro_image", "fluoro_markers", "status")

OnEvent = Callable[[str, str], None]
# Failed writes that mean "no room": the recording pauses and resumes when there is room again.
_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


@dataclass(frozen=True, kw_only=True)
class RecorderStatus:
    name: str
    files: tuple[str, ...]
    recording: bool          # False once closed
    paused: bool             # a write failed (disk full); waiting for space to resume in a new file
    pause_reason: str | None
    messages: int            # written
    bytes: int               # payload bytes written
    camera_frames_skipped: int   # by the camera_fps decimation (by design)
    dropped: int             # the writer thread fell behind: lost
    lost_while_paused: int   # arrived while paused: lost
    write_errors: int


def _no_event(level: str, message: str) -> None:
    pass


class CarriedState:
    """The latest of each state message under ``prefix``: what a new file must start with to replay alone.

    Each recorder keeps one from what it records. A daemon that starts recordings mid-case shares one that it
    keeps from start-up (``subscribe``), so a recording's first file carries the shots taken before it began.
    """

    def __init__(self, *, prefix: str) -> None:
        self.prefix = prefix
        self._rank = {name: i for i, name in enumerate(_STATE_TOPICS)}
        self._lock = threading.Lock()
        self._latest: dict[tuple[int, str], tuple[str, int, bytes]] = {}  # (rank, view or key) -> (key, log_time_ns, data)

    def keep(self, key_expr: str, log_time_ns: int, data: bytes) -> None:
        topic = topic_for_key(self.prefix, key_expr)
        name = next((n for n in _STATE_TOPICS if TOPICS[n] is topic), None)
        if name is None:
            return
        which = key_expr
        if name == "fluoro_shot":  # one key for every view: the view is in the message
            try:
                which = str(msg.decode_json(data)["view"])
            except (ValueError, KeyError):
                return  # a malformed shot is recorded but carried into no file
        with self._lock:
            self._latest[(self._rank[name], which)] = (key_expr, log_time_ns, data)

    def messages(self) -> list[tuple[str, int, bytes]]:
        """(key, first log_time_ns, payload), calibrations first, then shots, images, markers, status, each oldest first."""
        with self._lock:
            items = sorted(self._latest.items(), key=lambda kv: (kv[0][0], kv[1][1]))
        return [v for _, v in items]

    def subscribe(self, session: zenoh.Session) -> list:
        """Keep it from ``session`` (state keys only); returns the subscribers, to undeclare when done."""
        keys = [key(self.prefix, n, "*") if "*" in TOPICS[n].suffix else key(self.prefix, n) for n in _STATE_TOPICS]
        return [session.declare_subscriber(k, lambda sample: self.keep(str(sample.key_expr), time.time_ns(), sample.payload.to_bytes())) for k in keys]


class _McapFile:
    """One MCAP file written through a raw descriptor, so the offset after its last complete record is always known.

    ``Writer`` sees this object as its stream (write/tell/flush). A failed write leaves bytes past
    ``committed`` that :meth:`abort` cuts off before ending the file.
    """

    def __init__(self, path: Path, *, chunk_size: int) -> None:
        self.path = path
        # O_EXCL: never append to or clobber a file someone else made; 0600: patient data.
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
        # Held until closed: retention skips locked files, whichever recorder or process holds them.
        fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self.pos = self.committed = 0
        self.messages = 0
        self.channels: dict[str, int] = {}
        self.schemas: dict[str, int] = {}
        self.writer = Writer(self, chunk_size=chunk_size, compression=CompressionType.ZSTD)

    # -- the stream Writer writes to ---------------------------------------------------------
    def write(self, data) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            self.pos += n
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass  # unbuffered: every write is already the OS's

    # -- records ------------------------------------------------------------------------------
    def start(self, metadata: dict[str, str]) -> None:
        self.writer.start(profile="", library="drillnav")
        self.writer.add_metadata(FILE_METADATA, metadata)
        self.committed = self.pos

    def channel(self, prefix: str, key_expr: str) -> int:
        if key_expr in self.channels:
            return self.channels[key_expr]
        topic = topic_for_key(prefix, key_expr)
        if topic is None:
            schema_id, encoding = 0, "application/octet-stream"
        else:
            if topic.schema_name not in self.schemas:
                cs = channel_schema(topic)
                self.schemas[topic.schema_name] = self.writer.register_schema(name=cs.name, encoding=cs.encoding, data=cs.data)
            schema_id, encoding = self.schemas[topic.schema_name], topic.encoding.value
        self.channels[key_expr] = self.writer.register_channel(topic=key_expr, message_encoding=encoding, schema_id=schema_id)
        return self.channels[key_expr]

    def add(self, prefix: str, key_expr: str, *, log_time_ns: int, publish_time_ns: int, data: bytes) -> None:
        self.writer.add_message(channel_id=self.channel(prefix, key_expr), log_time=log_time_ns, publish_time=publish_time_ns, data=data)
        self.messages += 1
        # A chunk is written whole or the call raised: everything before this offset is complete records.
        self.committed = self.pos

    def finish(self) -> None:
        self.writer.finish()
        os.fsync(self.fd)
        os.close(self.fd)
        self.fd = -1

    def abort(self) -> bool:
        """After a failed write: cut back to the last complete record and end the file there.

        Returns False when the file held no message and was removed instead.
        """
        try:
            if self.messages == 0:
                os.unlink(self.path)
                return False
            os.ftruncate(self.fd, self.committed)
            self.pos = self.committed
            # Without a summary (summary_start 0), make_reader reads the file linearly; cutting the partial
            # chunk freed at least a few pages, so these 50 bytes fit. If not, the file stays cut at a
            # record boundary, which streaming readers read to the end.
            end = RecordBuilder()
            DataEnd(data_section_crc=0).write(end)
            Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(end)
            try:
                os.pwrite(self.fd, end.end() + _MAGIC, self.committed)
                os.fsync(self.fd)
            except OSError:
                os.ftruncate(self.fd, self.committed)
            return True
        finally:
            os.close(self.fd)
            self.fd = -1


def apply_retention(folder: Path, *, max_age_s: float | None, max_total_bytes: int | None, now_s: float | None = None) -> list[Path]:
    """Remove the oldest finished ``*.mcap`` files in ``folder``: all older than ``max_age_s``, then more
    until the folder holds at most ``max_total_bytes``. Files held open (locked) by a recorder count
    towards the total but are never removed. Returns the files removed."""
    now_s = time.time() if now_s is None else now_s
    files = []
    for p in Path(folder).glob("*.mcap"):
        try:
            st = p.stat()
        except FileNotFoundError:
            continue
        files.append((st.st_mtime, st.st_size, p))
    files.sort()
    total = sum(size for _, size, _ in files)
    removed = []
    for mtime, size, p in files:
        too_old = max_age_s is not None and now_s - mtime > max_age_s
        too_much = max_total_bytes is not None and total > max_total_bytes
        if not (too_old or too_much):
            continue
        try:
            fd = os.open(p, os.O_RDONLY | os.O_CLOEXEC)
        except FileNotFoundError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                continue  # being written
            raise
        else:
            p.unlink()
            total -= size
            removed.append(p)
        finally:
            os.close(fd)
    return removed


class Recorder:
    """Subscribes to ``<prefix>/**`` on ``session`` and writes MCAP files into ``folder`` named ``<name>-<UTC>-<n>.mcap``.

    Records from construction until :meth:`close` (like an open file; also a context manager).
    ``camera_fps`` / ``camera_jpeg_quality`` None (the defaults here) keep every frame as received; the budget
    is a policy of the settings ([recording], see :meth:`from_settings`). ``on_event(level, message)``
    hears pauses, resumes, drops and retention removals. ``carried_state``: a :class:`CarriedState` kept from
    before this recording began (the daemon's), else the recorder keeps its own from what it records.
    """

    def __init__(self, *, session: zenoh.Session, prefix: str, folder: Path, name: str, chunk_size: int = 256 * 1024,
                 rotate_bytes: int = 512 * 1024 * 1024, rotate_seconds: float = 3600.0, camera_fps: float | None = None,
                 camera_jpeg_quality: int | None = None, queue_size: int = 256, max_age_s: float | None = None,
                 max_total_bytes: int | None = None, resume_free_bytes: int = 64 * 1024 * 1024, resume_check_s: float = 2.0,
                 on_event: OnEvent = _no_event, carried_state: CarriedState | None = None, overlay_fps: float | None = None) -> None:
        if not name.replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"recording name '{name}' may hold only letters, digits, '-' and '_'")
        if rotate_bytes <= 0 or rotate_seconds <= 0:
            raise ValueError("rotate_bytes and rotate_seconds must be positive")
        if camera_fps is not None and camera_fps <= 0:
            raise ValueError(f"camera_fps must be positive or None (every frame), got {camera_fps}")
        if camera_jpeg_quality is not None and not 1 <= camera_jpeg_quality <= 100:
            raise ValueError(f"camera_jpeg_quality must be 1..100 or None (as received), got {camera_jpeg_quality}")
        if queue_size < 1 or chunk_size < 1 or resume_check_s <= 0:
            raise ValueError("queue_size, chunk_size and resume_check_s must be positive")
        self.prefix, self.folder, self.name = prefix, Path(folder), name
        self.chunk_size, self.rotate_bytes, self.rotate_ns = chunk_size, rotate_bytes, int(rotate_seconds * 1e9)
        self.camera_period_ns = int(1e9 / camera_fps) if camera_fps else 0
        # The node's overlay JPEGs are derived (shots + axes + scene annotations redraw them): kept at a low rate per view.
        if overlay_fps is not None and overlay_fps <= 0:
            raise ValueError(f"overlay_fps must be positive or None (every overlay), got {overlay_fps}")
        self.overlay_period_ns = int(1e9 / overlay_fps) if overlay_fps else 0
        self._overlay_prefix = key(prefix, "overlay", "x")[:-1]
        self._next_overlay_ns: dict[str, int] = {}
        self.overlays_skipped = 0
        self.camera_jpeg_quality = camera_jpeg_quality
        self.max_age_s, self.max_total_bytes = max_age_s, max_total_bytes
        self.resume_free_bytes, self.resume_check_ns = resume_free_bytes, int(resume_check_s * 1e9)
        self._on_event = on_event
        self._camera_key = key(prefix, "camera_image")
        self.folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(self.folder, 0o700)  # also an existing folder: recordings hold patient images
        self.files: list[Path] = []
        self.messages = self.bytes = self.camera_frames_skipped = self.dropped = self.lost_while_paused = self.write_errors = 0
        self._index = 0
        self._file: _McapFile | None = None
        self._file_bytes = 0
        self._file_started_ns = 0
        self.pause_reason: str | None = None
        self._retry_at_ns = self._paused_since_ns = 0
        self._pause_errno: int | None = None
        self.carried = carried_state if carried_state is not None else CarriedState(prefix=prefix)
        self._next_frame_ns = 0
        self._last_drop_event_ns = 0
        self._closed = False
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._open_file()
        if self._file is None and self._pause_errno not in _SPACE_ERRNOS:
            # A full disk at start is a pause like any other; a folder we may not write is a configuration error.
            raise OSError(self._pause_errno, f"recording '{name}': cannot write into {self.folder}: {self.pause_reason}")
        self._thread = threading.Thread(target=self._write_loop, name=f"recorder-{name}", daemon=True)
        self._thread.start()
        self._sub = session.declare_subscriber(f"{prefix}/**", self._on_sample)

    @classmethod
    def from_settings(cls, settings: RecordingSettings, *, session: zenoh.Session, prefix: str, name: str, on_event: OnEvent = _no_event,
                      carried_state: CarriedState | None = None) -> "Recorder":
        s = settings
        return cls(session=session, prefix=prefix, folder=s.folder, name=name, rotate_bytes=s.rotate_mb * 1024 * 1024,
                   rotate_seconds=s.rotate_minutes * 60.0, camera_fps=s.camera_fps or None, camera_jpeg_quality=s.camera_jpeg_quality or None,
                   queue_size=s.queue_size, max_age_s=s.max_age_days * 86400.0 if s.max_age_days else None,
                   max_total_bytes=int(s.max_total_gb * 1e9) if s.max_total_gb else None,
                   resume_free_bytes=int(s.resume_free_mb * 1024 * 1024), on_event=on_event, carried_state=carried_state,
                   overlay_fps=s.overlay_fps or None)

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- zenoh's callback thread: decide and enqueue, nothing more --------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        now = time.time_ns()
        key_expr = str(sample.key_expr)
        if key_expr == self._camera_key and self.camera_period_ns:
            if now < self._next_frame_ns:
                self.camera_frames_skipped += 1
                return
            # Due times advance by the period (not from this frame), so jittery arrivals keep the mean rate.
            self._next_frame_ns = self._next_frame_ns + self.camera_period_ns if now - self._next_frame_ns < self.camera_period_ns else now + self.camera_period_ns
        elif self.overlay_period_ns and key_expr.startswith(self._overlay_prefix):
            if now < self._next_overlay_ns.get(key_expr, 0):
                self.overlays_skipped += 1
                return
            self._next_overlay_ns[key_expr] = now + self.overlay_period_ns
        try:
            self._queue.put_nowait((key_expr, now, sample.payload.to_bytes()))
        except queue.Full:
            self.dropped += 1
            if now - self._last_drop_event_ns > 5e9:
                self._last_drop_event_ns = now
                self._event("warning", f"recording '{self.name}': the writer is behind; {self.dropped} message(s) dropped so far")

    # -- the writer thread ------------------------------------------------------------------
    def _write_loop(self) -> None:
        while True:
            try:
                # Paused, the writer wakes on its own to look for space: it resumes (and writes the carried
                # state into the new file) even when nothing is published.
                item = self._queue.get(timeout=self.resume_check_ns / 1e9 if self.paused else None)
            except queue.Empty:
                if time.monotonic_ns() >= self._retry_at_ns:
                    self._try_resume()
                continue
            if item is None:
                return
            try:
                self._write(*item)
            except Exception as exc:  # a worker survives: one bad message must not end the recording
                self.write_errors += 1
                self._event("error", f"recording '{self.name}': message on {item[0]} not recorded ({type(exc).__name__}: {exc})")

    def _write(self, key_expr: str, log_time_ns: int, data: bytes) -> None:
        if key_expr == self._camera_key and self.camera_jpeg_quality is not None:
            image, stamp_ns, frame_id = msg.decode_compressed_image(data)
            data = msg.compressed_image(image, stamp_ns=stamp_ns, frame_id=frame_id, fmt="jpeg", quality=self.camera_jpeg_quality)
        self.carried.keep(key_expr, log_time_ns, data)
        if self._file is None:
            if time.monotonic_ns() < self._retry_at_ns or not self._try_resume():
                self.lost_while_paused += 1
                return
        try:
            self._file.add(self.prefix, key_expr, log_time_ns=log_time_ns, publish_time_ns=log_time_ns, data=data)
        except OSError as exc:
            self.lost_while_paused += 1
            self._pause(exc)
            return
        self.messages += 1
        self.bytes += len(data)
        self._file_bytes += len(data)
        if self._file_bytes >= self.rotate_bytes or time.monotonic_ns() - self._file_started_ns >= self.rotate_ns:
            self._rotate()

    # -- files ------------------------------------------------------------------------------
    def _open_file(self) -> None:
        """Open the next file and write the carried state into it; on failure stay paused."""
        stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
        path = self.folder / f"{self.name}-{stamp}-{self._index}.mcap"
        self._index += 1
        self._retention()
        f = None
        try:
            f = _McapFile(path, chunk_size=self.chunk_size)
            state = self.carried.messages()
            f.start({"recording": self.name, "index": str(self._index - 1), "state_messages": str(len(state)),
                     "started_utc": stamp, "previous_file": self.files[-1].name if self.files else ""})
            opened_ns = time.time_ns()
            for key_expr, log_time_ns, data in state:
                # log_time: when it entered this file (replay timing); publish_time: when it was first recorded.
                f.add(self.prefix, key_expr, log_time_ns=opened_ns, publish_time_ns=log_time_ns, data=data)
        except OSError as exc:
            if f is not None and f.fd >= 0:
                f.abort()
            self._pause(exc, opening=path)
            return
        self._file, self._file_bytes, self._file_started_ns = f, 0, time.monotonic_ns()
        self.files.append(path)

    def _rotate(self) -> None:
        assert self._file is not None
        try:
            self._file.finish()
        except OSError as exc:
            self._pause(exc)
            return
        self._file = None
        self._open_file()

    def _pause(self, exc: OSError, *, opening: Path | None = None) -> None:
        self.write_errors += 1
        f, self._file = self._file, None
        if f is not None and f.fd >= 0:
            if not f.abort() and f.path in self.files:
                self.files.remove(f.path)
        was_paused = self.pause_reason is not None
        self._pause_errno = exc.errno
        self.pause_reason = f"{exc.strerror or exc} ({opening or (f.path if f else self.folder)})"
        self._retry_at_ns = time.monotonic_ns() + self.resume_check_ns
        if not was_paused:
            self._paused_since_ns = time.monotonic_ns()
            self._event("error", f"recording '{self.name}' paused: {self.pause_reason}; the files written so far are closed and readable; "
                                 f"it resumes in a new file once {self.resume_free_bytes / 2**20:.0f} MiB are free")

    def _try_resume(self) -> bool:
        self._retry_at_ns = time.monotonic_ns() + self.resume_check_ns
        try:
            free = shutil.disk_usage(self.folder).free
        except OSError:
            return False
        if free < self.resume_free_bytes:
            return False
        lost = self.lost_while_paused
        self._open_file()
        if self._file is None:
            return False
        paused_s = (time.monotonic_ns() - self._paused_since_ns) / 1e9
        self.pause_reason = None
        self._event("info", f"recording '{self.name}' resumed in {self.files[-1].name} after {paused_s:.0f} s paused ({lost} message(s) not recorded)")
        return True

    def _retention(self) -> None:
        if self.max_age_s is None and self.max_total_bytes is None:
            return
        try:
            removed = apply_retention(self.folder, max_age_s=self.max_age_s, max_total_bytes=self.max_total_bytes)
        except OSError as exc:
            self._event("error", f"recording retention failed in {self.folder}: {exc}")
            return
        if removed:
            self._event("info", f"recording retention removed {len(removed)} file(s): {', '.join(p.name for p in removed)}")

    def _event(self, level: str, message: str) -> None:
        try:
            self._on_event(level, message)
        except Exception:  # the recorder must not stop because a listener failed
            pass

    # -- public -----------------------------------------------------------------------------
    @property
    def paused(self) -> bool:
        return self.pause_reason is not None

    def status(self) -> RecorderStatus:
        return RecorderStatus(name=self.name, files=tuple(str(p) for p in self.files), recording=not self._closed, paused=self.paused,
                              pause_reason=self.pause_reason, messages=self.messages, bytes=self.bytes,
                              camera_frames_skipped=self.camera_frames_skipped, dropped=self.dropped,
                              lost_while_paused=self.lost_while_paused, write_errors=self.write_errors)

    def close(self) -> list[Path]:
        """Stop recording, write what is queued, and end the file with its summary; returns the files written."""
        if self._closed:
            return self.files
        self._closed = True
        self._sub.undeclare()
        self._queue.put(None)  # blocks while full: everything accepted is written
        self._thread.join()
        if self._file is not None:
            try:
                self._file.finish()
            except OSError as exc:
                self._pause(exc)
            self._file = None
        return self.files
