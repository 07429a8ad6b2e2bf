"""Key expressions of every drillnav stream, and the schema each carries.

All keys live under a prefix (default ``drillnav``). Camera and overlay images
use Foxglove's well-known ``foxglove.CompressedImage`` (protobuf) so a recording
opens in Foxglove as it is; drillnav's own messages are JSON with a JSON Schema.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

__all__ = ["Delivery", "Encoding", "Topic", "TOPICS", "key", "topic_for_key", "ALIASES"]


class Encoding(str, Enum):
    PROTOBUF = "protobuf"
    JSON = "json"


class Delivery(str, Enum):
    """What a stream promises when a link is busy (``service/bus.py`` maps each to zenoh's QoS).

    GUIDANCE: small messages a display or a surgeon acts on, on a priority of their own ahead of images; a client that
        stops reading loses its samples (gaps in ``sequence``) rather than hold the publisher.
    EVERY: every sample arrives, the publisher waiting for a busy link (megabytes, once per shot or per install).
    LATEST: a newer sample supersedes an older one, which may be dropped when the link is busy (per-frame images).
    """

    GUIDANCE = "guidance"
    EVERY = "every"
    LATEST = "latest"


@dataclass(frozen=True)
class Topic:
    suffix: str          # after the prefix; may contain one '*' for a view name
    schema_name: str
    encoding: Encoding
    description: str
    delivery: Delivery


TOPICS: dict[str, Topic] = {
    "camera_image": Topic("camera/image", "foxglove.CompressedImage", Encoding.PROTOBUF, "drill-camera frames, JPEG, stamped at capture", Delivery.LATEST),
    "camera_markers": Topic("camera/markers", "drillnav.VideoMarkers", Encoding.JSON, "video marker detections per frame (ids, corners, X_D)", Delivery.LATEST),
    "fluoro_shot": Topic("fluoro/shot", "drillnav.FluoroShot", Encoding.JSON, "a new fluoroscopy image with its projection matrix (16-bit PNG of log attenuation)", Delivery.EVERY),
    "fluoro_image": Topic("fluoro/*/image", "foxglove.CompressedImage", Encoding.PROTOBUF, "fluoroscopy views for display, PNG", Delivery.EVERY),
    "fluoro_markers": Topic("fluoro/markers", "drillnav.FluoroMarkers", Encoding.JSON, "marker poses in C from the last registration", Delivery.GUIDANCE),
    "axis_carm": Topic("axis/carm", "drillnav.DrillAxis", Encoding.JSON, "the drill axis in frame C with its predicted error, one per camera frame", Delivery.GUIDANCE),
    "axis_ct": Topic("axis/ct", "drillnav.DrillAxis", Encoding.JSON, "video-CT mode: the drill axis in the CT frame V with conformance to the nearest planned trajectory, one per camera frame once the CT is registered", Delivery.GUIDANCE),
    "status": Topic("registration/status", "drillnav.Status", Encoding.JSON, "registration state, counters, dropped frames, about 1 Hz", Delivery.GUIDANCE),
    "events": Topic("registration/events", "drillnav.Event", Encoding.JSON, "re-registrations, refusals and errors, as they happen", Delivery.GUIDANCE),
    "overlay": Topic("overlay/*", "foxglove.CompressedImage", Encoding.PROTOBUF, "each view with the axis, its cone and the detections, PNG", Delivery.LATEST),
    "calibration": Topic("calibration/active", "drillnav.Calibration", Encoding.JSON, "the calibrations in use (camera.json, drill.json, markers), at start and on each install; first in every recorded file", Delivery.EVERY),
    # Foxglove's own schemas (service/scene_publisher.py, docs/foxglove.md): the navigation scene in 3D and on each image.
    "scene_tf": Topic("scene/tf", "foxglove.FrameTransform", Encoding.PROTOBUF, "frames carm, drill_camera, carm/<view>, ct, marker/<id> (m, quaternion)", Delivery.LATEST),
    "scene_entities": Topic("scene/entities", "foxglove.SceneUpdate", Encoding.PROTOBUF, "the drill axis (arrow), its error cone and the registered markers", Delivery.LATEST),
    "scene_calibration": Topic("scene/calibration/*", "foxglove.CameraCalibration", Encoding.PROTOBUF, "a pinhole model per C-arm view (from its P) and for drill_camera", Delivery.LATEST),
    "scene_annotations": Topic("scene/annotations/*", "foxglove.ImageAnnotations", Encoding.PROTOBUF, "the axis, its cone and the markers projected onto each C-arm view", Delivery.LATEST),
    "scene_log": Topic("scene/log", "foxglove.Log", Encoding.PROTOBUF, "registration events as log lines", Delivery.GUIDANCE),
    "audit": Topic("audit", "drillnav.AuditEntry", Encoding.JSON, "who changed what through the REST API (calibration installed, recording started, shot requested, failed authentications)", Delivery.GUIDANCE),
    "twin_truth": Topic("twin/truth", "drillnav.TwinTruth", Encoding.JSON, "digital twin only: the true carm_from_drill and drill axis of each camera frame", Delivery.EVERY),
}

ALIASES = {"drill-axis": "axis_carm", "drill-axis-ct": "axis_ct", "status": "status", "events": "events", "markers": "camera_markers", "shots": "fluoro_shot"}


def key(prefix: str, name: str, view: str | None = None) -> str:
    suffix = TOPICS[name].suffix
    if "*" in suffix:
        if not view:
            raise ValueError(f"topic {name} needs a view name")
        suffix = suffix.replace("*", view)
    return f"{prefix}/{suffix}"


def topic_for_key(prefix: str, key_expr: str) -> Topic | None:
    """The topic a concrete key belongs to (None for keys drillnav does not publish)."""
    if not key_expr.startswith(prefix + "/"):
        return None
    parts = key_expr[len(prefix) + 1 :].split("/")
    for t in TOPICS.values():
        pat = t.suffix.split("/")
        if len(pat) == len(parts) and all(p == "*" or p == q for p, q in zip(pat, parts)):
            return t
    return None
