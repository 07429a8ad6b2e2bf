"""Marker localisation in drill-camera video: ArUco detection, sub-pixel corners, IPPE pose, X_D.

Per frame: detect the 6x6 tags, refine corners to sub-pixel, solve each tag's
pose with IPPE for squares (both solutions, the better reprojection wins, then
Levenberg-Marquardt refinement), and move the tag centre 2 mm along the tag
normal to the central BB: ``X_D = camera_from_tag @ (0, 0, -offset)``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .camera import PinholeCamera
from .transforms import make_transform

__all__ = ["VideoMarker", "VideoDetections", "VideoMarkerLocator", "detect_tags", "tag_object_points"]


@dataclass(frozen=True, kw_only=True)
class VideoMarker:
    """One localised marker.

    corners_px : (4, 2) sub-pixel tag corners, OpenCV order (TL, TR, BR, BL).
    camera_from_tag : (4, 4) tag pose in frame D.
    position_camera_mm : (3,) X_D, the central BB in frame D.
    covariance_mm2 : (3, 3) first-order covariance of X_D from the corner noise.
    reprojection_error_px : RMS corner reprojection error of the chosen pose.
    """

    marker_id: int
    corners_px: NDArray[np.float64]
    camera_from_tag: NDArray[np.float64]
    position_camera_mm: NDArray[np.float64]
    covariance_mm2: NDArray[np.float64]
    reprojection_error_px: float


@dataclass(frozen=True, kw_only=True)
class VideoDetections:
    markers: tuple[VideoMarker, ...]
    ignored_ids: tuple[int, ...]
    image_size: tuple[int, int]

    def by_id(self) -> dict[int, VideoMarker]:
        return {m.marker_id: m for m in self.markers}


def _dictionary(name: str):
    if not hasattr(cv2.aruco, name):
        raise ValueError(f"unknown ArUco dictionary '{name}' (e.g. DICT_6X6_250)")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def _detector(dictionary: str, *, refine: bool = True) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX if refine else cv2.aruco.CORNER_REFINE_NONE
    params.cornerRefinementWinSize = 4
    params.cornerRefinementMinAccuracy = 0.01
    params.adaptiveThreshWinSizeMin = 7
    params.adaptiveThreshWinSizeMax = 31
    params.adaptiveThreshWinSizeStep = 12
    params.minMarkerPerimeterRate = 0.05
    return cv2.aruco.ArucoDetector(_dictionary(dictionary), params)


def _gray(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise ValueError(f"expected a grayscale (H, W) or BGR (H, W, 3) image, got shape {img.shape}")
    return img


def detect_tags(image: NDArray[np.uint8], *, dictionary: str = "DICT_6X6_250") -> list[tuple[int, NDArray[np.float64]]]:
    """All tags of ``dictionary`` in the image: (id, corners (4, 2)), no camera needed."""
    corners, ids, _ = _detector(dictionary).detectMarkers(_gray(image))
    if ids is None:
        return []
    return [(int(i), c.reshape(4, 2).astype(np.float64)) for i, c in zip(ids.ravel(), corners)]


def tag_object_points(tag_size_mm: float) -> NDArray[np.float64]:
    """(4, 3) tag corners in the tag frame (IPPE_SQUARE order)."""
    h = tag_size_mm / 2.0
    return np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)


class VideoMarkerLocator:
    """Localises the configured markers in drill-camera frames."""

    def __init__(
        self,
        *,
        camera: PinholeCamera,
        marker_ids: Iterable[int] = range(48),
        tag_size_mm: float = 30.0,
        tag_to_bb_offset_mm: float = 2.0,
        dictionary: str = "DICT_6X6_250",
        corner_sigma_px: float = 0.1,
        detect_below_px: int = 800,
    ) -> None:
        self.camera = camera
        self.marker_ids = frozenset(int(i) for i in marker_ids)
        self.tag_size_mm = float(tag_size_mm)
        self.offset_mm = float(tag_to_bb_offset_mm)
        self.corner_sigma_px = float(corner_sigma_px)
        self._detector = _detector(dictionary)
        # Large frames are searched at half resolution (4x fewer pixels) and the corners refined at full resolution.
        self._coarse = _detector(dictionary, refine=False)
        self.detect_below_px = detect_below_px
        self._object = tag_object_points(self.tag_size_mm)

    def locate(self, image: NDArray[np.uint8]) -> VideoDetections:
        gray = _gray(image)
        h, w = gray.shape
        if (w, h) != (self.camera.width, self.camera.height):
            raise ValueError(f"frame is {w}x{h} but the camera calibration is for {self.camera.width}x{self.camera.height}")
        if w > self.detect_below_px:
            small = cv2.resize(gray, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
            corners, ids, _ = self._coarse.detectMarkers(small)
            if ids is not None:
                pts = np.concatenate([c.reshape(4, 2) for c in corners]) * 2.0 + 0.5
                refined = cv2.cornerSubPix(gray, pts.astype(np.float32).reshape(-1, 1, 2), (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
                corners = [refined[4 * i : 4 * i + 4].reshape(1, 4, 2) for i in range(len(ids))]
        else:
            corners, ids, _ = self._detector.detectMarkers(gray)
        found: list[VideoMarker] = []
        ignored: list[int] = []
        if ids is not None:
            for marker_id, c in zip(ids.ravel().tolist(), corners):
                if marker_id not in self.marker_ids:
                    ignored.append(int(marker_id))
                    continue
                found.append(self._pose(int(marker_id), c.reshape(4, 2).astype(np.float64)))
        return VideoDetections(markers=tuple(sorted(found, key=lambda m: m.marker_id)), ignored_ids=tuple(sorted(ignored)), image_size=(w, h))

    def _pose(self, marker_id: int, corners: NDArray[np.float64]) -> VideoMarker:
        k, dist = self.camera.camera_matrix, self.camera.distortion
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(self._object, corners, k, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        best = int(np.argmin(np.asarray(errs).ravel()))
        rvec, tvec = cv2.solvePnPRefineLM(self._object, corners, k, dist, rvecs[best].copy(), tvecs[best].copy())
        rot, _ = cv2.Rodrigues(rvec)
        camera_from_tag = make_transform(rot, tvec.ravel())
        bb_tag = np.array([0.0, 0.0, -self.offset_mm])
        x_d = rot @ bb_tag + tvec.ravel()
        proj, jac = cv2.projectPoints(self._object, rvec, tvec, k, dist)
        err = float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - corners) ** 2, axis=1))))
        # First-order covariance of the 6 pose parameters, pushed to X_D.
        j = jac[:, :6]
        cov_pose = np.linalg.pinv(j.T @ j) * self.corner_sigma_px**2
        eps = 1e-6
        jx = np.zeros((3, 6))
        for i in range(6):
            dr = rvec.ravel().copy()
            dt = tvec.ravel().copy()
            if i < 3:
                dr[i] += eps
            else:
                dt[i - 3] += eps
            r2, _ = cv2.Rodrigues(dr)
            jx[:, i] = ((r2 @ bb_tag + dt) - x_d) / eps
        cov = jx @ cov_pose @ jx.T
        return VideoMarker(marker_id=marker_id, corners_px=corners, camera_from_tag=camera_from_tag, position_camera_mm=x_d, covariance_mm2=cov, reprojection_error_px=err)
