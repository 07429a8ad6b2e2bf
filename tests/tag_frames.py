"""Synthetic camera frames of one ArUco tag, optionally with a glove's grey over part of it, shared by the tag tests."""

import cv2
import numpy as np


def synthetic_tag_frame(corners_px, *, aruco_id, glove_tag_xy=None, size=(480, 640), seed=0, blur_px=1.0, gain=1.0):
    """A grayscale frame (H, W) with one DICT_6X6_250 tag at ``corners_px`` (4, 2) (TL, TR, BR, BL, its black border's
    outer corners) on a white base over a mottled background; ``glove_tag_xy``: a polygon in the tag's unit square
    (x right, y down) painted in a glove's grey over it. Blurred as a lens blurs (Gaussian, ``blur_px``), then
    exposed with ``gain`` (over about 1.1 the white base clips at 255)."""
    rng = np.random.default_rng(seed)
    h, w = size
    frame = cv2.GaussianBlur(rng.normal(110, 25, size=(h, w)), (0, 0), 6)
    tag = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250), aruco_id, 800).astype(np.float64)
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)
    to_frame = cv2.getPerspectiveTransform(unit, np.asarray(corners_px, dtype=np.float32))
    base = cv2.perspectiveTransform(((unit - 0.5) * 1.6 + 0.5).reshape(-1, 1, 2), to_frame).reshape(-1, 2)
    cv2.fillConvexPoly(frame, np.round(base * 16).astype(np.int32), 235.0, lineType=cv2.LINE_AA, shift=4)
    warped = cv2.warpPerspective(tag, to_frame @ np.diag([1 / 800, 1 / 800, 1]), (w, h), flags=cv2.INTER_AREA, borderValue=-1.0)
    inside = cv2.warpPerspective(np.ones_like(tag), to_frame @ np.diag([1 / 800, 1 / 800, 1]), (w, h), flags=cv2.INTER_AREA)
    frame = np.where(inside > 0.5, np.clip(warped, 0, 255) * 0.85 + 25, frame)
    if glove_tag_xy is not None:
        glove = cv2.perspectiveTransform(np.asarray(glove_tag_xy, dtype=np.float32).reshape(-1, 1, 2), to_frame).reshape(-1, 2)
        cv2.fillPoly(frame, [np.round(glove * 16).astype(np.int32)], 185.0, lineType=cv2.LINE_AA, shift=4)
    frame = gain * cv2.GaussianBlur(frame, (0, 0), blur_px) + rng.normal(0, 2.0, size=(h, w))
    return np.clip(frame, 0, 255).astype(np.uint8)


def tag_points_px(corners_px, tag_xy):
    """Points (n, 2) px of a tag at ``corners_px`` (4, 2) (TL, TR, BR, BL) given in its unit square ``tag_xy`` (n, 2)
    (x right, y down; 0-1 across the black border, beyond it on the white base)."""
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)
    to_frame = cv2.getPerspectiveTransform(unit, np.asarray(corners_px, dtype=np.float32))
    return cv2.perspectiveTransform(np.asarray(tag_xy, dtype=np.float32).reshape(-1, 1, 2), to_frame).reshape(-1, 2).astype(np.float64)
