"""Every drillnav message: typed, validated at the boundary, and the only place that knows the wire format.

Stamps are integer nanoseconds. Foxglove messages are protobuf
(``foxglove_schemas_protobuf``); drillnav's own are UTF-8 JSON, one frozen
dataclass each (:class:`DrillAxis`, :class:`Status`, :class:`Event`,
:class:`FluoroShot`, :class:`FluoroMarkers`) with ``to_bytes()`` and a
validating ``from_bytes(data)``. Their JSON Schemas are generated from the
classes (pydantic), so the schema an MCAP file carries and what the wire holds
cannot drift apart; every schema forbids properties it does not list.

Validation is total: types, lengths, finite numbers (no NaN or inf), unit
directions, a decodable non-empty 16-bit image, a sane projection. A failure
is a ``ValueError`` whose message names the message type and the field.
"""

from __future__ import annotations

import base64
import json
from functools import cached_property
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError
from numpy.typing import NDArray
from pydantic import ConfigDict, Field, TypeAdapter, ValidationError
from pydantic.dataclasses import dataclass

from drillnav.registration.carm import CArmView

from .projection import view_from_json, view_to_json

__all__ = [
    "JSON_SCHEMAS",
    "DrillAxis",
    "PredictedError",
    "Conformance",
    "Status",
    "ShotCounts",
    "Event",
    "FluoroShot",
    "Projection",
    "FluoroMarkers",
    "AuditEntry",
    "MarkerPoseMsg",
    "VideoMarkers",
    "VideoTag",
    "compressed_image",
    "decode_compressed_image",
    "parse_compressed_image",
    "encode_json",
    "decode_json",
    "protobuf_schema",
    "LOG_SCALE",
]

LOG_SCALE = 4000.0  # 16-bit PNG counts per unit of log attenuation in a FluoroShot

# Strict: a string is never an int, a number never a bool; no NaN/inf; no property a class does not declare.
_CONFIG = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)

Vec3 = tuple[float, float, float]
Row4 = tuple[float, float, float, float]
Transform = tuple[Row4, Row4, Row4, Row4]  # a 4x4 homogeneous transform, row-major
Level = Literal["info", "warning", "error"]
NonNegInt = Annotated[int, Field(ge=0)]


def _vec(values: Any) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(values, dtype=np.float64).ravel())


def _transform(matrix: Any) -> Transform:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"a transform must be 4x4, got shape {m.shape}")
    return tuple(tuple(float(v) for v in row) for row in m)  # type: ignore[return-value]


class _Message:
    """``to_bytes``/``from_bytes``/``to_dict`` for the pydantic dataclasses below."""

    _adapter: TypeAdapter
    schema_name: str

    def to_dict(self) -> dict[str, Any]:
        return self._adapter.dump_python(self, mode="json")

    def to_bytes(self) -> bytes:
        return self._adapter.dump_json(self)

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview):
        """Decode and validate; ``ValueError`` naming the class and the first bad field."""
        try:
            return cls._adapter.validate_json(bytes(data))
        except ValidationError as exc:
            raise ValueError(_describe(cls.__name__, exc)) from None

    @classmethod
    def json_schema(cls) -> dict[str, Any]:
        return cls._adapter.json_schema()


def _describe(name: str, exc: ValidationError) -> str:
    errors = exc.errors(include_url=False)
    first = errors[0]
    where = ".".join(str(p) for p in first["loc"])
    if first["type"] in ("json_invalid", "json_type"):
        return f"{name}: not a JSON object ({first['msg']})"
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    text = first["msg"].removeprefix("Value error, ")  # a check of the whole message names its field itself
    return f"{name}.{where}: {text}{more}" if where else f"{name}: {text}{more}"


def _bind(cls):
    """Give a message class its adapter (validation, dump, schema) once, at import."""
    cls._adapter = TypeAdapter(cls)
    return cls


# -- the drill axis ---------------------------------------------------------------------------------
@dataclass(config=_CONFIG, kw_only=True)
class PredictedError:
    position_mm: float = Field(ge=0, description="predicted axis position error at the working point, mm")
    angle_deg: float = Field(ge=0, description="predicted axis angle error, degrees")
    position90_mm: float | None = Field(None, ge=0, description="90 % bound of the position error at the working point, mm")
    angle90_deg: float | None = Field(None, ge=0, description="90 % bound of the angle error, degrees")


@dataclass(config=_CONFIG, kw_only=True)
class Conformance:
    """Frame V only: the axis against the nearest planned trajectory."""

    trajectory: str
    axis_to_planned_entry_mm: float
    angle_to_plan_deg: float
    breach: bool
    min_clearance_mm: float | None = Field(description="null: the axis never enters the acceptance volume's map")
    kwire_radius_mm: float
    min_clearance_along_mm: float | None = Field(None, description="where the clearance is smallest: mm along the axis from its entry into bone")
    min_clearance_point_mm: Vec3 | None = Field(None, description="where the clearance is smallest: the point in V, mm")


@_bind
@dataclass(config=_CONFIG, kw_only=True)
class DrillAxis(_Message):
    """The drill axis in frame C (``axis/carm``) or the CT frame V (``axis/ct``), one per camera frame."""

    schema_name = "drillnav.DrillAxis"
    stamp_ns: NonNegInt
    frame_id: Literal["carm", "ct"]
    point_mm: Vec3 = Field(description="the axis point nearest the registered markers' centroid (working point), mm")
    direction: Vec3 = Field(description="unit direction of the drill, tip-wards")
    predicted_error: PredictedError
    source_frame_stamp_ns: NonNegInt = Field(description="capture stamp of the camera frame this axis comes from")
    registration_id: NonNegInt = Field(description="the marker registration in use")
    sequence: NonNegInt = Field(description="0, 1, 2, ... per daemon run, +1 per published axis; a gap is a lost message")
    reliable: bool = Field(True, description="false when the predicted error exceeds the limit: do not guide by it")
    markers_used: tuple[int, ...] = ()
    markers_rejected: tuple[int, ...] = ()
    fre_mm: dict[str, float] = Field(default_factory=dict, description="per marker id: fiducial registration error, mm")
    carm_from_drill: Transform | None = None
    detector_distortion_px: dict[str, tuple[float, float]] = Field(
        default_factory=dict, description="per fluoroscopy view from an image intensifier: its distortion as the registration estimated it, "
        "(pincushion, S) shift at the field's corner, px (docs/geometry.md#image-intensifier-distortion); a display draws the axis "
        "bent by it. Empty for flat panels")
    ct_registration_id: NonNegInt | None = None
    ct_similarity_gc: float | None = None
    carm_from_ct: Transform | None = None
    conformance: Conformance | None = None

    def __post_init__(self) -> None:
        n = float(np.linalg.norm(self.direction))
        if abs(n - 1.0) > 1e-6:
            raise ValueError(f"direction must be a unit vector, has norm {n:.6g}")


# -- status and events ----------------------------------------------------------------------------
@dataclass(config=_CONFIG, kw_only=True)
class ShotCounts:
    """How every received shot ended (``received == registered + superseded + failed + pending``)."""

    received: NonNegInt = 0
    registered: NonNegInt = Field(0, description="took part in a registration")
    superseded: NonNegInt = Field(0, description="a newer shot of the same view arrived before it was processed")
    failed: NonNegInt = Field(0, description="refused (malformed) or its registration failed")
    pending: NonNegInt = 0


@_bind
@dataclass(config=_CONFIG, kw_only=True)
class Status(_Message):
    """The node's state and counters, about 1 Hz on ``registration/status``."""

    schema_name = "drillnav.Status"
    stamp_ns: NonNegInt
    state: str = Field(description="uncalibrated | waiting for fluoroscopy | registered | registration failed: <why>")
    registration_id: NonNegInt
    views: tuple[str, ...] = Field(description="the views of the registration in use (a shot still being registered is not among them)")
    frames_received: NonNegInt
    frames_processed: NonNegInt
    frames_dropped: NonNegInt
    axes_published: NonNegInt
    shots_received: NonNegInt
    registrations: NonNegInt
    registration_failures: NonNegInt
    shots: ShotCounts
    bad_messages: dict[str, NonNegInt] = Field(description="per input key: messages refused at the boundary")
    loop_errors: dict[str, NonNegInt] = Field(description="per worker loop: unexpected exceptions caught (the loop went on)")
    thread_restarts: NonNegInt = Field(description="worker threads found dead and restarted")
    latency_ms_p50: float
    latency_ms_p99: float
    last_error: str | None
    calibrated: bool
    ct_registration_id: NonNegInt | None = None
    ct_registering: bool | None = None
    ct_failures: NonNegInt | None = None
    ct_similarity_gc: float | None = None
    ct_last_error: str | None = None
    joint_solves: dict[str, NonNegInt] | None = Field(None, description="the periodic joint solve: requested of its worker process, adopted, "
                                                      "late (adopted by a later frame), restarted (its worker died), dropped, failed, "
                                                      "unreliable (flagged by its own bound and less sure than the refinement in use: not adopted)")


@_bind
@dataclass(config=_CONFIG, kw_only=True)
class Event(_Message):
    """Re-registrations, refusals and errors on ``registration/events``, as they happen."""

    schema_name = "drillnav.Event"
    stamp_ns: NonNegInt
    level: Level
    message: str = Field(min_length=1)
    key: str | None = Field(None, description="the input key a refused message came on")
    reason: str | None = Field(None, description="why it was refused")


# -- fluoroscopy ----------------------------------------------------------------------------------
PositiveFloat = Annotated[float, Field(gt=0)]
Row3x4 = tuple[float, float, float, float]


@dataclass(config=_CONFIG, kw_only=True)
class Projection:
    """drillnav.projection/1, as in ``projection.schema.json``: C (mm) to homogeneous pixel (column, row)."""

    projection_matrix: tuple[Row3x4, Row3x4, Row3x4]
    rows: int = Field(ge=1)
    columns: int = Field(ge=1)
    pixel_spacing_mm: tuple[PositiveFloat, PositiveFloat] = Field(description="(row, column) spacing at the detector")
    distortion_sigma_px: float = Field(default=0.0, ge=0, allow_inf_nan=False,
                                       description="an uncorrected image intensifier's distortion prior at the field's corner, px (0: flat panel)")


@_bind
@dataclass(config=_CONFIG, kw_only=True)
class FluoroShot(_Message):
    """A new fluoroscopy image with its projection, on ``fluoro/shot``; the image is a 16-bit PNG of log attenuation."""

    schema_name = "drillnav.FluoroShot"
    stamp_ns: NonNegInt
    # The name becomes a key expression (overlay/<view>): none of zenoh's special characters, no '/'.
    view: str = Field(min_length=1, max_length=64, pattern=r"^[^/*$?#\s]+$", description="the view's name (e.g. p+0s-25); a newer shot of a view replaces the older")
    projection: Projection
    png16_base64: str = Field(min_length=1)
    source_file: str = ""

    def __post_init__(self) -> None:
        # Decoded here, at the boundary, so a shot that exists is one the node can use.
        self.carm_view
        img = self.image_log
        if img.shape != (self.carm_view.rows, self.carm_view.columns):
            raise ValueError(f"image is {img.shape[1]}x{img.shape[0]} px but the projection's detector is {self.carm_view.columns}x{self.carm_view.rows}")

    @cached_property
    def image_log(self) -> NDArray[np.float32]:
        """The image as log attenuation, shape (rows, columns)."""
        try:
            raw = base64.b64decode(self.png16_base64, validate=True)
        except ValueError:
            raise ValueError("png16_base64 is not base64") from None
        img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED) if raw else None
        if img is None or img.dtype != np.uint16 or img.ndim != 2 or img.size == 0:
            raise ValueError("png16_base64 is not a non-empty single-channel 16-bit PNG")
        return img.astype(np.float32) / LOG_SCALE

    @cached_property
    def carm_view(self) -> CArmView:
        return view_from_json(_PROJECTION.dump_python(self.projection, mode="json"), source="projection")  # the camera model's own checks (a singular matrix)

    @classmethod
    def build(cls, image_log: NDArray[np.float32], view: CArmView, *, stamp_ns: int, view_name: str, source_file: str = "") -> FluoroShot:
        png = cv2.imencode(".png", np.clip(np.round(image_log * LOG_SCALE), 0, 65535).astype(np.uint16))[1].tobytes()
        p = view_to_json(view)
        projection = Projection(projection_matrix=tuple(tuple(row) for row in p["projection_matrix"]), rows=p["rows"], columns=p["columns"],
                                pixel_spacing_mm=tuple(p["pixel_spacing_mm"]), distortion_sigma_px=float(view.distortion_sigma_px))
        return cls(stamp_ns=int(stamp_ns), view=view_name, projection=projection, png16_base64=base64.b64encode(png).decode(), source_file=source_file)


_PROJECTION = TypeAdapter(Projection)


@dataclass(config=_CONFIG, kw_only=True)
class MarkerPoseMsg:
    id: int
    position_carm_mm: Vec3
    residual_px: float = Field(ge=0)
    views: NonNegInt
    converged: bool
    # Posed from rings matched only at the looser cost: counts only where the camera sees its tag.
    needs_camera: bool = False


@_bind
@dataclass(config=_CONFIG, kw_only=True)
class FluoroMarkers(_Message):
    """Marker poses in C from the last registration, on ``fluoro/markers``."""

    schema_name = "drillnav.FluoroMarkers"
    stamp_ns: NonNegInt
    registration_id: NonNegInt
    views: tuple[str, ...]
    markers: tuple[MarkerPoseMsg, ...]


@_bind
@dataclass(config=_CONFIG, kw_only=True)
class AuditEntry(_Message):
    """Who changed what through the REST API (also appended to the audit log file), on ``audit``."""

    schema_name = "drillnav.AuditEntry"
    stamp_ns: NonNegInt
    actor: str = Field(description="the client address (and what authenticated it)")
    action: str = Field(min_length=1, description="e.g. calibration_installed, recording_started, shot_requested, auth_failed")
    detail: dict[str, Any] = Field(default_factory=dict)


# -- the drill camera's detections (the display's camera preview draws them) -----------------------------
Corner2 = tuple[float, float]


@dataclass(config=_CONFIG, kw_only=True)
class VideoTag:
    id: int = Field(description="the marker id (markers.json)")
    corners_px: tuple[Corner2, Corner2, Corner2, Corner2] = Field(description="tag corners (column, row) px, OpenCV order TL, TR, BR, BL")


@_bind
@dataclass(config=_CONFIG, kw_only=True)
class VideoMarkers(_Message):
    """The markers the node found in one camera frame, on ``camera/markers`` (after that frame's axis)."""

    schema_name = "drillnav.VideoMarkers"
    stamp_ns: NonNegInt = Field(description="capture stamp of the camera frame")
    image_size: tuple[int, int] = Field(description="frame width, height (px)")
    markers: tuple[VideoTag, ...]
    ignored_ids: tuple[int, ...] = Field((), description="ArUco ids seen that are not in the marker set")
    unplaced_ids: tuple[int, ...] = Field((), description="markers whose tag was decoded but whose corners are no view of its square "
                                          "(a glove's edge taken for the tag's) and could not be placed: not in markers, not used")
    misread_ids: tuple[int, ...] = Field((), description="marker ids decoded on a tag whose code cells, read again, another id of the "
                                         "marker set fits better, or decoded at two places in the frame: that place not used (an id "
                                         "decoded twice is not in markers)")


MESSAGE_CLASSES: tuple[type[_Message], ...] = (DrillAxis, Status, Event, FluoroShot, FluoroMarkers, AuditEntry, VideoMarkers)

JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    **{c.schema_name: c.json_schema() for c in MESSAGE_CLASSES},
    # Written by hand: the node does not publish it (the twin's truth).
    "drillnav.TwinTruth": {"type": "object", "required": ["frame_stamp_ns", "carm_from_drill", "drill_axis_carm"]},
}


def drill_axis_fields(*, point_mm: Any, direction: Any, carm_from_drill: Any = None, carm_from_ct: Any = None) -> dict[str, Any]:
    """numpy geometry as the tuples :class:`DrillAxis` holds (the builders' one conversion)."""
    out: dict[str, Any] = {"point_mm": _vec(point_mm), "direction": _vec(direction)}
    if carm_from_drill is not None:
        out["carm_from_drill"] = _transform(carm_from_drill)
    if carm_from_ct is not None:
        out["carm_from_ct"] = _transform(carm_from_ct)
    return out


# -- generic JSON (tools that print any message) ------------------------------------------------------
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


# -- Foxglove images (protobuf) ---------------------------------------------------------------------
def compressed_image(image: NDArray[np.uint8], *, stamp_ns: int, frame_id: str, fmt: str = "jpeg", quality: int = 90) -> bytes:
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", image, [cv2.IMWRITE_JPEG_QUALITY, quality] if fmt == "jpeg" else [])
    if not ok:
        raise ValueError(f"could not encode the image as {fmt}")
    msg = CompressedImage(frame_id=frame_id, data=buf.tobytes(), format=fmt)
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(int(stamp_ns), 1_000_000_000)
    return msg.SerializeToString()


_MAGIC = {"jpeg": (b"\xff\xd8",), "jpg": (b"\xff\xd8",), "png": (b"\x89PNG\r\n\x1a\n",)}


def parse_compressed_image(data: bytes) -> CompressedImage:
    """The envelope checked without decoding pixels (microseconds: fit for a subscriber's callback).

    ``ValueError`` unless it parses as ``foxglove.CompressedImage`` with a known
    format and data that starts as that format does.
    """
    msg = CompressedImage()
    try:
        msg.ParseFromString(bytes(data))
    except DecodeError as exc:
        raise ValueError(f"CompressedImage: not a protobuf message ({exc})") from None
    if not msg.data:
        raise ValueError("CompressedImage.data: empty")
    magic = _MAGIC.get(msg.format.lower())
    if magic is None:
        raise ValueError(f"CompressedImage.format: '{msg.format[:20]}' is neither jpeg nor png")
    if not msg.data.startswith(magic):
        raise ValueError(f"CompressedImage.data: does not start as {msg.format} data does")
    return msg


def decode_compressed_image(data: bytes) -> tuple[NDArray[np.uint8], int, str]:
    """``(image, stamp_ns, frame_id)``; ``ValueError`` for anything that is not a decodable, non-empty image."""
    msg = parse_compressed_image(data)
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ValueError(f"CompressedImage.data: no decodable {msg.format} data")
    return img, msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos, msg.frame_id


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
