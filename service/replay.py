"""Replays an MCAP recording onto zenoh at the recorded timing (times a rate), and rebuilds the node it needs.

Files are read with mcap's stream reader, front to back, whether or not they
were finished: a file cut by a crash or a full disk replays up to its last
complete chunk and the cut is reported, not raised. Each file the recorder
writes starts with the state carried over from before it (calibrations, the
latest shots, marker poses, status; announced by a ``drillnav.file`` metadata
record), so a rotated file replays alone; :func:`read_calibration` and
:func:`replay_node` rebuild the registration node's calibration from it.
"""

from __future__ import annotations

import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import zenoh
import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader

from drillnav.registration.axis_uncertainty import AxisUncertainty
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.errors import DrillnavError
from drillnav.registration.line import Line3D
from drillnav.registration.markers import MarkerSet, default_marker_set
from drillnav.schemas.calibration_message import ActiveCalibration, decode_calibration_message
from drillnav.schemas.topics import TOPICS

from .recorder import FILE_METADATA

_BLOCK, _DROP = zenoh.CongestionControl.BLOCK, zenoh.CongestionControl.DROP

__all__ = ["RecordingUnreadable", "RecordedMessage", "RecordingReader", "ReplayResult", "iter_recording", "read_calibration", "replay", "replay_node"]

# What a stream cut short, or damaged past some point, raises from the reader.
_CUT_ERRORS = (McapError, ValueError, EOFError, zstandard.ZstdError, zlib.error)
_RECORD_LIMIT = 1 << 30  # no drillnav record is near 1 GiB; a damaged length field must not allocate one


class RecordingUnreadable(DrillnavError):
    """The MCAP file is missing, not MCAP, or damaged before its first message."""


@dataclass(frozen=True, kw_only=True)
class RecordedMessage:
    topic: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes
    carried_state: bool  # written at the file's start from before it (a rotated file's calibrations, shots, ...)


@dataclass(frozen=True, kw_only=True)
class ReplayResult:
    messages: int
    cut: str | None  # why the file ended early (a crash, a full disk), None when it was read to its end


class RecordingReader:
    """Iterates a recording's messages in file order; after the iteration, ``cut`` says where and why it stopped
    early (None: read to the end). Raises :class:`RecordingUnreadable` only when nothing could be read."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingUnreadable(f"{self.path}: no such file")
        self.cut: str | None = None
        self.messages = 0

    def __iter__(self) -> Iterator[RecordedMessage]:
        channels: dict[int, Channel] = {}
        state_left = 0
        started = False
        with open(self.path, "rb") as f:
            try:
                for record in StreamReader(f, skip_magic=False, validate_crcs=True, record_size_limit=_RECORD_LIMIT).records:
                    started = True
                    if isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Metadata) and record.name == FILE_METADATA:
                        state_left = int(record.metadata.get("state_messages", "0"))
                    elif isinstance(record, Message):
                        channel = channels.get(record.channel_id)
                        if channel is None:
                            raise McapError(f"message on unknown channel {record.channel_id}")
                        self.messages += 1
                        yield RecordedMessage(topic=channel.topic, log_time_ns=record.log_time, publish_time_ns=record.publish_time,
                                              data=record.data, carried_state=state_left > 0)
                        state_left = max(0, state_left - 1)
            except _CUT_ERRORS as exc:
                if not started or self.messages == 0:
                    raise RecordingUnreadable(f"{self.path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
                what = "the file ends inside a record" if isinstance(exc, EndOfFile) else f"{type(exc).__name__}: {exc}"
                self.cut = f"cut after {self.messages} messages at byte {f.tell()} of {self.path.stat().st_size} ({what})"


def iter_recording(path: str | Path) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log_time_ns, payload) in file order (which the recorder keeps in log-time order), up to any cut."""
    for m in RecordingReader(path):
        yield m.topic, m.log_time_ns, m.data


def read_calibration(path: str | Path) -> ActiveCalibration:
    """The first ``drillnav.Calibration`` message of the file (a rotated file carries it at its start)."""
    for m in RecordingReader(path):
        if m.topic.endswith("/" + TOPICS["calibration"].suffix):
            try:
                return decode_calibration_message(m.data)
            except ValueError as exc:
                raise RecordingUnreadable(f"{path}: its calibration message is malformed: {exc}") from None
    raise RecordingUnreadable(f"{path}: holds no {TOPICS['calibration'].schema_name} message; give the calibration files")


def replay_node(path: str | Path, *, session: zenoh.Session, prefix: str, marker_set: MarkerSet | None = None,
                camera: PinholeCamera | None = None, axis_drill: Line3D | None = None, axis_uncertainty: AxisUncertainty | None = None):
    """A :class:`~drillnav.service.node.RegistrationNode` for replaying ``path``: what is not given comes from the
    file's calibration message (the marker set from it too, else the default design; the drill axis's stated
    uncertainty with the file's axis)."""
    from .node import RegistrationNode

    if camera is None or axis_drill is None or marker_set is None:
        need_file = camera is None or axis_drill is None
        try:
            cal = read_calibration(path)
        except RecordingUnreadable:
            if need_file:
                raise
            cal = None
        if cal is not None:
            camera = camera if camera is not None else cal.camera
            if axis_drill is None:
                axis_drill, axis_uncertainty = cal.axis_drill, cal.axis_uncertainty
            marker_set = marker_set if marker_set is not None else cal.marker_set
    # Entered (its workers running); the caller closes it.
    return RegistrationNode(session=session, prefix=prefix, marker_set=marker_set or default_marker_set(), camera=camera, axis_drill=axis_drill,
                            axis_uncertainty=axis_uncertainty).__enter__()


def replay(path: str | Path, session: zenoh.Session, *, rate: float = 1.0, stop: threading.Event | None = None, state_settle_s: float = 0.0) -> ReplayResult:
    """Publish every message at its recorded time offset divided by ``rate``, up to any cut.

    ``state_settle_s``: a pause after the state a file carries at its start, so a node registers from the
    carried shots before the camera frames that follow arrive (as it had in the live run).
    """
    if rate <= 0:
        raise ValueError(f"rate must be positive, got {rate}")
    if state_settle_s < 0:
        raise ValueError(f"state_settle_s must not be negative, got {state_settle_s}")
    reader = RecordingReader(path)
    start_wall, start_log, n, in_state = time.monotonic(), None, 0, False
    for m in reader:
        if stop is not None and stop.is_set():
            break
        if in_state and not m.carried_state and state_settle_s:
            time.sleep(state_settle_s)
            start_wall, start_log = time.monotonic(), m.log_time_ns
        in_state = m.carried_state
        if start_log is None:
            start_log = m.log_time_ns
        delay = start_wall + (m.log_time_ns - start_log) / 1e9 / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        # Shots, calibrations and state are megabytes or once-only: blocked, never dropped, when the link is busy
        # (zenoh's default for a put drops it); camera frames keep the live stream's drop-the-stale rule.
        session.put(m.topic, m.data, congestion_control=_DROP if m.topic.endswith("camera/image") else _BLOCK)
        n += 1
    return ReplayResult(messages=n, cut=reader.cut)
