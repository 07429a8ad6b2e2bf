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
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .camera import PinholeCamera

__all__ = ["SquareFit", "fit_square_to_edges"]


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
    x0 = np.concatenate([rvec.ravel(), tvec.ravel()])
    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:  # one pose (6,) -> (n,), or a batch (b, 6) -> (b, n)
        return _distances(_pinhole(camera, x, obj), undist, edge)

    # The Jacobian's six steps in one batched call: the fit runs in the displaced-corner repair up to 16 times a tag.
    fit = least_squares(residuals, x0, jac=lambda x: _forward_jacobian(residuals, x), method="lm", x_scale="jac")
    if not fit.success:
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
    corner_sigma = np.sqrt(np.array([(cov_c[2 * i, 2 * i] + cov_c[2 * i + 1, 2 * i + 1]) / 2.0 for i in range(4)]))
    if not np.all(np.isfinite(corner_sigma)) or corner_sigma.max() > max_corner_sigma_px:
        return None
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot, t
    return SquareFit(camera_from_tag=pose, corners_px=camera.project(in_d), corner_sigma_px=corner_sigma,
                     rms_px=float(np.sqrt(np.mean(res**2))))
