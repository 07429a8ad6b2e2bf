"""Encoding and decoding of every drillnav message. Stamps are integer nanoseconds.

Foxglove messages are protobuf (``foxglove_schemas_protobuf``); drillnav's own
are UTF-8 JSON validated against the JSON Schemas below, which also go into
MCAP files as the channels' schemas.
"""

from __future__ import annotations

import base64
import json
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf import descriptor_pb2
from numpy.typing import NDArray

from drillnav.registration.carm import CArmView

from .projection import view_from_json, view_to_json

__all__ = [
    "JSON_SCHEMAS",
    "compressed_image",
    "decode_compressed_image",
    "encode_json",
    "decode_json",
    "fluoro_shot",
    "decode_fluoro_shot",
    "protobuf_schema",
    "LOG_SCALE",
]

LOG_SCALE = 4000.0

_NUM3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "drillnav.DrillAxis": {
        "type": "object",
        "required": ["stamp_ns", "frame_id", "point_mm", "direction", "predicted_error", "source_frame_stamp_ns", "registration_id"],
        "properties": {
            "stamp_ns": {"type": "integer"}, "frame_id": {"type": "string"}, "point_mm": _NUM3, "direction": _NUM3,
            "predicted_error": {"type": "object", "properties": {"position_mm": {"type": "number"}, "angle_deg": {"type": "number"}}},
            "source_frame_stamp_ns": {"type": "integer"}, "registration_id": {"type": "integer"}, "markers_used": {"type": "array"},
            "ct_registration_id": {"type": "integer"}, "ct_similarity_gc": {"type": "number"},
            "conformance": {"type": "object", "description": "frame V only: against the nearest planned trajectory",
                            "properties": {"trajectory": {"type": "string"}, "breach": {"type": "boolean"}, "min_clearance_mm": {"type": ["number", "null"]},
                                           "axis_to_planned_entry_mm": {"type": "number"}, "angle_to_plan_deg": {"type": "number"}, "kwire_radius_mm": {"type": "number"}}},
        },
    },
    "drillnav.VideoMarkers": {"type": "object", "required": ["stamp_ns", "markers"], "properties": {"stamp_ns": {"type": "integer"}, "markers": {"type": "array"}}},
    "drillnav.FluoroShot": {
        "type": "object",
        "required": ["stamp_ns", "view", "projection", "png16_base64"],
        "properties": {"stamp_ns": {"type": "integer"}, "view": {"type": "string"}, "projection": {"type": "object"}, "png16_base64": {"type": "string"}, "source_file": {"type": "string"}},
    },
    "drillnav.FluoroMarkers": {"type": "object", "required": ["stamp_ns", "registration_id", "markers"]},
    "drillnav.Status": {"type": "object", "required": ["stamp_ns", "state"]},
    "drillnav.Event": {"type": "object", "required": ["stamp_ns", "level", "message"]},
    "drillnav.TwinTruth": {"type": "object", "required": ["frame_stamp_ns", "carm_from_drill", "drill_axis_carm"]},
}


def encode_json(doc: dict[str, Any]) -> bytes:
    return json.dumps(doc, separators=(",", ":")).encode()


def decode_json(data: bytes) -> dict[str, Any]:
    try:
        doc = json.loads(bytes(data))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"malformed JSON message: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError("malformed message: expected a JSON object")
    return doc


def compressed_image(image: NDArray[np.uint8], *, stamp_ns: int, frame_id: str, fmt: str = "jpeg", quality: int = 90) -> bytes:
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", image, [cv2.IMWRITE_JPEG_QUALITY, quality] if fmt == "jpeg" else [])
    if not ok:
        raise ValueError(f"could not encode the image as {fmt}")
    msg = CompressedImage(frame_id=frame_id, data=buf.tobytes(), format=fmt)
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(int(stamp_ns), 1_000_000_000)
    return msg.SerializeToString()


def decode_compressed_image(data: bytes) -> tuple[NDArray[np.uint8], int, str]:
    msg = CompressedImage()
    msg.ParseFromString(bytes(data))
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"CompressedImage holds no decodable {msg.format} data")
    return img, msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos, msg.frame_id


def fluoro_shot(image_log: NDArray[np.float32], view: CArmView, *, stamp_ns: int, view_name: str, source_file: str = "") -> bytes:
    png = cv2.imencode(".png", np.clip(np.round(image_log * LOG_SCALE), 0, 65535).astype(np.uint16))[1].tobytes()
    return encode_json({"stamp_ns": int(stamp_ns), "view": view_name, "projection": view_to_json(view), "png16_base64": base64.b64encode(png).decode(), "source_file": source_file})


def decode_fluoro_shot(data: bytes) -> tuple[NDArray[np.float32], CArmView, int, str]:
    doc = decode_json(data)
    for k in ("stamp_ns", "view", "projection", "png16_base64"):
        if k not in doc:
            raise ValueError(f"malformed FluoroShot: missing '{k}'")
    img = cv2.imdecode(np.frombuffer(base64.b64decode(doc["png16_base64"]), np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16:
        raise ValueError("malformed FluoroShot: the image is not a 16-bit PNG")
    return img.astype(np.float32) / LOG_SCALE, view_from_json(doc["projection"], source="FluoroShot"), int(doc["stamp_ns"]), str(doc["view"])


def protobuf_schema(message_cls) -> bytes:
    """FileDescriptorSet (serialised) of a protobuf message type and its dependencies, as MCAP wants it."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        for dep in fd.dependencies:
            add(dep)
        seen.add(fd.name)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        fds.file.append(proto)

    add(message_cls.DESCRIPTOR.file)
    return fds.SerializeToString()
