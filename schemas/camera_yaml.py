"""camera.json <-> OpenCV's calibration YAML and ROS's camera_info YAML, so a calibration from another tool works.

- **OpenCV** (``cv2.FileStorage``, as OpenCV's ``calibration`` sample writes it): ``image_width``,
  ``image_height``, ``camera_matrix`` (3x3 ``opencv-matrix``), ``distortion_coefficients`` (5x1),
  ``avg_reprojection_error``, ``per_view_reprojection_errors``.
- **ROS** (``camera_calibration_parsers``, what ``cameracalibrator`` saves and ``camera_info_manager``
  loads): ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix``, ``distortion_model``
  (``plumb_bob``: OpenCV's k1, k2, p1, p2, k3), ``distortion_coefficients``, ``rectification_matrix``
  (identity: a monocular camera), ``projection_matrix`` (``[K | 0]``).

camera.json's own fields with no place in the other format (label, date, RMS,
per-view errors, the stated uncertainty of the intrinsics) travel under a ``drillnav`` key (ROS's parser reads only the
keys it knows), so camera.json -> YAML -> camera.json is exact. Every document
read is checked against camera.json's schema and the camera model before it is
returned: a bad file fails here with the field named.
"""

from __future__ import annotations

import enum
import json
from typing import Any

import cv2
import numpy as np
import yaml

from .calibration import camera_calibration_from_json

__all__ = ["CalibrationFormat", "detect_format", "to_opencv_yaml", "from_opencv_yaml", "to_ros_yaml", "from_ros_yaml", "convert"]

_EXTRAS = ("schema", "label", "date", "rms_px", "per_view_errors_px", "intrinsics_sigma")


class CalibrationFormat(str, enum.Enum):
    JSON = "json"      # drillnav's camera.json
    OPENCV = "opencv"  # cv2.FileStorage YAML
    ROS = "ros"        # camera_info YAML


def _checked(doc: dict[str, Any], source: str) -> dict[str, Any]:
    camera_calibration_from_json(doc, source=source)  # raises ValueError naming the field
    return doc


def detect_format(text: str) -> CalibrationFormat:
    """Which of the three a file's text is (OpenCV's YAML announces itself with ``%YAML:1.0``)."""
    stripped = text.lstrip()
    if stripped.startswith("{"):
        return CalibrationFormat.JSON
    if stripped.startswith("%YAML:1.") or "!!opencv-matrix" in text:
        return CalibrationFormat.OPENCV
    return CalibrationFormat.ROS


# -- OpenCV -------------------------------------------------------------------------------
def to_opencv_yaml(doc: dict[str, Any]) -> str:
    _checked(doc, "camera.json")
    fs = cv2.FileStorage("camera.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML)
    fs.write("image_width", int(doc["image_size"][0]))
    fs.write("image_height", int(doc["image_size"][1]))
    fs.write("camera_matrix", np.asarray(doc["camera_matrix"], dtype=np.float64))
    fs.write("distortion_coefficients", np.asarray(doc["distortion"], dtype=np.float64).reshape(5, 1))
    if "rms_px" in doc:
        fs.write("avg_reprojection_error", float(doc["rms_px"]))
    if "per_view_errors_px" in doc:
        fs.write("per_view_reprojection_errors", np.asarray(doc["per_view_errors_px"], dtype=np.float64).reshape(-1, 1))
    for k in ("schema", "label", "date"):
        if k in doc:
            fs.write(f"drillnav_{k}", str(doc[k]))
    if "intrinsics_sigma" in doc:  # a mapping: as its JSON text
        fs.write("drillnav_intrinsics_sigma", json.dumps(doc["intrinsics_sigma"]))
    return fs.releaseAndGetString()


def from_opencv_yaml(text: str, *, source: str = "OpenCV YAML") -> dict[str, Any]:
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except cv2.error as exc:
        raise ValueError(f"{source}: not readable by OpenCV's FileStorage ({exc.err})") from None
    try:
        def node(name: str):
            n = fs.getNode(name)
            return None if n.empty() or n.isNone() else n

        for required in ("image_width", "image_height", "camera_matrix", "distortion_coefficients"):
            if node(required) is None:
                raise ValueError(f"{source}: missing '{required}'")
        k, d = node("camera_matrix").mat(), node("distortion_coefficients").mat()
        if k is None or k.shape != (3, 3):
            raise ValueError(f"{source}: camera_matrix must be a 3x3 matrix")
        if d is None or d.size != 5:
            raise ValueError(f"{source}: distortion_coefficients must hold 5 terms (k1, k2, p1, p2, k3), got {0 if d is None else d.size}")
        doc: dict[str, Any] = {}
        for k_ in ("schema", "label", "date"):
            if node(f"drillnav_{k_}") is not None:
                doc[k_] = node(f"drillnav_{k_}").string()
        doc["image_size"] = [int(node("image_width").real()), int(node("image_height").real())]
        doc["camera_matrix"] = k.astype(np.float64).tolist()
        doc["distortion"] = d.astype(np.float64).reshape(-1).tolist()
        if node("avg_reprojection_error") is not None:
            doc["rms_px"] = float(node("avg_reprojection_error").real())
        if node("per_view_reprojection_errors") is not None:
            doc["per_view_errors_px"] = node("per_view_reprojection_errors").mat().reshape(-1).astype(np.float64).tolist()
        if node("drillnav_intrinsics_sigma") is not None:
            try:
                doc["intrinsics_sigma"] = json.loads(node("drillnav_intrinsics_sigma").string())
            except json.JSONDecodeError as exc:
                raise ValueError(f"{source}: drillnav_intrinsics_sigma is not the JSON of camera.json's intrinsics_sigma ({exc})") from None
    finally:
        fs.release()
    return _ordered(_checked(doc, source))


# -- ROS ----------------------------------------------------------------------------------
def _ros_matrix(values: np.ndarray) -> dict[str, Any]:
    m = np.atleast_2d(np.asarray(values, dtype=np.float64))
    return {"rows": m.shape[0], "cols": m.shape[1], "data": [float(v) for v in m.reshape(-1)]}


def to_ros_yaml(doc: dict[str, Any], *, camera_name: str = "drill_camera") -> str:
    _checked(doc, "camera.json")
    k = np.asarray(doc["camera_matrix"], dtype=np.float64)
    out = {
        "image_width": int(doc["image_size"][0]),
        "image_height": int(doc["image_size"][1]),
        "camera_name": camera_name,
        "camera_matrix": _ros_matrix(k),
        "distortion_model": "plumb_bob",
        "distortion_coefficients": _ros_matrix(np.asarray(doc["distortion"], dtype=np.float64).reshape(1, 5)),
        "rectification_matrix": _ros_matrix(np.eye(3)),
        "projection_matrix": _ros_matrix(np.hstack([k, np.zeros((3, 1))])),
        "drillnav": {k_: doc[k_] for k_ in _EXTRAS if k_ in doc},
    }
    return yaml.safe_dump(out, sort_keys=False, default_flow_style=None)


def _ros_data(root: dict, name: str, shape: tuple[int, ...], source: str) -> np.ndarray:
    m = root.get(name)
    if not isinstance(m, dict) or "data" not in m:
        raise ValueError(f"{source}: missing '{name}' (a mapping with rows, cols, data)")
    try:
        data = np.asarray(m["data"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{source}: {name}.data is not a list of numbers") from None
    if data.size != int(np.prod(shape)):
        raise ValueError(f"{source}: {name} must hold {int(np.prod(shape))} numbers, got {data.size}")
    return data.reshape(shape)


def from_ros_yaml(text: str, *, source: str = "ROS camera_info YAML") -> dict[str, Any]:
    try:
        root = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{source}: not valid YAML ({exc})") from None
    if not isinstance(root, dict):
        raise ValueError(f"{source}: expected a YAML mapping at the top level")
    for required in ("image_width", "image_height"):
        if not isinstance(root.get(required), int):
            raise ValueError(f"{source}: missing or non-integer '{required}'")
    model = root.get("distortion_model", "plumb_bob")
    if model != "plumb_bob":
        raise ValueError(f"{source}: distortion_model '{model}' is not supported (camera.json holds OpenCV's 5-term plumb_bob model)")
    k = _ros_data(root, "camera_matrix", (3, 3), source)
    d = _ros_data(root, "distortion_coefficients", (5,), source)
    if "rectification_matrix" in root and not np.allclose(_ros_data(root, "rectification_matrix", (3, 3), source), np.eye(3)):
        raise ValueError(f"{source}: rectification_matrix is not the identity (a stereo-rectified camera); drillnav needs the monocular calibration")
    extras = root.get("drillnav") or {}
    if not isinstance(extras, dict):
        raise ValueError(f"{source}: 'drillnav' must be a mapping")
    doc = {k_: extras[k_] for k_ in _EXTRAS if k_ in extras}
    doc.update({"image_size": [root["image_width"], root["image_height"]], "camera_matrix": k.tolist(), "distortion": d.tolist()})
    return _ordered(_checked(doc, source))


def _ordered(doc: dict[str, Any]) -> dict[str, Any]:
    """camera.json's own key order (schemas/calibration.py), so a converted file reads like a written one."""
    order = ("schema", "label", "date", "image_size", "camera_matrix", "distortion", "rms_px", "per_view_errors_px", "intrinsics_sigma")
    return {k: doc[k] for k in order if k in doc}


def convert(text: str, to: CalibrationFormat, *, source: str = "calibration", camera_name: str = "drill_camera") -> str:
    """Any of the three formats to ``to`` (camera.json is written as indented JSON)."""
    fmt = detect_format(text)
    if fmt is CalibrationFormat.JSON:
        try:
            doc = _checked(json.loads(text), source)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{source}: not valid JSON ({exc})") from None
    elif fmt is CalibrationFormat.OPENCV:
        doc = from_opencv_yaml(text, source=source)
    else:
        doc = from_ros_yaml(text, source=source)
    if to is CalibrationFormat.JSON:
        return json.dumps(doc, indent=1)
    if to is CalibrationFormat.OPENCV:
        return to_opencv_yaml(doc)
    return to_ros_yaml(doc, camera_name=camera_name)
