"""Camera calibration (Zhang's method, Brown-Conrady k1 k2 p1 p2 k3) from checkerboard or ChArUco views.

Pure: takes images as arrays. Detection refines corners to sub-pixel; views
whose reprojection error is an outlier are rejected and the calibration is
solved again; degenerate sets are refused with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .camera import PinholeCamera
from .camera_uncertainty import IntrinsicsUncertainty
from .errors import DegenerateInput

__all__ = ["BoardSpec", "parse_board", "detect_board", "calibrate_camera", "CameraCalibration"]


@dataclass(frozen=True, kw_only=True)
class BoardSpec:
    """kind 'checkerboard': inner corners (cols x rows), square size; 'charuco': squares (cols x rows), square and marker size, dictionary."""

    kind: str
    cols: int
    rows: int
    square_mm: float
    marker_mm: float = 0.0
    dictionary: str = "DICT_6X6_250"

    def object_points(self) -> NDArray[np.float64]:
        """(N, 3) inner-corner positions on the board, mm, row-major as OpenCV orders them."""
        n_c, n_r = (self.cols, self.rows) if self.kind == "checkerboard" else (self.cols - 1, self.rows - 1)
        g = np.mgrid[0:n_c, 0:n_r].T.reshape(-1, 2) * self.square_mm
        return np.hstack([g, np.zeros((len(g), 1))]).astype(np.float64)


def parse_board(text: str) -> BoardSpec:
    """'checkerboard:9x6:25mm' or 'charuco:5x7:40mm:30mm[:DICT_6X6_250]'."""
    parts = text.split(":")
    try:
        kind = parts[0]
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        square = float(parts[2].removesuffix("mm"))
        if kind == "checkerboard" and len(parts) == 3:
            spec = BoardSpec(kind=kind, cols=cols, rows=rows, square_mm=square)
        elif kind == "charuco" and len(parts) in (4, 5):
            spec = BoardSpec(kind=kind, cols=cols, rows=rows, square_mm=square, marker_mm=float(parts[3].removesuffix("mm")), dictionary=parts[4] if len(parts) == 5 else "DICT_6X6_250")
        else:
            raise ValueError
    except (ValueError, IndexError):
        raise ValueError(f"bad board '{text}': use checkerboard:COLSxROWS:SQUAREmm (inner corners) or charuco:COLSxROWS:SQUAREmm:MARKERmm[:DICT]") from None
    if min(cols, rows) < 2 or square <= 0:
        raise ValueError(f"bad board '{text}': needs at least 2x2 corners and a positive square size")
    return spec


def _charuco_detector(spec: BoardSpec):
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    board = cv2.aruco.CharucoBoard((spec.cols, spec.rows), spec.square_mm, spec.marker_mm, d)
    return cv2.aruco.CharucoDetector(board), board


def detect_board(image: NDArray[np.uint8], spec: BoardSpec) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """(object points (N, 3) mm, image points (N, 2) px) of one view, or None if the board is not found."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if spec.kind == "checkerboard":
        ok, corners = cv2.findChessboardCorners(gray, (spec.cols, spec.rows), cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return None
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3))
        return spec.object_points(), corners.reshape(-1, 2).astype(np.float64)
    detector, board = _charuco_detector(spec)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < 6:
        return None
    obj = board.getChessboardCorners()[ids.ravel()]
    return np.asarray(obj, np.float64), corners.reshape(-1, 2).astype(np.float64)


def _scale_variation(obj_img) -> float:
    """Ratio of the largest to the smallest local image scale over the board (1.0 for a fronto-parallel view)."""
    obj, img = obj_img
    hmat, _ = cv2.findHomography(obj[:, :2], img)
    if hmat is None:
        return 1.0
    scales = []
    for x, y in obj[:, :2][[0, -1, np.argmax(obj[:, 0] - obj[:, 1]), np.argmax(obj[:, 1] - obj[:, 0])]]:
        w = hmat[2] @ [x, y, 1.0]
        jac = (hmat[:2, :2] * w - np.outer(hmat[:2] @ [x, y, 1.0], hmat[2, :2])) / w**2
        scales.append(np.sqrt(abs(np.linalg.det(jac))))
    return float(max(scales) / min(scales))


@dataclass(frozen=True, kw_only=True)
class CameraCalibration:
    camera: PinholeCamera
    rms_px: float
    per_view_errors_px: tuple[float, ...]
    used_views: tuple[int, ...]
    rejected_views: tuple[int, ...]
    not_found_views: tuple[int, ...]


def calibrate_camera(images: list[NDArray[np.uint8]], spec: BoardSpec, *, min_views: int = 3, outlier_factor: float = 3.0) -> CameraCalibration:
    if len(images) < min_views:
        raise DegenerateInput(f"camera calibration needs at least {min_views} views, got {len(images)}")
    sizes = {im.shape[:2] for im in images}
    if len(sizes) != 1:
        raise DegenerateInput(f"views differ in size: {sorted(sizes)}")
    h, w = images[0].shape[:2]
    found, missing = [], []
    for i, im in enumerate(images):
        d = detect_board(im, spec)
        (found.append((i, d)) if d is not None else missing.append(i))
    if not found:
        raise DegenerateInput(f"the board {spec.kind} {spec.cols}x{spec.rows} was not found in any of the {len(images)} views")
    if len(found) < min_views:
        raise DegenerateInput(f"the board was found in only {len(found)} view(s) (views {[i for i, _ in found]}); at least {min_views} are needed")
    # Fronto-parallel views leave the focal length unobservable: a tilted board's image scale varies across it.
    variation = max(_scale_variation(obj_img) for _, obj_img in found)
    if variation < 1.03:
        raise DegenerateInput(f"all views are nearly fronto-parallel (image scale varies by only {100 * (variation - 1):.1f} % across the board): focal length is not observable; tilt the board 15-45 deg in some views")
    use = list(range(len(found)))
    rejected: list[int] = []
    while True:
        obj = [found[k][1][0].astype(np.float32) for k in use]
        img = [found[k][1][1].astype(np.float32) for k in use]
        rms, k_mat, dist, rvecs, tvecs, std_intrinsics, _, _ = cv2.calibrateCameraExtended(obj, img, (w, h), None, None)
        errs = []
        for o, p, rv, tv in zip(obj, img, rvecs, tvecs):
            proj, _ = cv2.projectPoints(o, rv, tv, k_mat, dist)
            errs.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - p) ** 2, axis=1)))))
        worst = int(np.argmax(errs))
        if errs[worst] > max(outlier_factor * np.median(errs), 1.0) and len(use) > min_views:
            rejected.append(found[use.pop(worst)][0])
            continue
        break
    cam = PinholeCamera(width=w, height=h, camera_matrix=k_mat, distortion=dist.ravel()[:5], uncertainty=_stated(k_mat, std_intrinsics))
    return CameraCalibration(camera=cam, rms_px=float(rms), per_view_errors_px=tuple(errs), used_views=tuple(found[k][0] for k in use), rejected_views=tuple(rejected), not_found_views=tuple(missing))


def _stated(camera_matrix: np.ndarray, std_intrinsics: np.ndarray) -> IntrinsicsUncertainty | None:
    """OpenCV's standard deviations of fx, fy, cx, cy as the calibration's stated uncertainty (the distortion's are
    not stated: see :class:`IntrinsicsUncertainty`); None where they are not finite (a degenerate set of views)."""
    s = np.asarray(std_intrinsics, dtype=np.float64).ravel()
    if s.size < 4 or not np.all(np.isfinite(s[:4])):
        return None
    fx, fy = camera_matrix[0, 0], camera_matrix[1, 1]
    return IntrinsicsUncertainty(focal_rel=float(0.5 * (s[0] / fx + s[1] / fy)), principal_px=float(max(s[2], s[3])))
