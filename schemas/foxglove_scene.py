"""drillnav state as Foxglove's well-known messages, so Foxglove shows a navigation scene (pure; no I/O).

Frames (``frame_id``), all below the C-arm frame:

- ``carm``: C, the root (isocentre, patient LPS axes);
- ``drill_camera``: D, the drill camera (OpenCV axes), ``carm_from_drill``;
- ``carm/<view>``: the x-ray source S of each C-arm view, ``carm_from_source`` (its CameraCalibration
  projects C onto that view: the same frame id as the view's images, so the Image panel overlays the scene);
- ``ct``: V, the CT (video-CT mode), ``carm_from_ct``;
- ``marker/<id>``: each registered marker's central BB (translation only: the registration gives positions).

Foxglove's 3D panel works in metres, so lengths leave drillnav's millimetres
here and nowhere else. A projection is unchanged by that: Foxglove's ``P`` acts
on points in the camera frame, and ``P @ [R | t/1000] @ (x/1000, 1)`` is the
view's ``P @ [R | t] @ (x, 1)`` over 1000. Quaternions are Foxglove's
``(x, y, z, w)``, from scipy's scalar-last order.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CylinderPrimitive_pb2 import CylinderPrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextAnnotation_pb2 import TextAnnotation
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.carm import CArmView
from drillnav.registration.line import Line3D
from drillnav.registration.transforms import invert

__all__ = [
    "FRAME_CARM",
    "FRAME_DRILL_CAMERA",
    "FRAME_CT",
    "view_frame",
    "marker_frame",
    "frame_transform",
    "view_calibration",
    "drill_camera_calibration",
    "axis_scene",
    "markers_scene",
    "view_annotations",
    "event_log",
]

FRAME_CARM = "carm"
FRAME_DRILL_CAMERA = "drill_camera"  # the frame id of the camera images (service/daemon.py)
FRAME_CT = "ct"
M_PER_MM = 1e-3

_AXIS_COLOUR = (0.1, 0.9, 0.2, 1.0)
_CONE_COLOUR = (1.0, 0.8, 0.1, 0.25)
_MARKER_COLOUR = (0.2, 0.6, 1.0, 1.0)
_LOG_LEVELS = {"debug": Log.DEBUG, "info": Log.INFO, "warning": Log.WARNING, "error": Log.ERROR, "fatal": Log.FATAL}
# The axis as drawn: from this far behind its working point (the drill side) to this far beyond it, mm.
AXIS_BEHIND_MM, AXIS_AHEAD_MM = 150.0, 80.0
STRIP_POINTS = 33  # a line on an intensifier view, drawn bent: points per strip (230 mm of axis, one every 7 mm)


def view_frame(view_name: str) -> str:
    """The frame id of a C-arm view's source, as on its images (``carm/<view>``)."""
    return f"{FRAME_CARM}/{view_name}"


def marker_frame(marker_id: int) -> str:
    return f"marker/{int(marker_id)}"


def _stamp(field, stamp_ns: int) -> None:
    field.seconds, field.nanos = divmod(int(stamp_ns), 1_000_000_000)


def _colour(rgba: Sequence[float]) -> Color:
    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def _check_transform(m: ArrayLike, name: str) -> NDArray[np.float64]:
    t = np.asarray(m, dtype=np.float64)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise ValueError(f"{name} must be a finite 4x4 matrix, got shape {t.shape}")
    return t


def _pose(position_mm: ArrayLike, rotation: NDArray[np.float64]) -> Pose:
    pose = Pose()
    p = np.asarray(position_mm, dtype=np.float64).reshape(3) * M_PER_MM
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in p)
    q = Rotation.from_matrix(rotation).as_quat()  # (x, y, z, w): Foxglove's order
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


def _rotation_taking(axis_from: ArrayLike, axis_to: ArrayLike) -> NDArray[np.float64]:
    """A rotation matrix taking unit vector ``axis_from`` onto ``axis_to`` (the primitive's axis onto the drill's)."""
    rot, _ = Rotation.align_vectors([np.asarray(axis_to, float)], [np.asarray(axis_from, float)])
    return rot.as_matrix()


def frame_transform(parent: str, child: str, parent_from_child: ArrayLike, *, stamp_ns: int) -> FrameTransform:
    """The child frame's pose in the parent: ``parent_from_child`` (4x4, mm) as Foxglove wants it (m, quaternion)."""
    m = _check_transform(parent_from_child, f"{parent}_from_{child}")
    rot = m[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise ValueError(f"{parent}_from_{child} is not a rigid transform (its 3x3 block is not a rotation)")
    msg = FrameTransform(parent_frame_id=parent, child_frame_id=child)
    _stamp(msg.timestamp, stamp_ns)
    t = m[:3, 3] * M_PER_MM
    msg.translation.x, msg.translation.y, msg.translation.z = (float(v) for v in t)
    q = Rotation.from_matrix(rot).as_quat()
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = (float(v) for v in q)
    return msg


def view_calibration(view: CArmView, *, view_name: str, stamp_ns: int) -> tuple[CameraCalibration, NDArray[np.float64]]:
    """A C-arm view as a pinhole camera at its source: (CameraCalibration, ``carm_from_source`` 4x4 mm).

    ``P = K [R | t]`` splits into Foxglove's ``P = [K | 0]`` (no rectification, ``R`` = I) in frame
    ``carm/<view>`` and the transform ``carm_from_source = [R | t]^-1``, so that
    ``P_foxglove @ source_from_carm`` is the view's matrix up to scale.
    """
    k, source_from_carm = view.decompose()
    msg = CameraCalibration(frame_id=view_frame(view_name), width=view.columns, height=view.rows, distortion_model="")
    _stamp(msg.timestamp, stamp_ns)
    msg.K.extend(float(v) for v in k.reshape(-1))
    msg.R.extend(float(v) for v in np.eye(3).reshape(-1))
    msg.P.extend(float(v) for v in np.hstack([k, np.zeros((3, 1))]).reshape(-1))
    return msg, invert(source_from_carm)


def drill_camera_calibration(camera: PinholeCamera, *, stamp_ns: int, frame_id: str = FRAME_DRILL_CAMERA) -> CameraCalibration:
    """The drill camera: OpenCV's 5-term model is ROS's ``plumb_bob`` (k1, k2, p1, p2, k3)."""
    msg = CameraCalibration(frame_id=frame_id, width=camera.width, height=camera.height, distortion_model="plumb_bob")
    _stamp(msg.timestamp, stamp_ns)
    msg.D.extend(float(v) for v in camera.distortion[:5])
    msg.K.extend(float(v) for v in camera.camera_matrix.reshape(-1))
    msg.R.extend(float(v) for v in np.eye(3).reshape(-1))
    msg.P.extend(float(v) for v in np.hstack([camera.camera_matrix, np.zeros((3, 1))]).reshape(-1))
    return msg


def axis_scene(axis: Line3D, *, angle_deg: float, position_mm: float, stamp_ns: int, frame_id: str = FRAME_CARM) -> SceneUpdate:
    """The drill axis (an arrow into the patient) and its error cone, in ``frame_id``.

    The axis point is its working point (near the markers). The cone's apex is where the arrow starts
    (the drill side); its half-angle is the predicted angular error and it widens by the predicted
    position error, so the true axis lies inside it with the prediction's confidence.
    """
    if not (np.isfinite(angle_deg) and np.isfinite(position_mm)) or angle_deg < 0 or position_mm < 0:
        raise ValueError(f"predicted errors must be finite and >= 0, got {angle_deg} deg, {position_mm} mm")
    start = axis.at(-AXIS_BEHIND_MM)
    length = AXIS_BEHIND_MM + AXIS_AHEAD_MM
    entity = SceneEntity(id="drill_axis", frame_id=frame_id)
    _stamp(entity.timestamp, stamp_ns)
    along_x = _rotation_taking([1.0, 0.0, 0.0], axis.direction)  # Foxglove arrows point along their pose's +x
    entity.arrows.append(ArrowPrimitive(pose=_pose(start, along_x), shaft_length=length * 0.92 * M_PER_MM, shaft_diameter=2.0 * M_PER_MM,
                                        head_length=length * 0.08 * M_PER_MM, head_diameter=6.0 * M_PER_MM, color=_colour(_AXIS_COLOUR)))
    along_z = _rotation_taking([0.0, 0.0, 1.0], axis.direction)  # a cylinder's axis is its pose's +z, centred on the pose
    radius = length * np.tan(np.radians(angle_deg)) + position_mm
    entity.cylinders.append(CylinderPrimitive(pose=_pose(axis.at(-AXIS_BEHIND_MM + length / 2), along_z), bottom_scale=0.0, top_scale=1.0,
                                              color=_colour(_CONE_COLOUR)))
    c = entity.cylinders[0]
    c.size.x = c.size.y = 2 * radius * M_PER_MM
    c.size.z = length * M_PER_MM
    return SceneUpdate(entities=[entity])


def markers_scene(positions_carm_mm: Mapping[int, ArrayLike], *, stamp_ns: int, diameter_mm: float = 4.0) -> SceneUpdate:
    """Each registered marker's central BB as a sphere in C."""
    entity = SceneEntity(id="markers", frame_id=FRAME_CARM)
    _stamp(entity.timestamp, stamp_ns)
    for marker_id, p in sorted(positions_carm_mm.items()):
        s = SpherePrimitive(pose=_pose(p, np.eye(3)), color=_colour(_MARKER_COLOUR))
        s.size.x = s.size.y = s.size.z = diameter_mm * M_PER_MM
        entity.spheres.append(s)
        entity.metadata.add(key=str(marker_id), value=",".join(f"{float(v):.3f}" for v in np.asarray(p, float)))
    return SceneUpdate(entities=[entity])


def _points(pixels: NDArray[np.float64], kind: int, rgba: Sequence[float], stamp_ns: int, thickness: float = 2.0) -> PointsAnnotation:
    ann = PointsAnnotation(type=kind, outline_color=_colour(rgba), thickness=thickness)
    _stamp(ann.timestamp, stamp_ns)
    ann.points.extend(Point2(x=float(u), y=float(v)) for u, v in pixels)
    return ann


def view_annotations(view: CArmView, *, stamp_ns: int, axis_carm: Line3D | None = None, cone_half_angle_deg: float = 0.0,
                     markers_carm_mm: Mapping[int, ArrayLike] | None = None, distortion_px: ArrayLike | None = None) -> ImageAnnotations:
    """What the overlay used to burn into a view, as annotations: the axis (and its cone's edges) and the markers, projected by P.

    ``distortion_px`` (2,): the view's image-intensifier distortion as the registration estimated it (pincushion and
    S shift at the field's corner, px; ``DrillAxis.detector_distortion_px``): everything is placed where that
    intensifier shows it, the lines as strips of :data:`STRIP_POINTS` points (the image of a line is then bent).
    """
    k = None if distortion_px is None else np.asarray(distortion_px, dtype=np.float64).reshape(2)

    def image(points_carm_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        return view.distorted_px(view.project(points_carm_mm), k)

    n = 2 if k is None else STRIP_POINTS
    out = ImageAnnotations()
    if axis_carm is not None:
        s = np.linspace(-AXIS_BEHIND_MM, AXIS_AHEAD_MM, n)
        out.points.append(_points(image(axis_carm.at(s)), PointsAnnotation.LINE_STRIP, _AXIS_COLOUR, stamp_ns))
        if cone_half_angle_deg > 0:
            apex, far = axis_carm.at(-AXIS_BEHIND_MM).reshape(3), AXIS_BEHIND_MM + AXIS_AHEAD_MM
            # The cone's edges in this image: rotate the axis by the half-angle about the view's depth direction.
            depth = axis_carm.point_mm - view.source_position_mm
            normal = np.cross(axis_carm.direction, depth)
            normal /= np.linalg.norm(normal)
            for sign in (-1.0, 1.0):
                edge = Rotation.from_rotvec(sign * np.radians(cone_half_angle_deg) * normal).apply(axis_carm.direction)
                out.points.append(_points(image(apex + np.linspace(0.0, far, n)[:, None] * edge), PointsAnnotation.LINE_STRIP, _CONE_COLOUR[:3] + (1.0,),
                                          stamp_ns, 1.0))
    for marker_id, p in sorted((markers_carm_mm or {}).items()):
        uv = image(np.asarray(p, float).reshape(1, 3))[0]
        circle = _points(uv.reshape(1, 2), PointsAnnotation.POINTS, _MARKER_COLOUR, stamp_ns, 8.0)
        out.points.append(circle)
        text = TextAnnotation(text=f"m{marker_id}", font_size=14.0, text_color=_colour(_MARKER_COLOUR), background_color=_colour((0, 0, 0, 0.5)))
        _stamp(text.timestamp, stamp_ns)
        text.position.x, text.position.y = float(uv[0]) + 8.0, float(uv[1]) - 8.0
        out.texts.append(text)
    return out


def event_log(level: str, message: str, *, stamp_ns: int, name: str = "drillnav") -> Log:
    if level not in _LOG_LEVELS:
        raise ValueError(f"unknown event level '{level}' (expected one of {', '.join(_LOG_LEVELS)})")
    msg = Log(level=_LOG_LEVELS[level], message=message, name=name)
    _stamp(msg.timestamp, stamp_ns)
    return msg
