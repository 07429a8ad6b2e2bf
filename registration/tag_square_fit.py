"""A tag's pose fitted to the border steps of its edges, for a tag with one edge hidden.

A glare spot on a glossy tag, or a gloved finger, can hide most of one border edge: four edge lines cannot be
fitted and the tag's corners cannot be the lines' crossings. Its other three edges, with the camera's intrinsics and
the tag's known square, still fix its pose: the two sides beside the hidden edge give the tag's width across (so its
distance) and the convergence of its sides, the opposite edge where it starts; the tag's side length then places
the hidden edge. The pose (6 parameters) is fitted by least squares to the distance of every clean border step from
its edge's projected line, in undistorted pixels (a pinhole image of a straight edge is straight), starting from the
predicted corners' planar pose. Its corners are then the projection of the square, with lens distortion.

The fit states how well it places the corners: the covariance of the pose from the steps' own scatter, pushed to
the corners. A fit whose corners it cannot place within ``max_corner_sigma_px`` is refused.

Three edges' lines have six parameters, as the pose has: at the right pose the square follows the steps about as
closely as a free line through each edge's steps does (a few steps of the fourth edge add two parameters more to the
lines). Least squares started from a prediction far off can settle on another pose, one that follows them much worse
(``RETRY_EXCESS``): the fit is then started again from where the free lines put the corners, and the better of the
two kept. Twin seed 3006 (every camera degradation, second pose): a foreshortened tag placed from three of its corners,
the fourth predicted 26 px off; the fit from that prediction followed the steps to 0.41 px RMS where free lines
followed them to 0.15 px, and put the far corners 17 and 7 px off while stating 0.22 px; started again, 0.6 px.
Drawn steps of a tag tilted 30-65 deg with its fourth edge seen only beside one corner, predicted 15-30 px off at the
other: 58 of 160 fits put a corner over 1 px off (up to 22 px) from the prediction alone, none over 0.3 px started
again (``tests/test_tag_square_fit.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .camera import PinholeCamera

__all__ = ["SquareFit", "fit_square_to_edges", "RETRY_EXCESS", "RETRY_MOVE_PX"]

# The squared distances of the steps from the square fit's edges, less those from free lines through each edge's
# steps, in units of the steps' scatter about the free lines: at the right pose about chi-square with (2 x edges - 6)
# degrees of freedom (drawn steps, 0.15 px noise: 1.3-1.6 median, 11 at most over 200 fits). Over this the fit is
# tried again from the free lines' corners, and the better of the two kept.
RETRY_EXCESS = 16.0
# ... and when the fit puts a corner where two free lines cross more than this (px) from their crossing: a fit at the
# crossings already started where the retry would (under motion blur the steps follow no square closely).
RETRY_MOVE_PX = 1.0


@dataclass(frozen=True, kw_only=True)
class SquareFit:
    """A tag's pose fitted to its border steps.

    camera_from_tag : (4, 4) the tag's pose in frame D.
    corners_px : (4, 2) its corners (OpenCV order), distorted pixels.
    corner_sigma_px : (4,) each corner's 1-sigma placement (px, RMS over its two axes), from the fit's covariance.
    rms_px : RMS distance of the steps from their edges' lines.
    """

    camera_from_tag: NDArray[np.float64]
    corners_px: NDArray[np.float64]
    corner_sigma_px: NDArray[np.float64]
    rms_px: float


def _pose(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pose parameters (..., 6) (rotation vector, translation mm) -> rotation (..., 3, 3), translation (..., 3)."""
    x = np.asarray(x, dtype=np.float64)
    rot = Rotation.from_rotvec(x[..., :3].reshape(-1, 3)).as_matrix().reshape(x.shape[:-1] + (3, 3))
    return rot, x[..., 3:]


def _pinhole(camera: PinholeCamera, x: NDArray[np.float64], object_points: NDArray[np.float64]) -> NDArray[np.float64]:
    """The square's corners (..., 4, 2) in undistorted pixels for pose parameters x (..., 6) (rotation vector,
    translation mm): one pose or a batch."""
    rot, t = _pose(x)
    p = np.einsum("ij,...kj->...ik", object_points, rot) + t[..., None, :]               # (..., 4, 3)
    k = camera.camera_matrix
    xy = p[..., :2] / p[..., 2:3]
    return np.stack([k[0, 0] * xy[..., 0] + k[0, 1] * xy[..., 1] + k[0, 2], k[1, 1] * xy[..., 1] + k[1, 2]], axis=-1)


def _distances(corners: NDArray[np.float64], points: NDArray[np.float64], edge: NDArray[np.int64]) -> NDArray[np.float64]:
    """Signed distance (..., n) px of each point (n, 2) from the line of its edge (edge k: corner k -> k + 1), for
    corners (..., 4, 2)."""
    a, b = corners[..., edge, :], corners[..., (edge + 1) % 4, :]                        # (..., n, 2)
    d = b - a
    length = np.linalg.norm(d, axis=-1)
    return ((points[:, 0] - a[..., 0]) * d[..., 1] - (points[:, 1] - a[..., 1]) * d[..., 0]) / np.maximum(length, 1e-9)


def _forward_jacobian(fun, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Forward-difference Jacobian (m, 6) of a batched ``fun`` ((b, 6) -> (b, m)) at x (6,), every step in one call
    (steps as scipy's 2-point rule takes them: sqrt(eps) relative, at least sqrt(eps))."""
    h = np.sqrt(np.finfo(np.float64).eps) * np.maximum(1.0, np.abs(x))
    values = fun(np.vstack([x, x + np.diag(h)]))                                          # (7, m)
    return ((values[1:] - values[0]) / h[:, None]).T


def _line_rss(points: NDArray[np.float64], edge: NDArray[np.int64]) -> tuple[float, dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]]]:
    """The sum of squared distances of points (n, 2) from a free line through each edge's points (edges with at
    least 2), and each such edge's line (a point on it, its unit direction)."""
    sq, lines = 0.0, {}
    for k in np.unique(edge):
        p = points[edge == k]
        if len(p) < 2:
            continue
        centre = p.mean(axis=0)
        _, sv, vt = np.linalg.svd(p - centre, full_matrices=False)
        sq += float(sv[-1] ** 2)
        lines[int(k)] = (centre, vt[0])
    return sq, lines


def _corners_on_lines(predicted: NDArray[np.float64], lines: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]]
                      ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The predicted corners (4, 2) moved onto the free lines: a corner between two lines at their crossing, a corner
    on one line the nearest point of it; and which corners (4,) are crossings."""
    out = predicted.copy()
    crossed = np.zeros(4, dtype=bool)
    for c in range(4):
        near = [k for k in ((c - 1) % 4, c) if k in lines]  # corner c ends edge c - 1 and starts edge c
        if len(near) == 2:
            (p1, d1), (p2, d2) = lines[near[0]], lines[near[1]]
            a = np.array([d1, -d2]).T
            if abs(np.linalg.det(a)) > 1e-6:
                out[c] = p1 + np.linalg.solve(a, p2 - p1)[0] * d1
                crossed[c] = True
                continue
        if near:
            p, d = lines[near[0]]
            out[c] = p + float((predicted[c] - p) @ d) * d
    return out, crossed


def fit_square_to_edges(
    points_px: NDArray[np.float64],
    kept: NDArray[np.bool_],
    *,
    camera: PinholeCamera,
    object_points_mm: NDArray[np.float64],
    predicted_px: NDArray[np.float64],
    max_corner_sigma_px: float,
    min_sigma_px: float = 0.1,
) -> SquareFit | None:
    """The pose of a square tag fitted to its border steps; None when the fit does not hold.

    points_px : (4, s, 2) the border steps found along each edge (edge k from corner k to k + 1), distorted pixels.
    kept : (4, s) the clean ones, those the fit uses (at least two edges' worth).
    object_points_mm : (4, 3) the tag's corners in its frame (OpenCV order, z = 0).
    predicted_px : (4, 2) where the tag is expected: its planar pose starts the fit.
    max_corner_sigma_px : the most a corner's stated 1-sigma placement may be.
    min_sigma_px : the floor of the steps' noise in the covariance (their scatter can be smaller by chance).

    None when the start has no pose, the fit does not converge, the tag would lie behind the camera, or a corner's
    1-sigma placement exceeds ``max_corner_sigma_px``.
    """
    pts = np.asarray(points_px, dtype=np.float64)
    keep = np.asarray(kept, dtype=bool)
    obj = np.asarray(object_points_mm, dtype=np.float64)
    if pts.shape[:2] != keep.shape or pts.shape[0] != 4 or obj.shape != (4, 3):
        raise ValueError(f"points_px (4, s, 2), kept (4, s) and object_points_mm (4, 3) expected, got {pts.shape}, {keep.shape}, {obj.shape}")
    if keep.sum() < 8:
        return None
    edge = np.nonzero(keep)[0].astype(np.int64)
    undist = camera.undistort_pixels(pts[keep])
    ok, rvec, tvec = cv2.solvePnP(obj, np.asarray(predicted_px, dtype=np.float64).reshape(4, 1, 2), camera.camera_matrix, camera.distortion,
                                  flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not ok:
        return None
    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:  # one pose (6,) -> (n,), or a batch (b, 6) -> (b, n)
        return _distances(_pinhole(camera, x, obj), undist, edge)

    def fitted(rvec: NDArray[np.float64], tvec: NDArray[np.float64]):
        # The Jacobian's six steps in one batched call: the fit runs in the displaced-corner repair up to 16 times a tag.
        fit = least_squares(residuals, np.concatenate([np.ravel(rvec), np.ravel(tvec)]), jac=lambda x: _forward_jacobian(residuals, x),
                            method="lm", x_scale="jac")
        return fit if fit.success else None

    free_rss, lines = _line_rss(undist, edge)
    free_dof = len(undist) - 2 * len(lines)
    noise = max(free_rss / max(free_dof, 1), min_sigma_px**2)   # the steps' scatter about their lines, px^2

    def excess(fit) -> float:  # how much worse than free lines the square follows the steps, in units of their scatter
        return np.inf if fit is None else (float(np.sum(fit.fun**2)) - free_rss) / noise

    fit = fitted(rvec, tvec)
    first = excess(fit)
    if first > RETRY_EXCESS:
        on_lines, crossed = _corners_on_lines(camera.undistort_pixels(np.asarray(predicted_px, dtype=np.float64)), lines)  # undistorted pixels
        if fit is None or np.linalg.norm(_pinhole(camera, fit.x, obj)[crossed] - on_lines[crossed], axis=1).max(initial=0.0) > RETRY_MOVE_PX:
            # Settled on another pose than the steps' (it misses where their lines cross): again from the corners the
            # free lines give, the better kept.
            ok, rvec, tvec = cv2.solvePnP(obj, on_lines.reshape(4, 1, 2), camera.camera_matrix, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            again = fitted(rvec, tvec) if ok else None
            if excess(again) < first:
                fit, first = again, excess(again)
    if fit is None:
        return None
    rot, t = _pose(fit.x)
    in_d = obj @ rot.T + t
    if np.any(in_d[:, 2] <= 1.0):
        return None
    res = fit.fun
    dof = max(len(res) - 6, 1)
    sigma = max(float(np.sqrt(np.sum(res**2) / dof)), min_sigma_px)
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * sigma**2
    except np.linalg.LinAlgError:
        return None
    # The corners' Jacobian (8, 6) by central differences of the pinhole projection (distortion changes it little).
    h = 1e-6 * np.maximum(1.0, np.abs(fit.x))
    steps = np.diag(h)
    jc = ((_pinhole(camera, fit.x + steps, obj) - _pinhole(camera, fit.x - steps, obj)).reshape(6, 8) / (2 * h[:, None])).T
    cov_c = jc @ cov @ jc.T
    with np.errstate(invalid="ignore"):  # a pose the steps leave unfixed: its covariance, near singular, can come out negative (refused below)
        corner_sigma = np.sqrt(np.array([(cov_c[2 * i, 2 * i] + cov_c[2 * i + 1, 2 * i + 1]) / 2.0 for i in range(4)]))
    if not np.all(np.isfinite(corner_sigma)) or corner_sigma.max() > max_corner_sigma_px:
        return None
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot, t
    return SquareFit(camera_from_tag=pose, corners_px=camera.project(in_d), corner_sigma_px=corner_sigma,
                     rms_px=float(np.sqrt(np.mean(res**2))))
