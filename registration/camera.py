"""The drill camera: a pinhole model with Brown-Conrady distortion (OpenCV's 5-term model).

Frame D (drill camera): origin at the optical centre, +x along image columns,
+y along image rows (down), +z along the optical axis into the scene. Units mm.
Pixel coordinates are (column, row) with (0, 0) at the centre of the top-left
pixel, as in OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .camera_uncertainty import IntrinsicsUncertainty
from .transforms import check_points

__all__ = ["PinholeCamera"]


@dataclass(frozen=True, kw_only=True)
class PinholeCamera:
    """Intrinsics of a camera with Brown-Conrady lens distortion.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    camera_matrix : array, shape (3, 3)
        ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
    distortion : array, shape (5,)
        ``[k1, k2, p1, p2, k3]`` (OpenCV order).
    uncertainty : IntrinsicsUncertainty or None
        What the calibration states of its own error (camera.json's ``intrinsics_sigma``); None: not stated (the
        joint solve's priors then take the defaults, ``registration/camera_uncertainty.py``).
    """

    width: int
    height: int
    camera_matrix: NDArray[np.float64]
    distortion: NDArray[np.float64] = field(default_factory=lambda: np.zeros(5))
    uncertainty: IntrinsicsUncertainty | None = None

    def __post_init__(self) -> None:
        k = np.asarray(self.camera_matrix, dtype=np.float64)
        d = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        if k.shape != (3, 3) or k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0, 0, 1]):
            raise ValueError(f"camera_matrix must be 3x3 [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0, got {k.tolist()}")
        if d.shape[0] not in (4, 5, 8):
            raise ValueError(f"distortion must have 4, 5 or 8 terms (OpenCV order), got {d.shape[0]}")
        if d.shape[0] == 4:
            d = np.concatenate([d, [0.0]])
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "camera_matrix", k)
        object.__setattr__(self, "distortion", d)

    @classmethod
    def from_fov(cls, *, width: int, height: int, horizontal_fov_deg: float, distortion: ArrayLike = (0, 0, 0, 0, 0)) -> "PinholeCamera":
        """Camera with square pixels, centred principal point and the given horizontal field of view."""
        f = (width / 2.0) / np.tan(np.radians(horizontal_fov_deg) / 2.0)
        k = np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])
        return cls(width=width, height=height, camera_matrix=k, distortion=np.asarray(distortion, float))

    @property
    def focal_px(self) -> tuple[float, float]:
        return float(self.camera_matrix[0, 0]), float(self.camera_matrix[1, 1])

    @property
    def principal_point_px(self) -> tuple[float, float]:
        return float(self.camera_matrix[0, 2]), float(self.camera_matrix[1, 2])

    def distort_normalized(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Apply lens distortion to ideal normalized coordinates (N, 2) -> distorted normalized (N, 2)."""
        k1, k2, p1, p2, k3 = self.distortion[:5]
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, points_camera_mm: ArrayLike) -> NDArray[np.float64]:
        """Project points in frame D (N, 3) mm to distorted pixels (N, 2) (column, row).

        Points at or behind the optical centre (z <= 0) give NaN.
        """
        p = check_points(points_camera_mm)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        xyd = self.distort_normalized(xy)
        k = self.camera_matrix
        return np.stack([k[0, 0] * xyd[:, 0] + k[0, 1] * xyd[:, 1] + k[0, 2], k[1, 1] * xyd[:, 1] + k[1, 2]], axis=1)

    def undistort(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Distorted pixels (N, 2) -> ideal normalized image coordinates (N, 2) (x/z, y/z)."""
        px = check_points(pixels, dim=2)
        out = cv2.undistortPoints(
            px.reshape(-1, 1, 2), self.camera_matrix, self.distortion,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10),
        )
        return out.reshape(-1, 2)

    def undistort_pixels(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Distorted pixels (N, 2) -> pixels (N, 2) of the same camera without distortion."""
        xy = self.undistort(pixels)
        k = self.camera_matrix
        return np.stack([k[0, 0] * xy[:, 0] + k[0, 1] * xy[:, 1] + k[0, 2], k[1, 1] * xy[:, 1] + k[1, 2]], axis=1)

    def backproject(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Distorted pixels (N, 2) -> unit ray directions (N, 3) in frame D from the optical centre."""
        xy = self.undistort(pixels)
        rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)
