"""Video-to-fluoroscopy registration: ``carm_from_drill`` from markers seen by both the camera and the C-arm.

1. Horn (weighted by the video covariances) between X_D(m) and X_C(m), the reference's method.
2. Joint PnP on every tag corner: the corners' 3D positions in C (from each
   registered marker pose and the design) against their sub-pixel image
   positions, so all markers constrain the camera pose together.
3. An outlier marker (e.g. one bumped since the shot) is rejected by its
   point-based residual (leave-one-out), and per-marker FRE is reported.
4. A predicted error for the drill axis by Monte-Carlo propagation of the
   input uncertainties.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .camera import PinholeCamera
from .errors import DegenerateInput, MarkersNotFound
from .horn import absolute_orientation, absolute_orientation_batch
from .line import Line3D
from .marker_pose import MarkerPose
from .markers import MarkerSet
from .transforms import apply, invert, make_transform
from .video_markers import VideoDetections

__all__ = ["DrillRegistration", "PredictedError", "register_video_to_fluoro", "predicted_axis_error"]


@dataclass(frozen=True, kw_only=True)
class PredictedError:
    """1-sigma-based 95 % figures of the drill axis: position at the working point (mm) and angle (deg)."""

    position_mm: float
    angle_deg: float
    cone_half_angle_deg: float


@dataclass(frozen=True, kw_only=True)
class DrillRegistration:
    """carm_from_drill (4, 4); fre_mm: per-marker distance between X_C and the registered X_D."""

    carm_from_drill: NDArray[np.float64]
    carm_from_drill_horn: NDArray[np.float64]
    fre_mm: dict[int, float]
    used_ids: tuple[int, ...]
    rejected_ids: tuple[int, ...]
    corner_rms_px: float


def register_video_to_fluoro(
    video: VideoDetections,
    marker_poses: tuple[MarkerPose, ...],
    marker_set: MarkerSet,
    camera: PinholeCamera,
    *,
    outlier_mm: float = 2.5,
    min_markers: int = 3,
) -> DrillRegistration:
    poses = {p.marker_id: p for p in marker_poses if p.converged}
    vids = video.by_id()
    common = sorted(set(poses) & set(vids))
    if len(common) < min_markers:
        raise MarkersNotFound(
            f"only {len(common)} marker(s) seen by both the camera and fluoroscopy "
            f"(camera: {sorted(vids)}, fluoroscopy: {sorted(poses)}); at least {min_markers} are needed"
        )
    used = list(common)
    rejected: list[int] = []
    while True:
        fit = _horn(used, vids, poses)
        worst = int(np.argmax(fit.residuals_mm))
        if fit.residuals_mm[worst] <= outlier_mm or len(used) <= min_markers:
            break
        # Leave-one-out: does the fit without the worst marker explain the others well?
        rest = [i for k, i in enumerate(used) if k != worst]
        if _horn(rest, vids, poses).fre_mm < fit.fre_mm:
            rejected.append(used.pop(worst))
        else:
            break
    carm_from_drill_horn = fit.target_from_source
    # Joint PnP on all tag corners of the markers kept.
    obj, img = [], []
    for i in used:
        design = marker_set.by_id(i)
        obj.append(apply(poses[i].carm_from_marker, design.tag_corners_mm()))
        img.append(vids[i].corners_px)
    obj_a, img_a = np.concatenate(obj), np.concatenate(img)
    drill_from_carm0 = invert(carm_from_drill_horn)
    rvec0, _ = cv2.Rodrigues(drill_from_carm0[:3, :3])
    rvec, tvec = cv2.solvePnPRefineLM(obj_a, img_a, camera.camera_matrix, camera.distortion, rvec0.copy(), drill_from_carm0[:3, 3].reshape(3, 1).copy())
    rot, _ = cv2.Rodrigues(rvec)
    carm_from_drill = invert(make_transform(rot, tvec.ravel()))
    proj, _ = cv2.projectPoints(obj_a, rvec, tvec, camera.camera_matrix, camera.distortion)
    corner_rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_a) ** 2, axis=1))))
    drill_from_carm = invert(carm_from_drill)
    fre = {i: float(np.linalg.norm(apply(drill_from_carm, poses[i].position_carm_mm) - vids[i].position_camera_mm)) for i in common}
    return DrillRegistration(
        carm_from_drill=carm_from_drill,
        carm_from_drill_horn=carm_from_drill_horn,
        fre_mm=fre,
        used_ids=tuple(used),
        rejected_ids=tuple(rejected),
        corner_rms_px=corner_rms,
    )


def _horn(ids, vids, poses):
    src = np.array([vids[i].position_camera_mm for i in ids])
    dst = np.array([poses[i].position_carm_mm for i in ids])
    w = np.array([1.0 / max(np.trace(vids[i].covariance_mm2), 1e-4) for i in ids])
    try:
        return absolute_orientation(src, dst, w / w.max())
    except DegenerateInput as exc:
        raise MarkersNotFound(f"markers usable for registration are degenerate: {exc}") from None


def predicted_axis_error(
    video: VideoDetections,
    marker_poses: tuple[MarkerPose, ...],
    registration: DrillRegistration,
    axis_drill: Line3D,
    *,
    working_point_carm_mm: NDArray[np.float64],
    fluoro_sigma_mm: float = 0.15,
    axis_sigma_mm: float = 0.15,
    axis_sigma_deg: float = 0.12,
    focal_rel_sigma: float = 0.002,
    samples: int = 64,
    seed: int = 0,
) -> PredictedError:
    """Monte-Carlo error of the axis from every input's uncertainty.

    Draws the video X_D from their covariances with a common focal-length scale
    error (which scales depth for all markers alike), the fluoroscopy X_C with
    ``fluoro_sigma_mm``, and the calibrated drill axis with its calibration
    uncertainty; the 95th percentiles of the axis's displacement at the working
    point and of its angle are the prediction.
    """
    rng = np.random.default_rng(seed)
    vids = video.by_id()
    poses = {p.marker_id: p for p in marker_poses}
    ids = list(registration.used_ids)
    src = np.array([vids[i].position_camera_mm for i in ids])  # (N, 3)
    dst = np.array([poses[i].position_carm_mm for i in ids])
    chol = np.linalg.cholesky(np.array([vids[i].covariance_mm2 for i in ids]) + 1e-9 * np.eye(3))  # (N, 3, 3)
    axis_c = axis_drill.transformed(registration.carm_from_drill)
    s0 = float(np.dot(working_point_carm_mm - axis_c.point_mm, axis_c.direction))
    ref = axis_c.at(s0)[0]
    # All draws at once (B samples): video points, common focal scale, fluoroscopy points, axis calibration.
    s = src + np.einsum("nij,bnj->bni", chol, rng.normal(size=(samples, len(ids), 3)))
    s = s * (1.0 + rng.normal(scale=focal_rel_sigma, size=(samples, 1, 1)))
    d = dst + rng.normal(scale=fluoro_sigma_mm, size=(samples, *dst.shape))
    carm_from_drill = absolute_orientation_batch(s, d)  # (B, 4, 4)
    tilt = np.radians(axis_sigma_deg) * rng.normal(size=(samples, 3))
    k = np.linalg.norm(tilt, axis=1, keepdims=True)
    unit = np.divide(tilt, k, out=np.zeros_like(tilt), where=k > 0)
    direction_d = np.cos(k) * axis_drill.direction + np.sin(k) * np.cross(unit, axis_drill.direction)
    point_d = axis_drill.point_mm + rng.normal(scale=axis_sigma_mm, size=(samples, 3))
    point_c = np.einsum("bij,bj->bi", carm_from_drill[:, :3, :3], point_d) + carm_from_drill[:, :3, 3]
    direction_c = np.einsum("bij,bj->bi", carm_from_drill[:, :3, :3], direction_d)
    direction_c /= np.linalg.norm(direction_c, axis=1, keepdims=True)
    nearest = point_c + np.sum((ref - point_c) * direction_c, axis=1, keepdims=True) * direction_c
    pos = np.linalg.norm(nearest - ref, axis=1)
    ang = np.degrees(np.arccos(np.clip(direction_c @ axis_c.direction, -1.0, 1.0)))
    p95, a95 = float(np.percentile(pos, 95)), float(np.percentile(ang, 95))
    return PredictedError(position_mm=p95, angle_deg=a95, cone_half_angle_deg=a95)
