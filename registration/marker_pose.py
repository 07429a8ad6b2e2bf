"""Marker poses in the C-arm frame from one or several views.

Known-component registration with the marker's design as the component: each
identified BB gives a 2D-3D correspondence. IPPE on the best single view
initialises the pose (planar target), then a joint Levenberg-Marquardt
refinement minimises the reprojection error of every BB in every view. Each
pose gets a residual (RMS px) and a convergence flag.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .carm import CArmView
from .fluoro_markers import FluoroDetections
from .markers import MarkerSet
from .transforms import apply, from_rotvec, invert, make_transform, to_rotvec

__all__ = ["MarkerPose", "register_markers"]


@dataclass(frozen=True, kw_only=True)
class MarkerPose:
    """carm_from_marker (4, 4); residual_px: RMS BB reprojection error over all views; n_views, n_points used."""

    marker_id: int
    carm_from_marker: NDArray[np.float64]
    residual_px: float
    n_views: int
    n_points: int
    converged: bool

    @property
    def position_carm_mm(self) -> NDArray[np.float64]:
        """X_C: the central BB in frame C."""
        return self.carm_from_marker[:3, 3].copy()


def _initial_pose(view: CArmView, obj: NDArray[np.float64], img: NDArray[np.float64]) -> NDArray[np.float64]:
    k, source_from_carm = view.decompose()
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ValueError("IPPE failed for the marker's BBs")
    rot, _ = cv2.Rodrigues(rvec)
    return invert(source_from_carm) @ make_transform(rot, tvec.ravel())


def _solve_one(marker_id: int, observations: list[tuple[CArmView, NDArray[np.float64], NDArray[np.float64]]], max_residual_px: float) -> MarkerPose:
    best = max(observations, key=lambda o: len(o[1]))
    carm_from_marker0 = _initial_pose(best[0], best[1], best[2])
    rv0, t0 = to_rotvec(carm_from_marker0)

    def residual(x: NDArray[np.float64]) -> NDArray[np.float64]:
        t = from_rotvec(x[:3], x[3:])
        return np.concatenate([(view.project(apply(t, obj)) - img).ravel() for view, obj, img in observations])

    sol = least_squares(residual, np.concatenate([rv0, t0]), method="lm", xtol=1e-10, ftol=1e-10)
    pose = from_rotvec(sol.x[:3], sol.x[3:])
    r = sol.fun.reshape(-1, 2)
    rms = float(np.sqrt(np.mean(np.sum(r * r, axis=1))))
    n_points = sum(len(o[1]) for o in observations)
    return MarkerPose(
        marker_id=marker_id,
        carm_from_marker=pose,
        residual_px=rms,
        n_views=len(observations),
        n_points=n_points,
        converged=bool(sol.success and rms <= max_residual_px),
    )


def register_markers(
    detections: list[FluoroDetections],
    views: list[CArmView],
    marker_set: MarkerSet,
    *,
    max_residual_px: float = 1.5,
    workers: int = 2,
) -> tuple[MarkerPose, ...]:
    """Pose of every marker identified in at least one view, solved jointly over the views that see it.

    Markers are independent, so they are solved in parallel (threads: the work is in numpy/OpenCV).
    """
    if len(detections) != len(views):
        raise ValueError(f"{len(detections)} detection sets for {len(views)} views")
    per_marker: dict[int, list] = {}
    for det, view in zip(detections, views):
        for m in det.markers:
            design = marker_set.by_id(m.marker_id)
            ok = m.bb_index >= 0
            if ok.sum() < 4:
                continue
            obj = design.bb_centers_mm[m.bb_index[ok]]
            img = np.array([b.center_px for b, keep in zip(m.bbs, ok) if keep])
            per_marker.setdefault(m.marker_id, []).append((view, obj, img))
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        poses = list(pool.map(lambda item: _solve_one(item[0], item[1], max_residual_px), sorted(per_marker.items())))
    return tuple(poses)
