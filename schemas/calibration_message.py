"""``drillnav.Calibration``: the calibrations in use, as one message (topic ``calibration``, key ``<prefix>/calibration/active``).

The daemon publishes it at start and on each install; the recorder writes the
latest one at the start of every file, so a recording (or one rotated file of
it) can be replayed without the calibration files. ``camera`` and ``drill``
hold exactly the JSON of ``camera.json`` and ``drill.json`` (their schemas in
``schemas/*.schema.json``); ``markers``, when present, the markers file's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drillnav.registration.axis_uncertainty import AxisUncertainty
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.line import Line3D
from drillnav.registration.markers import MarkerSet

from .calibration import (camera_calibration_from_json, camera_calibration_to_json, drill_calibration_from_json, drill_calibration_to_json,
                          drill_uncertainty_from_json)
from .markers import marker_set_from_json, marker_set_to_json
from .messages import decode_json, encode_json

__all__ = ["CALIBRATION_SCHEMA", "ActiveCalibration", "active_calibration_message", "calibration_message", "calibration_message_from_models", "decode_calibration_message"]

CALIBRATION_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["stamp_ns", "camera", "drill"],
    "properties": {
        "stamp_ns": {"type": "integer"},
        "camera": {"type": "object", "description": "camera.json as installed (drillnav.camera/1)"},
        "drill": {"type": "object", "description": "drill.json as installed (drillnav.drill/1)"},
        "markers": {"type": "object", "description": "the marker set in use (drillnav markers file), when known"},
        "source": {"type": "string", "description": "where the calibrations came from: files, the twin, an install"},
    },
}


@dataclass(frozen=True, kw_only=True)
class ActiveCalibration:
    """The calibrations a ``drillnav.Calibration`` message carries, built and validated."""

    camera: PinholeCamera
    axis_drill: Line3D          # the drill axis in the drill-camera frame D, mm
    axis_uncertainty: AxisUncertainty  # the drill document's stated uncertainty of it (its residuals; defaults where 0)
    marker_set: MarkerSet | None
    stamp_ns: int
    source: str


def calibration_message(*, camera_doc: dict[str, Any], drill_doc: dict[str, Any], stamp_ns: int, marker_set: MarkerSet | None = None, source: str = "") -> bytes:
    """Encode the message; the documents are validated first, so a bad one never reaches a recording."""
    camera_calibration_from_json(camera_doc, source="calibration message: camera")
    drill_calibration_from_json(drill_doc, source="calibration message: drill")
    doc: dict[str, Any] = {"stamp_ns": int(stamp_ns), "camera": camera_doc, "drill": drill_doc, "source": source}
    if marker_set is not None:
        doc["markers"] = marker_set_to_json(marker_set)
    return encode_json(doc)


def calibration_message_from_models(*, camera: PinholeCamera, axis_drill: Line3D, stamp_ns: int, marker_set: MarkerSet | None = None, source: str,
                                    axis_uncertainty: AxisUncertainty | None = None) -> bytes:
    """For calibrations held as objects (the twin's): the camera's residuals are unknown here and written as 0; the
    drill's are its ``axis_uncertainty`` (None: unknown, 0, which a reader takes as the defaults)."""
    camera_doc = camera_calibration_to_json(camera, rms_px=0.0, per_view_errors_px=[], label=source)
    u = axis_uncertainty
    drill_doc = drill_calibration_to_json(axis_drill, method=source, residual_mm=u.sigma_mm if u else 0.0, residual_deg=u.rms_tilt_deg if u else 0.0, label=source)
    return calibration_message(camera_doc=camera_doc, drill_doc=drill_doc, stamp_ns=stamp_ns, marker_set=marker_set, source=source)


def active_calibration_message(*, camera: PinholeCamera, axis_drill: Line3D, stamp_ns: int, marker_set: MarkerSet | None = None,
                               camera_file: str | Path | None = None, drill_file: str | Path | None = None,
                               axis_uncertainty: AxisUncertainty | None = None) -> bytes:
    """What the daemon publishes at start and after each install: each calibration file's own JSON where the
    calibration came from a file that exists, else (the twin's) built from the object in use (the drill's
    residuals its ``axis_uncertainty``)."""
    camera_doc = _file_doc(camera_file) or camera_calibration_to_json(camera, rms_px=0.0, per_view_errors_px=[], label="in use (no file)")
    u = axis_uncertainty
    drill_doc = _file_doc(drill_file) or drill_calibration_to_json(axis_drill, method="in use (no file)", residual_mm=u.sigma_mm if u else 0.0,
                                                                   residual_deg=u.rms_tilt_deg if u else 0.0, label="in use (no file)")
    source = ", ".join(str(f) for f in (camera_file, drill_file) if f is not None and Path(f).is_file()) or "in use (no files)"
    return calibration_message(camera_doc=camera_doc, drill_doc=drill_doc, stamp_ns=stamp_ns, marker_set=marker_set, source=source)


def _file_doc(path: str | Path | None) -> dict[str, Any] | None:
    if path is None or not Path(path).is_file():
        return None
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None


def decode_calibration_message(data: bytes) -> ActiveCalibration:
    """``ValueError`` naming the missing or bad part otherwise."""
    doc = decode_json(data)
    for k in ("stamp_ns", "camera", "drill"):
        if k not in doc:
            raise ValueError(f"malformed Calibration message: missing '{k}'")
    markers = marker_set_from_json(doc["markers"]) if doc.get("markers") is not None else None
    return ActiveCalibration(camera=camera_calibration_from_json(doc["camera"], source="Calibration message: camera"),
                             axis_drill=drill_calibration_from_json(doc["drill"], source="Calibration message: drill"),
                             axis_uncertainty=drill_uncertainty_from_json(doc["drill"], source="Calibration message: drill"),
                             marker_set=markers, stamp_ns=int(doc["stamp_ns"]), source=str(doc.get("source", "")))
