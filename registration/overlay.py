"""Overlays on fluoroscopy views: the drill axis, its error cone, marker detections, optional marker masking."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from .carm import CArmView
from .fluoro_markers import FluoroDetections
from .line import Line3D

__all__ = ["to_display", "draw_axis", "draw_detections", "mask_markers"]


def to_display(image_log: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Log-attenuation image -> 8-bit BGR, attenuation dark (as a radiograph is read)."""
    lo, hi = np.percentile(image_log, [0.5, 99.5])
    g = np.clip((image_log - lo) / max(hi - lo, 1e-6), 0, 1)
    return cv2.cvtColor(((1.0 - g) * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def _segment(view: CArmView, a: NDArray[np.float64], b: NDArray[np.float64]) -> tuple[tuple[int, int], tuple[int, int]]:
    pa, pb = view.project(np.vstack([a, b]))
    return (int(round(pa[0])), int(round(pa[1]))), (int(round(pb[0])), int(round(pb[1])))


def draw_axis(bgr: NDArray[np.uint8], view: CArmView, axis: Line3D, *, cone_half_angle_deg: float, length_mm: float = 150.0, near_mm: float = -60.0) -> NDArray[np.uint8]:
    """Draw the axis (cyan) from ``near_mm`` to ``length_mm`` along it, and its error cone (yellow)."""
    out = bgr.copy()
    start, end = axis.at([near_mm])[0], axis.at([length_mm])[0]
    a, b = _segment(view, start, end)
    # The cone: lines at +/- the half angle in the plane containing the axis and the view's beam.
    _, source_from_carm = view.decompose()
    beam = source_from_carm[2, :3]
    side = np.cross(axis.direction, beam)
    if np.linalg.norm(side) > 1e-9:
        side /= np.linalg.norm(side)
        for sgn in (-1.0, 1.0):
            tip = end + sgn * side * np.tan(np.radians(cone_half_angle_deg)) * (length_mm - 0.0)
            c, d = _segment(view, axis.at([0.0])[0], tip)
            cv2.line(out, c, d, (0, 215, 255), 1, cv2.LINE_AA)
    cv2.line(out, a, b, (255, 255, 0), 2, cv2.LINE_AA)
    return out


def draw_detections(bgr: NDArray[np.uint8], detections: FluoroDetections) -> NDArray[np.uint8]:
    out = bgr.copy()
    for m in detections.markers:
        (cx, cy), (d1, d2), ang = m.ring_ellipse
        cv2.ellipse(out, ((cx, cy), (d1, d2), ang), (0, 200, 0), 1, cv2.LINE_AA)
        for b in m.bbs:
            cv2.circle(out, (int(round(b.center_px[0])), int(round(b.center_px[1]))), int(round(b.diameter_px / 2 + 2)), (0, 0, 255), 1, cv2.LINE_AA)
        cv2.putText(out, str(m.marker_id), (int(cx + d1 / 2), int(cy)), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 200, 0), 1, cv2.LINE_AA)
    for r in detections.rejected:
        cv2.drawMarker(out, (int(r.center_px[0]), int(r.center_px[1])), (0, 0, 255), cv2.MARKER_TILTED_CROSS, 24, 2)
    return out


def mask_markers(image_log: NDArray[np.float32], detections: FluoroDetections, *, ring_width_px: float = 9.0) -> NDArray[np.float32]:
    """Replace the known BB and wire pixels by a median of their surroundings (the reference's masking)."""
    mask = np.zeros(image_log.shape, np.uint8)
    for m in detections.markers:
        (cx, cy), (d1, d2), ang = m.ring_ellipse
        cv2.ellipse(mask, ((cx, cy), (d1, d2), ang), 255, int(ring_width_px))
        for b in m.bbs:
            cv2.circle(mask, (int(round(b.center_px[0])), int(round(b.center_px[1]))), int(np.ceil(b.diameter_px / 2 + 3)), 255, -1)
    med = cv2.medianBlur(np.clip(image_log * 1000, 0, 65535).astype(np.uint16), 5).astype(np.float32) / 1000
    out = image_log.copy()
    # Grow the median inwards over the mask a few times so wide BBs are filled from outside.
    filled = np.where(mask > 0, np.nan, image_log)
    for _ in range(12):
        valid = ~np.isnan(filled)
        if valid.all():
            break
        blur = cv2.blur(np.nan_to_num(filled), (7, 7))
        weight = cv2.blur(valid.astype(np.float32), (7, 7))
        grow = (~valid) & (weight > 0.2)
        filled[grow] = blur[grow] / weight[grow]
    out[mask > 0] = np.nan_to_num(filled, nan=float(np.median(med)))[mask > 0]
    return out
