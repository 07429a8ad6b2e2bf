"""Drill-axis calibration from a jig rotated about the drill axis while the drill camera watches it.

Two methods on the jig board's poses ``camera_from_board`` (4, 4) per frame:

- ``cylinder``: the reference's. Board points sweep a cylinder about the axis;
  MLESAC fits the cylinder (axis point, direction, radius) to the 3D points.
- ``screw`` (better): every relative motion ``T_i T_0^-1`` is a rotation about
  the same axis; its direction is the common eigen-axis of the relative
  rotations (closed form: SVD of the stacked rotation axes), a point on it the
  least-squares solution of ``(I - R_i) p = t_i``, refined jointly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .errors import DegenerateInput
from .line import Line3D
from .transforms import apply, invert

__all__ = ["AxisFit", "fit_axis_screw", "fit_axis_cylinder"]


@dataclass(frozen=True, kw_only=True)
class AxisFit:
    """axis in the camera frame; residual_mm: RMS of the method's residual; residual_deg: spread of the rotation axes."""

    axis: Line3D
    residual_mm: float
    residual_deg: float
    rotation_range_deg: float
    method: str


def _relative(poses: list[NDArray[np.float64]]):
    if len(poses) < 3:
        raise DegenerateInput(f"drill-axis calibration needs at least 3 jig poses, got {len(poses)}")
    rel = [p @ invert(poses[0]) for p in poses[1:]]
    angles = np.array([np.degrees(Rotation.from_matrix(r[:3, :3]).magnitude()) for r in rel])
    if angles.max() < 1.0:
        raise DegenerateInput("the jig did not rotate (board static): rotate the jig about the drill axis")
    if angles.max() < 20.0:
        raise DegenerateInput(f"rotation too small ({angles.max():.1f} deg); rotate the jig at least 20 deg about the drill axis")
    return rel, angles


def fit_axis_screw(poses: list[NDArray[np.float64]], *, max_axis_spread_deg: float = 2.0) -> AxisFit:
    rel, angles = _relative(poses)
    axes = []
    for r, a in zip(rel, angles):
        if a > 5.0:
            rv = Rotation.from_matrix(r[:3, :3]).as_rotvec()
            axes.append(rv / np.linalg.norm(rv))
    axes = np.array(axes)
    ref = axes[0]
    axes = axes * np.sign(axes @ ref)[:, None]
    direction = np.linalg.svd(axes)[2][0]
    direction *= np.sign(direction @ ref)
    spread = float(np.degrees(np.arccos(np.clip(np.abs(axes @ direction), -1, 1))).max())
    if spread > max_axis_spread_deg:
        raise DegenerateInput(f"jig poses disagree: their rotation axes spread {spread:.1f} deg (> {max_axis_spread_deg}); the jig slipped or the board poses are wrong")
    a_mat = np.vstack([np.eye(3) - r[:3, :3] for r in rel])
    b = np.concatenate([r[:3, 3] for r in rel])
    point = np.linalg.lstsq(a_mat, b, rcond=None)[0]

    def residual(x):
        d = x[3:] / np.linalg.norm(x[3:])
        out = []
        for r in rel:
            # A rotation about the axis (point p, direction d) leaves axis points fixed.
            for s in (-50.0, 50.0):
                q = x[:3] + s * d
                out.append(apply(r, q) - q)
        return np.concatenate(out)

    sol = least_squares(residual, np.concatenate([point, direction]))
    d = sol.x[3:] / np.linalg.norm(sol.x[3:])
    axis = Line3D(point_mm=sol.x[:3], direction=d)
    axis = Line3D(point_mm=axis.closest_point(np.zeros(3)), direction=d if d[2] >= 0 else -d)
    rms = float(np.sqrt(np.mean(sol.fun**2)))
    return AxisFit(axis=axis, residual_mm=rms, residual_deg=spread, rotation_range_deg=float(angles.max()), method="screw")


def fit_axis_cylinder(poses: list[NDArray[np.float64]], board_points_mm: NDArray[np.float64], *, iterations: int = 100, threshold_mm: float = 0.5, seed: int = 0) -> AxisFit:
    """The reference's method: MLESAC fit of coaxial cylinders to the board points swept by the rotation.

    Each board point sweeps its own circle, so every point gets its own radius
    about one common axis. Minimal samples are frames (all their points).
    """
    _, angles = _relative(poses)
    pts = np.stack([apply(p, board_points_mm) for p in poses])  # (K frames, J points, 3)
    k, j = pts.shape[:2]
    rng = np.random.default_rng(seed)
    centroid = pts.reshape(-1, 3).mean(axis=0)
    # Initial direction: the normal of the plane that the first point's circle spans.
    circle = pts[:, 0] - pts[:, 0].mean(axis=0)
    n0 = np.linalg.svd(circle)[2][2]

    def res(x, p):
        d = x[3:6] / np.linalg.norm(x[3:6])
        v = p - x[:3]
        dist = np.linalg.norm(v - (v @ d)[..., None] * d, axis=-1)
        return (dist - x[6:][None, :]).ravel()

    x0 = np.concatenate([centroid, n0, np.linalg.norm(pts[0] - centroid, axis=1)])
    best, best_cost = None, np.inf
    sigma = threshold_mm / 2
    for _ in range(iterations):
        sample = pts[rng.choice(k, size=min(k, 4), replace=False)]
        start = x0 + np.concatenate([rng.normal(scale=5.0, size=3), rng.normal(scale=0.1, size=3), np.zeros(j)])
        sol = least_squares(lambda x: res(x, sample), start)
        e = res(sol.x, pts)
        # MLESAC: negative log-likelihood of a Gaussian inlier / uniform outlier mixture.
        cost = float(-np.sum(np.log(0.9 * np.exp(-(e**2) / (2 * sigma**2)) / (np.sqrt(2 * np.pi) * sigma) + 0.1 / 50.0)))
        if cost < best_cost:
            best, best_cost = sol.x, cost
    sol = least_squares(lambda x: res(x, pts), best)
    d = sol.x[3:6] / np.linalg.norm(sol.x[3:6])
    d = d if d[2] >= 0 else -d
    axis = Line3D(point_mm=sol.x[:3], direction=d)
    axis = Line3D(point_mm=axis.closest_point(np.zeros(3)), direction=d)
    return AxisFit(axis=axis, residual_mm=float(np.sqrt(np.mean(sol.fun**2))), residual_deg=0.0, rotation_range_deg=float(angles.max()), method="cylinder-mlesac")


# The jig: an ArUco grid board (ids outside the marker set) centred on the drill sleeve.
JIG_MARKERS = (4, 4)
JIG_MARKER_MM = 12.0
JIG_SEPARATION_MM = 3.0
JIG_FIRST_ID = 100


def jig_board():
    import cv2

    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    ids = np.arange(JIG_FIRST_ID, JIG_FIRST_ID + JIG_MARKERS[0] * JIG_MARKERS[1], dtype=np.int32)
    return cv2.aruco.GridBoard(JIG_MARKERS, JIG_MARKER_MM, JIG_SEPARATION_MM, d, ids)


def jig_size_mm() -> float:
    return JIG_MARKERS[0] * JIG_MARKER_MM + (JIG_MARKERS[0] - 1) * JIG_SEPARATION_MM


def jig_pose(image: NDArray[np.uint8], camera) -> NDArray[np.float64] | None:
    """``camera_from_board`` (4, 4) of the jig in one frame (board frame: OpenCV GridBoard), or None."""
    import cv2

    board = jig_board()
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(board.getDictionary(), params)
    corners, ids, _ = det.detectMarkers(image)
    if ids is None or len(ids) < 4:
        return None
    obj, img = board.matchImagePoints(corners, ids)
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera.camera_matrix, camera.distortion, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.camera_matrix, camera.distortion, rvec, tvec)
    from .transforms import make_transform

    return make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
