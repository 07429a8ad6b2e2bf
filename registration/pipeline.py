"""The live pipeline, composed once: camera frame -> video markers -> video-to-fluoro registration -> drill axis in C.

Both the registration node (every camera frame) and ``drillnav register`` (one
frame) call :func:`track_frame`, so a calibration reaches every step the same
way. The calibration a frame is tracked with is one immutable
:class:`LiveCalibration` (camera, drill axis and the marker locator built from
that camera): a service swaps it as a single reference, so no frame ever meets
a new camera with an old locator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .camera import PinholeCamera
from .errors import MarkersNotFound
from .line import Line3D
from .marker_pose import MarkerPose
from .markers import MarkerSet
from .video_fluoro import RELIABLE_ANGLE_DEG, RELIABLE_POSITION_MM, DrillRegistration, PredictedError, predicted_axis_error, register_video_to_fluoro
from .video_markers import VideoDetections, VideoMarkerLocator

__all__ = ["LiveCalibration", "FrameAxis", "ReliableLimits", "track_frame"]


@dataclass(frozen=True, kw_only=True)
class LiveCalibration:
    """Camera intrinsics, the drill axis in the camera frame D, and the locator built from that camera."""

    camera: PinholeCamera
    axis_drill: Line3D
    locator: VideoMarkerLocator

    @classmethod
    def build(cls, *, camera: PinholeCamera, axis_drill: Line3D, marker_set: MarkerSet) -> LiveCalibration:
        locator = VideoMarkerLocator(camera=camera, marker_set=marker_set)  # each marker's own dictionary, tag size and offset
        return cls(camera=camera, axis_drill=axis_drill, locator=locator)


@dataclass(frozen=True, kw_only=True)
class ReliableLimits:
    """Limits on the predicted error's 90 % bounds (mm at the working point, degrees) beyond which an axis is unreliable."""

    position_mm: float = RELIABLE_POSITION_MM
    angle_deg: float = RELIABLE_ANGLE_DEG


@dataclass(frozen=True, kw_only=True)
class FrameAxis:
    """One frame's result.

    ``axis_carm`` passes through the working point: the axis point nearest the
    centroid of the markers used (frame C, mm). ``axis_full_carm`` is the same
    line with the drill calibration's own point (for drawing).
    """

    video: VideoDetections
    registration: DrillRegistration
    axis_carm: Line3D
    axis_full_carm: Line3D
    predicted_error: PredictedError

    @property
    def working_point_carm_mm(self) -> NDArray[np.float64]:
        return self.axis_carm.point_mm


def track_frame(image: NDArray[np.uint8], *, calibration: LiveCalibration, poses: tuple[MarkerPose, ...], marker_set: MarkerSet,
                limits: ReliableLimits = ReliableLimits()) -> FrameAxis:
    """The drill axis in C from one camera frame and the fluoroscopy marker poses.

    ``limits``: the 90 % bounds above which the axis is flagged unreliable (``predicted_error.reliable``).

    Raises ``MarkersNotFound`` when no marker of the set is seen, and the
    registration's own errors (too few shared markers) as they are.
    """
    video = calibration.locator.locate(image)
    if not video.markers:
        raise MarkersNotFound(f"no marker of the marker set ({len(marker_set.ids)} ids) is visible in the camera frame")
    reg = register_video_to_fluoro(video, poses, marker_set, calibration.camera)
    axis = calibration.axis_drill.transformed(reg.carm_from_drill)
    centroid = np.mean([p.position_carm_mm for p in poses if p.marker_id in reg.used_ids], axis=0)
    work = axis.closest_point(centroid)
    pe = predicted_axis_error(video, poses, reg, calibration.axis_drill, working_point_carm_mm=work,
                              position_limit_mm=limits.position_mm, angle_limit_deg=limits.angle_deg)  # vectorised: ~1 ms
    return FrameAxis(video=video, registration=reg, axis_carm=Line3D(point_mm=work, direction=axis.direction), axis_full_carm=axis, predicted_error=pe)
