"""camera.json and drill.json: the drill camera's intrinsics and the drill axis in its frame."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np

from drillnav.registration.axis_uncertainty import AxisUncertainty
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.camera_uncertainty import IntrinsicsUncertainty
from drillnav.registration.line import Line3D

from .geometry_json import axis_from_json, axis_to_json

CAMERA_SCHEMA = json.loads(Path(__file__).with_name("camera_calibration.schema.json").read_text())
DRILL_SCHEMA = json.loads(Path(__file__).with_name("drill_calibration.schema.json").read_text())

__all__ = [
    "camera_calibration_to_json",
    "camera_calibration_from_json",
    "write_camera_calibration",
    "read_camera_calibration",
    "write_drill_calibration",
    "read_drill_calibration",
    "read_drill_uncertainty",
    "drill_uncertainty_from_json",
    "drill_calibration_to_json",
    "drill_calibration_from_json",
]


def camera_calibration_to_json(camera: PinholeCamera, *, rms_px: float, per_view_errors_px: list[float], label: str) -> dict[str, Any]:
    return {
        "schema": "drillnav.camera/1",
        "label": label,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "image_size": [camera.width, camera.height],
        "camera_matrix": [[float(v) for v in row] for row in camera.camera_matrix],
        "distortion": [float(v) for v in camera.distortion[:5]],
        "rms_px": float(rms_px),
        "per_view_errors_px": [float(v) for v in per_view_errors_px],
        **({} if camera.uncertainty is None else {"intrinsics_sigma": _sigma_json(camera.uncertainty)}),
    }


def _sigma_json(u: IntrinsicsUncertainty) -> dict[str, Any]:
    return {"focal_rel": u.focal_rel, "principal_px": u.principal_px, **({} if u.distortion is None else {"distortion": list(u.distortion)})}


def camera_calibration_from_json(doc: Any, *, source: str = "camera calibration") -> PinholeCamera:
    """Build the camera; ``ValueError`` naming the missing or bad field otherwise."""
    _validate(doc, CAMERA_SCHEMA, source)
    try:
        w, h = (int(v) for v in doc["image_size"])
        k = np.asarray(doc["camera_matrix"], dtype=np.float64)
        d = np.asarray(doc["distortion"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: malformed image_size/camera_matrix/distortion ({exc})") from None
    sigma = doc.get("intrinsics_sigma")
    try:
        stated = None if sigma is None else IntrinsicsUncertainty(focal_rel=sigma["focal_rel"], principal_px=sigma["principal_px"],
                                                                  distortion=tuple(sigma["distortion"]) if "distortion" in sigma else None)
        return PinholeCamera(width=w, height=h, camera_matrix=k, distortion=d, uncertainty=stated)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None


def _validate(doc: Any, schema: dict, source: str) -> None:
    try:
        jsonschema.validate(doc, schema)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise ValueError(f"{source}: invalid at {where}: {exc.message}") from None


def _read_json(path: str | Path) -> Any:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such file")
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not valid JSON ({exc})") from None


def write_camera_calibration(path: str | Path, camera: PinholeCamera, *, rms_px: float, per_view_errors_px: list[float], label: str) -> None:
    Path(path).write_text(json.dumps(camera_calibration_to_json(camera, rms_px=rms_px, per_view_errors_px=per_view_errors_px, label=label), indent=1))


def read_camera_calibration(path: str | Path) -> PinholeCamera:
    return camera_calibration_from_json(_read_json(path), source=str(path))


def drill_calibration_to_json(axis_camera: Line3D, *, method: str, residual_mm: float, residual_deg: float, label: str) -> dict[str, Any]:
    return {
        "schema": "drillnav.drill/1",
        "label": label,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "frame": "drill camera D (OpenCV), mm; direction from the drill into the patient",
        "axis_camera": axis_to_json(axis_camera),
        "method": method,
        "residual_mm": float(residual_mm),
        "residual_deg": float(residual_deg),
    }


def drill_calibration_from_json(doc: Any, *, source: str = "drill calibration") -> Line3D:
    """The drill axis in the camera frame D; ``ValueError`` naming the missing or bad field otherwise."""
    _validate(doc, DRILL_SCHEMA, source)
    return axis_from_json(doc["axis_camera"], name=f"{source}: axis_camera")


def drill_uncertainty_from_json(doc: Any, *, source: str = "drill calibration") -> AxisUncertainty:
    """The axis's calibration uncertainty the document states (``residual_mm``, ``residual_deg``; absent or 0: the defaults)."""
    _validate(doc, DRILL_SCHEMA, source)
    return AxisUncertainty.from_residuals(residual_mm=doc.get("residual_mm"), residual_deg=doc.get("residual_deg"))


def write_drill_calibration(path: str | Path, axis_camera: Line3D, *, method: str, residual_mm: float, residual_deg: float, label: str) -> None:
    doc = drill_calibration_to_json(axis_camera, method=method, residual_mm=residual_mm, residual_deg=residual_deg, label=label)
    Path(path).write_text(json.dumps(doc, indent=1))


def read_drill_calibration(path: str | Path) -> Line3D:
    return drill_calibration_from_json(_read_json(path), source=str(path))


def read_drill_uncertainty(path: str | Path) -> AxisUncertainty:
    return drill_uncertainty_from_json(_read_json(path), source=str(path))
