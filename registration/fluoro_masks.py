"""Masks of fluoroscopy pixels that must not drive CT registration: markers, tools, metal, collimation."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from .fluoro_markers import FluoroDetections

__all__ = ["marker_mask", "metal_mask", "field_mask"]


def marker_mask(shape: tuple[int, int], detections: FluoroDetections, *, margin_px: float = 6.0) -> NDArray[np.bool_]:
    """True where a detected (or rejected) marker's ring or BBs lie, widened by ``margin_px``; (rows, columns)."""
    m = np.zeros(shape, np.uint8)
    w = max(1, int(round(2 * margin_px)))
    for marker in detections.markers:
        (cx, cy), (d1, d2), ang = marker.ring_ellipse
        cv2.ellipse(m, ((cx, cy), (d1, d2), ang), 1, w, cv2.LINE_8)
        for bb in marker.bbs:
            cv2.circle(m, (int(round(bb.center_px[0])), int(round(bb.center_px[1]))), int(round(bb.diameter_px / 2 + margin_px)), 1, -1)
    for r in detections.rejected:  # unidentified rings: blank a generous disc
        cv2.circle(m, (int(round(r.center_px[0])), int(round(r.center_px[1]))), int(round(8 * margin_px + 60)), 1, -1)
    return m.astype(bool)


def metal_mask(image_log: NDArray[np.float32], *, excess: float = 1.2, size_px: int = 41, margin_px: int = 4) -> NDArray[np.bool_]:
    """True where attenuation exceeds its local background (morphological opening) by more than ``excess``.

    Anatomy varies slowly at this scale; tungsten BBs, wires, K-wires and
    screws stand far above it.
    """
    img = np.asarray(image_log, np.float32)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size_px, size_px))
    top_hat = img - cv2.morphologyEx(img, cv2.MORPH_OPEN, k)
    m = (top_hat > excess).astype(np.uint8)
    if margin_px > 0:
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1)))
    return m.astype(bool)


def field_mask(shape: tuple[int, int], *, border_px: int = 8) -> NDArray[np.bool_]:
    """True on a frame of ``border_px`` round the detector edge (collimator and edge artefacts)."""
    m = np.zeros(shape, bool)
    if border_px > 0:
        m[:border_px] = m[-border_px:] = True
        m[:, :border_px] = m[:, -border_px:] = True
    return m
