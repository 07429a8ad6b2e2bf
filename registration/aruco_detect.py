"""ArUco detection with one return convention whatever OpenCV's version.

OpenCV 5.0 and earlier return ``ids=None`` when a frame holds no tag; 5.1 returns empty arrays. Every caller in the
product goes through :func:`detect_aruco`, which gives both as plain lists, so "no tag" is one case, not two.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray


def detect_aruco(detector: cv2.aruco.ArucoDetector, gray: NDArray[np.uint8]) -> tuple[list[int], list[NDArray[np.float64]]]:
    """Run ``detector`` on a grey (H, W) uint8 frame: (ids, corners), the i-th corners (4, 2) px in the detector's
    order (clockwise from the tag's top-left); both empty when no tag is found."""
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return [], []
    return [int(i) for i in np.asarray(ids).ravel()], [np.asarray(c, np.float64).reshape(4, 2) for c in corners]
