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

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .errors import DegenerateInput
from .line import Line3D
from .transforms import apply, invert

__all__ = [
    "AxisFit", "fit_axis_screw", "fit_axis_cylinder", "JigDetection", "JigNotFound", "detect_jig", "find_jig_poses", "jig_pose",
    "jig_board", "jig_ids", "jig_size_mm", "jig_tag_corners_mm", "describe_missing_jig",
]


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


# The jig: an ArUco grid board (ids outside the marker set) turning with the drill. Its printable sheet and geometry
# file come from ``drillnav markers jig``; these constants are the design both are drawn from.
JIG_MARKERS = (4, 4)  # tags across, down
JIG_MARKER_MM = 12.0
JIG_SEPARATION_MM = 3.0
JIG_FIRST_ID = 100
JIG_DICTIONARY = "DICT_6X6_250"
MIN_JIG_TAGS = 4  # 16 board points spread over the board: a stable pose; fewer tags and the frame is not used
MIN_JIG_POSES = 3  # the screw fit needs at least two relative rotations


class JigNotFound(DegenerateInput):
    """Too few frames show the jig board; the message says what the frames showed instead."""


@dataclass(frozen=True, kw_only=True)
class JigDetection:
    """The jig in one frame: its pose if enough of its tags were seen, and every tag id seen."""

    camera_from_board: NDArray[np.float64] | None  # (4, 4), board frame of :func:`jig_board` (x right, y down, mm)
    jig_ids: tuple[int, ...]  # the jig's tags seen
    other_ids: tuple[int, ...]  # tags seen that are not the jig's (field markers, strays)
    points: int  # board points (tag corners) used for the pose; 0 without a pose


def jig_ids() -> tuple[int, ...]:
    return tuple(range(JIG_FIRST_ID, JIG_FIRST_ID + JIG_MARKERS[0] * JIG_MARKERS[1]))


def jig_board():
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, JIG_DICTIONARY))
    return cv2.aruco.GridBoard(JIG_MARKERS, JIG_MARKER_MM, JIG_SEPARATION_MM, d, np.array(jig_ids(), dtype=np.int32))


def jig_size_mm() -> float:
    return JIG_MARKERS[0] * JIG_MARKER_MM + (JIG_MARKERS[0] - 1) * JIG_SEPARATION_MM


def jig_tag_corners_mm() -> dict[int, NDArray[np.float64]]:
    """Each jig tag's id -> its 4 corners (4, 3) in the board frame (mm; top-left, top-right, bottom-right, bottom-left)."""
    board = jig_board()
    return {int(i): np.asarray(c, dtype=np.float64).reshape(4, 3) for i, c in zip(board.getIds().ravel(), board.getObjPoints())}


def detect_jig(image: NDArray[np.uint8], camera) -> JigDetection:
    """Find the jig board in a grey or BGR frame and, from its own tags' corners only, its pose.

    Tags that are not the jig's (the field markers, say) are listed but never
    enter the pose; fewer than :data:`MIN_JIG_TAGS` of the jig's tags give no pose.
    """
    import cv2

    from .aruco_detect import detect_aruco
    from .transforms import make_transform

    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"expected a grey (H, W) or BGR (H, W, 3) uint8 frame, got {image.dtype} {image.shape}")
    board = jig_board()
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    seen, corners = detect_aruco(cv2.aruco.ArucoDetector(board.getDictionary(), params), image)
    own = set(jig_ids())
    keep = [k for k, i in enumerate(seen) if i in own]
    found, others = tuple(sorted(seen[k] for k in keep)), tuple(sorted(set(seen) - own))
    if len(set(found)) < MIN_JIG_TAGS:
        return JigDetection(camera_from_board=None, jig_ids=found, other_ids=others, points=0)
    table = jig_tag_corners_mm()
    obj = np.concatenate([table[seen[k]] for k in keep]).astype(np.float64)
    img = np.concatenate([np.asarray(corners[k], dtype=np.float64).reshape(4, 2) for k in keep])
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera.camera_matrix, camera.distortion, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return JigDetection(camera_from_board=None, jig_ids=found, other_ids=others, points=0)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.camera_matrix, camera.distortion, rvec, tvec)
    pose = make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
    return JigDetection(camera_from_board=pose, jig_ids=found, other_ids=others, points=len(obj))


def jig_pose(image: NDArray[np.uint8], camera) -> NDArray[np.float64] | None:
    """``camera_from_board`` (4, 4) of the jig in one frame, or None (see :func:`detect_jig`)."""
    return detect_jig(image, camera).camera_from_board


def _ids_text(ids) -> str:
    return ", ".join(str(i) for i in sorted(ids))


def describe_missing_jig(detections: Sequence[JigDetection], *, field_ids: Sequence[int] = ()) -> str:
    """What frames without the jig showed instead, in one line: "saw tags 3, 7 (field markers), none of the jig's 16 tags"."""
    misses = [d for d in detections if d.camera_from_board is None]
    if not misses:
        return "every frame showed it"
    own, field = set(jig_ids()), set(field_ids)
    seen_jig = sorted({i for d in misses for i in d.jig_ids})
    others = sorted({i for d in misses for i in d.other_ids})
    parts = []
    if others:
        in_field = [i for i in others if i in field]
        strays = [i for i in others if i not in field]
        if in_field:
            parts.append(f"tags {_ids_text(in_field)} (field markers)")
        if strays:
            parts.append(f"tags {_ids_text(strays)} (neither field markers nor the jig's)")
    jig = (f"only the jig's tags {_ids_text(seen_jig)} ({MIN_JIG_TAGS} or more of its {len(own)} tags are needed in one frame)" if seen_jig
           else f"none of the jig's {len(own)} tags (ids {min(own)}-{max(own)})")
    return ("saw " + ", ".join(parts) + ", " + jig) if parts else ("saw no ArUco tag at all" if not seen_jig else "saw " + jig)


def find_jig_poses(frames: Sequence[tuple[str, NDArray[np.uint8]]], camera, *, min_poses: int = MIN_JIG_POSES,
                   before_each: Callable[[int, str], None] | None = None) -> list[NDArray[np.float64]]:
    """The jig's ``camera_from_board`` poses in the named frames that show it; :class:`JigNotFound` when fewer than
    ``min_poses`` do, naming what the others showed. ``before_each(index, name)`` is called before each frame
    (progress, cancellation)."""
    from .markers import default_marker_set

    detections = []
    for i, (name, image) in enumerate(frames):
        if before_each is not None:
            before_each(i, name)
        detections.append(detect_jig(image, camera))
    poses = [d.camera_from_board for d in detections if d.camera_from_board is not None]
    if len(poses) < min_poses:
        seen = describe_missing_jig(detections, field_ids=[m.aruco_id for m in default_marker_set().markers])
        raise JigNotFound(f"the jig board was found in only {len(poses)} of {len(frames)} frames (at least {min_poses} are needed): {seen}")
    return poses
