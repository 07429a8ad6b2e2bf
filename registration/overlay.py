"""Overlays on fluoroscopy views (the CLI's ``--overlays`` and the daemon's overlay topic): the drill axis across the
whole image, its error cone, the detections, a title and a legend; optional marker masking.

The browser display draws the same from the streamed axis (service/display_static/display.js).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from .carm import CArmView
from .fluoro_markers import FluoroDetections
from .line import Line3D

__all__ = ["to_display", "draw_axis", "draw_detections", "annotate", "line_across_image", "axis_curve_px", "mask_markers",
           "AXIS_BGR", "CONE_BGR", "PLAN_BGR", "ENTRY_BGR", "OK_BGR", "ALARM_BGR", "STALE_BGR"]


def to_display(image_log: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Log-attenuation image -> 8-bit BGR, attenuation dark (as a radiograph is read)."""
    lo, hi = np.percentile(image_log, [0.5, 99.5])
    g = np.clip((image_log - lo) / max(hi - lo, 1e-6), 0, 1)
    return cv2.cvtColor(((1.0 - g) * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


# Okabe-Ito (colour-blind safe), BGR; the browser display uses the same (service/display_static/display.css).
AXIS_BGR = (66, 228, 240)      # yellow
CONE_BGR = (0, 159, 230)       # orange
PLAN_BGR = (233, 180, 86)      # sky blue
ENTRY_BGR = (167, 121, 204)    # reddish purple
OK_BGR = (115, 158, 0)         # bluish green
ALARM_BGR = (0, 94, 213)       # vermillion
STALE_BGR = (154, 154, 154)
_FONT = cv2.FONT_HERSHEY_SIMPLEX
CONE_REACH_MM = 400.0  # the cone is drawn this far either side of the working point


def line_across_image(view: CArmView, axis: Line3D) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Where the image of the (infinite) axis crosses the detector's border: two pixels (column, row), in the drill's direction.

    The image of a 3-D line is the 2-D line through the images of two of its points; clipped to the image
    rectangle (pixel centres from 0 to columns-1, edges half a pixel beyond). None when it misses the image.
    """
    a, b = view.project(np.vstack([axis.point_mm, axis.point_mm + 100.0 * axis.direction]))
    line = np.cross([a[0], a[1], 1.0], [b[0], b[1], 1.0])
    x0, y0, x1, y1 = -0.5, -0.5, view.columns - 0.5, view.rows - 0.5
    hits = []
    if abs(line[1]) > 1e-12:
        hits += [(x, -(line[0] * x + line[2]) / line[1]) for x in (x0, x1)]
    if abs(line[0]) > 1e-12:
        hits += [(-(line[1] * y + line[2]) / line[0], y) for y in (y0, y1)]
    hits = [np.array(h) for h in hits if x0 - 1e-6 <= h[0] <= x1 + 1e-6 and y0 - 1e-6 <= h[1] <= y1 + 1e-6]
    if len(hits) < 2:
        return None
    p, q = max(((p, q) for i, p in enumerate(hits) for q in hits[i + 1:]), key=lambda pq: float(np.linalg.norm(pq[0] - pq[1])))
    return (p, q) if (q - p) @ (b - a) >= 0 else (q, p)


# An image intensifier bends the image of a straight line: the axis is drawn through this many points across the image.
CURVE_POINTS = 65


def _project(view: CArmView, points_carm_mm: NDArray[np.float64], distortion_px: NDArray[np.float64] | None) -> NDArray[np.float64]:
    return view.distorted_px(view.project(points_carm_mm), distortion_px)


def _clip_to_image(view: CArmView, curve_px: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The part (K, 2) of a polyline that runs through the image, its ends cut at the border; None when it misses it.

    The curve is an intensifier's image of a line: it crosses the border at most twice.
    """
    lo, hi = np.array([-0.5, -0.5]), np.array([view.columns - 0.5, view.rows - 0.5])
    inside = np.all((curve_px >= lo) & (curve_px <= hi), axis=1)
    if not inside.any():
        return None
    i, j = int(np.argmax(inside)), len(inside) - 1 - int(np.argmax(inside[::-1]))
    kept = [curve_px[i:j + 1]]
    for k, (a, b) in ((0, (i - 1, i)), (1, (j + 1, j))):  # from the outside point to the inside one
        if 0 <= a < len(curve_px):
            p, q = curve_px[a], curve_px[b]
            d = q - p
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.nanmax(np.concatenate([np.where(p < lo, (lo - p) / d, 0.0), np.where(p > hi, (hi - p) / d, 0.0)]))
            cut = p + float(np.clip(t, 0.0, 1.0)) * d
            kept.insert(0 if k == 0 else len(kept), cut[None])
    return np.vstack(kept)


def axis_curve_px(view: CArmView, axis: Line3D, distortion_px: NDArray[np.float64] | None = None) -> NDArray[np.float64] | None:
    """The image of the (infinite) axis across the detector, in the drill's direction: (K, 2) pixels (column, row).

    Without ``distortion_px`` the two border points of :func:`line_across_image`. With an intensifier's distortion
    (2,) (pincushion and S shift at the field's corner, px, as the joint solve estimates it) the line's image is
    bent: :data:`CURVE_POINTS` points along it, its ends on the border. None when it misses the image.
    """
    seg = line_across_image(view, axis)
    if distortion_px is None:
        return None if seg is None else np.vstack(seg)
    # The ideal line a little beyond the border either side: pincushion pulls its ends in, barrel pushes them out.
    a, b = view.project(np.vstack([axis.point_mm, axis.point_mm + 100.0 * axis.direction]))
    u = (b - a) / np.linalg.norm(b - a)
    c = view.center_px
    mid = a + ((c - a) @ u) * u  # the line's point nearest the centre
    reach = 1.2 * view.corner_radius_px
    ideal = mid + np.linspace(-reach, reach, CURVE_POINTS)[:, None] * u
    return _clip_to_image(view, view.distorted_px(ideal, distortion_px))


def _px(points: NDArray[np.float64]) -> NDArray[np.int32]:
    """Pixel coordinates to cv2's fixed point (4 fractional bits): sub-pixel lines, as the browser draws them."""
    return np.round(np.atleast_2d(points) * 16).astype(np.int32)


def _thickness(bgr: NDArray[np.uint8]) -> int:
    return max(2, round(bgr.shape[1] / 220))  # ~4 px on a 976 px view: legible when shown on a monitor across the room


def draw_axis(bgr: NDArray[np.uint8], view: CArmView, axis: Line3D, *, cone_half_angle_deg: float, position_error_mm: float = 0.0,
              stale: bool = False, distortion_px: NDArray[np.float64] | None = None) -> NDArray[np.uint8]:
    """The axis across the whole image (yellow, outlined), its error cone (orange band) and its working point.

    The cone is the predicted position error at ``axis.point_mm`` widening by ``cone_half_angle_deg`` either side
    of it, in the plane of the axis and the beam; ``stale`` draws everything grey (an axis that is not live).
    ``distortion_px`` (2,): the view's intensifier distortion as the registration estimated it (pincushion and S
    shift at the field's corner, px); everything is drawn where that image intensifier shows it.
    """
    out = bgr.copy()
    lw = _thickness(out)
    d = axis.direction
    s = np.arange(-CONE_REACH_MM, CONE_REACH_MM + 1e-9, 20.0)
    centres = axis.at(s)
    side = np.cross(d, centres - view.source_position_mm)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    r = (position_error_mm + np.abs(s) * np.tan(np.radians(cone_half_angle_deg)))[:, None]
    ahead = view.depth_mm(centres) > 1.0  # points behind the source have no image
    if ahead.sum() > 1:
        upper, lower = _project(view, (centres + r * side)[ahead], distortion_px), _project(view, (centres - r * side)[ahead], distortion_px)
        band = out.copy()
        cv2.fillPoly(band, [_px(np.vstack([upper, lower[::-1]]))], STALE_BGR if stale else CONE_BGR, cv2.LINE_AA, 4)
        out = cv2.addWeighted(band, 0.3, out, 0.7, 0.0)
        for edge in (upper, lower):
            cv2.polylines(out, [_px(edge)], False, STALE_BGR if stale else CONE_BGR, max(1, lw // 2), cv2.LINE_AA, 4)
    curve = axis_curve_px(view, axis, distortion_px)
    if curve is not None and len(curve) >= 2:
        cv2.polylines(out, [_px(curve)], False, (0, 0, 0), lw * 2, cv2.LINE_AA, 4)
        cv2.polylines(out, [_px(curve)], False, STALE_BGR if stale else AXIS_BGR, lw, cv2.LINE_AA, 4)
        # An arrowhead near the far border: the way the drill advances.
        u = (curve[-1] - curve[-2]) / max(float(np.linalg.norm(curve[-1] - curve[-2])), 1e-9)
        tip = curve[-1] - 4 * lw * u
        k = 6 * lw
        tri = np.array([tip, tip - k * u + 0.5 * k * np.array([-u[1], u[0]]), tip - k * u - 0.5 * k * np.array([-u[1], u[0]])])
        cv2.fillPoly(out, [_px(tri)], STALE_BGR if stale else AXIS_BGR, cv2.LINE_AA, 4)
    if view.depth_mm(axis.point_mm[None])[0] > 1.0:
        c = _px(_project(view, axis.point_mm[None], distortion_px))[0]
        cv2.circle(out, tuple(c), 2 * lw * 16, STALE_BGR if stale else ENTRY_BGR, -1, cv2.LINE_AA, 4)
        cv2.circle(out, tuple(c), 2 * lw * 16, (0, 0, 0), max(1, lw // 2), cv2.LINE_AA, 4)
    return out


def draw_detections(bgr: NDArray[np.uint8], detections: FluoroDetections) -> NDArray[np.uint8]:
    """Identified markers (ring and BBs, bluish green, with their id) and candidates refused (vermillion cross, with why)."""
    out = bgr.copy()
    scale = out.shape[1] / 976
    for m in detections.markers:
        (cx, cy), (d1, d2), ang = m.ring_ellipse
        cv2.ellipse(out, ((cx, cy), (d1, d2), ang), OK_BGR, 2, cv2.LINE_AA)
        for b in m.bbs:
            cv2.circle(out, (int(round(b.center_px[0])), int(round(b.center_px[1]))), int(round(b.diameter_px / 2 + 2)), OK_BGR, 1, cv2.LINE_AA)
        _text(out, f"#{m.marker_id}", (int(cx + d1 / 2 + 4), int(cy)), 0.8 * scale, OK_BGR)
    for r in detections.rejected:
        c = (int(r.center_px[0]), int(r.center_px[1]))
        cv2.drawMarker(out, c, ALARM_BGR, cv2.MARKER_TILTED_CROSS, int(24 * scale), 3)
        _text(out, f"not used: {r.reason}"[:48], (c[0] + int(16 * scale), c[1] + int(6 * scale)), 0.55 * scale, ALARM_BGR)
    return out


def _text(img: NDArray[np.uint8], text: str, org: tuple[int, int], scale: float, colour, thickness: int | None = None) -> None:
    """Text with a black outline, readable on bone and on air."""
    t = thickness or max(1, round(2 * scale))
    cv2.putText(img, text, org, _FONT, scale, (0, 0, 0), t + 3, cv2.LINE_AA)
    cv2.putText(img, text, org, _FONT, scale, colour, t, cv2.LINE_AA)


def annotate(bgr: NDArray[np.uint8], *, view_name: str, stamp_ns: int | None = None, predicted_error: tuple[float, float] | None = None,
             legend: bool = True, plan: bool = False) -> NDArray[np.uint8]:
    """A title strip (view, time of the shot, predicted error in mm and deg) above the image, and a legend in its corner."""
    import datetime as _dt

    h, w = bgr.shape[:2]
    scale = w / 976
    strip = np.zeros((int(44 * scale), w, 3), np.uint8)
    title = f"view {view_name}"
    if stamp_ns is not None:
        title += "   " + _dt.datetime.fromtimestamp(stamp_ns / 1e9).strftime("%H:%M:%S")
    if predicted_error is not None:
        title += f"   predicted error {predicted_error[0]:.1f} mm, {predicted_error[1]:.1f} deg"
    _text(strip, title, (int(8 * scale), int(31 * scale)), 0.9 * scale, (255, 255, 255))
    out = np.vstack([strip, bgr])
    if legend:
        items = [("drill axis", AXIS_BGR), ("error cone (95 %)", CONE_BGR), ("working point", ENTRY_BGR), ("markers", OK_BGR)]
        if plan:
            items.insert(2, ("plan, corridor", PLAN_BGR))
        y0 = out.shape[0] - int((len(items) * 26 + 10) * scale)
        box = out[y0:, : int(250 * scale)]
        box[:] = (box * 0.35).astype(np.uint8)
        for i, (name, colour) in enumerate(items):
            y = y0 + int((22 + 26 * i) * scale)
            cv2.line(out, (int(10 * scale), y - int(6 * scale)), (int(46 * scale), y - int(6 * scale)), colour, max(2, round(5 * scale)), cv2.LINE_AA)
            _text(out, name, (int(56 * scale), y), 0.65 * scale, (255, 255, 255))
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
