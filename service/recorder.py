"""Records every drillnav stream to MCAP: chunked, zstd-compressed, indexed, with schemas.

Chunks are small and the file is flushed after every message (the writer only
emits bytes when a chunk completes), so a killed process leaves a file whose
every complete chunk is on disk; a clean stop writes the summary
and index. Files rotate by size and by time.
"""

from __future__ import annotations

import datetime as dt
import threading
import time
from pathlib import Path

import zenoh
from mcap.writer import CompressionType, Writer

from drillnav.schemas.messages import JSON_SCHEMAS, protobuf_schema
from drillnav.schemas.protobuf_types import PROTOBUF_TYPES
from drillnav.schemas.topics import Encoding, topic_for_key

__all__ = ["Recorder"]

_PROTO = PROTOBUF_TYPES


class Recorder:
    """Subscribes to ``<prefix>/**`` on ``session`` and writes MCAP files into ``folder`` named ``<name>-<UTC>-<n>.mcap``."""

    def __init__(self, *, session: zenoh.Session, prefix: str, folder: Path, name: str, chunk_size: int = 256 * 1024,
                 rotate_bytes: int = 512 * 1024 * 1024, rotate_seconds: float = 3600.0) -> None:
        if not name.replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"recording name '{name}' may hold only letters, digits, '-' and '_'")
        self.prefix, self.folder, self.name = prefix, Path(folder), name
        if rotate_bytes <= 0 or rotate_seconds <= 0:
            raise ValueError("rotate_bytes and rotate_seconds must be positive")
        self.chunk_size, self.rotate_bytes, self.rotate_ns = chunk_size, rotate_bytes, int(rotate_seconds * 1e9)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._index = 0
        self.files: list[Path] = []
        self.messages = 0
        self.bytes = 0
        self._open_file()
        self._sub = session.declare_subscriber(f"{prefix}/**", self._on_sample)

    def _open_file(self) -> None:
        stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
        path = self.folder / f"{self.name}-{stamp}-{self._index}.mcap"
        self._index += 1
        self._fp = open(path, "wb")
        self._writer = Writer(self._fp, chunk_size=self.chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="drillnav")
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._file_bytes = 0
        self._file_started_ns = time.monotonic_ns()
        self.files.append(path)

    def _channel(self, key_expr: str) -> int:
        if key_expr in self._channels:
            return self._channels[key_expr]
        topic = topic_for_key(self.prefix, key_expr)
        if topic is None:
            schema_id, encoding = 0, "application/octet-stream"
        else:
            if topic.schema_name not in self._schemas:
                if topic.encoding is Encoding.PROTOBUF:
                    self._schemas[topic.schema_name] = self._writer.register_schema(name=topic.schema_name, encoding="protobuf", data=protobuf_schema(_PROTO[topic.schema_name]))
                else:
                    import json

                    self._schemas[topic.schema_name] = self._writer.register_schema(name=topic.schema_name, encoding="jsonschema", data=json.dumps(JSON_SCHEMAS[topic.schema_name]).encode())
            schema_id, encoding = self._schemas[topic.schema_name], topic.encoding.value
        self._channels[key_expr] = self._writer.register_channel(topic=key_expr, message_encoding=encoding, schema_id=schema_id)
        return self._channels[key_expr]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        now = time.time_ns()
        with self._lock:
            if self._fp is None:
                return
            self._writer.add_message(channel_id=self._channel(str(sample.key_expr)), log_time=now, publish_time=now, data=data)
            # Hand every completed chunk to the OS at once, so a killed process loses only the open chunk.
            self._fp.flush()
            self.messages += 1
            self.bytes += len(data)
            self._file_bytes += len(data)
            if self._file_bytes >= self.rotate_bytes or time.monotonic_ns() - self._file_started_ns >= self.rotate_ns:
                self._finish_file()
                self._open_file()

    def _finish_file(self) -> None:
        self._writer.finish()
        self._fp.close()

    def close(self) -> list[Path]:
        """Stop recording and write the summary; returns the files written."""
        self._sub.undeclare()
        with self._lock:
            if self._fp is not None:
                self._finish_file()
                self._fp = None
        return self.files
