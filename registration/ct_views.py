"""The surgeon's CT views (reference Fig. 8b): axial, coronal and sagittal slices through the axis's entry point
and an oblique slice along the axis, with the drill axis, its error cone, the planned trajectory and corridor drawn.

Slices are resampled from the CT in the patient frame (LPS) in radiological
display: axial and coronal show the patient's right on the image's left,
anterior up (axial) and head up (coronal, sagittal, oblique).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from .line import Line3D
from .overlay import ALARM_BGR, AXIS_BGR, CONE_BGR, OK_BGR, PLAN_BGR
from .transforms import apply
from .volume import Volume

__all__ = ["PlannedTrajectory", "SlicePlane", "slice_planes", "render_ct_views", "compose_views"]



@dataclass(frozen=True, kw_only=True)
class PlannedTrajectory:
    name: str
    entry_mm: NDArray[np.float64]
    target_mm: NDArray[np.float64]
    radius_mm: float


@dataclass(frozen=True, kw_only=True)
class SlicePlane:
    """A plane through ``centre_mm`` (3,), image columns along ``right`` (3,), rows along ``down`` (3,)."""

    name: str
    centre_mm: NDArray[np.float64]
    right: NDArray[np.float64]
    down: NDArray[np.float64]
    labels: tuple[str, str, str, str]  # left, right, top, bottom edge letters


def _unit(v: ArrayLike) -> NDArray[np.float64]:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def slice_planes(axis_ct: Line3D, centre_mm: ArrayLike) -> list[SlicePlane]:
    c = np.asarray(centre_mm, dtype=np.float64)
    x, y, z = np.eye(3)
    d = axis_ct.direction
    # Oblique: the axis runs left to right; rows along the direction across it nearest the patient's feet.
    down = -z - (-z @ d) * d
    if np.linalg.norm(down) < 1e-3:
        down = y - (y @ d) * d
    return [
        SlicePlane(name="axial", centre_mm=c, right=x, down=y, labels=("R", "L", "A", "P")),
        SlicePlane(name="coronal", centre_mm=c, right=x, down=-z, labels=("R", "L", "H", "F")),
        SlicePlane(name="sagittal", centre_mm=c, right=y, down=-z, labels=("A", "P", "H", "F")),
        SlicePlane(name="oblique", centre_mm=c, right=d, down=_unit(down), labels=("", "", "", "")),
    ]


class _Canvas:
    def __init__(self, plane: SlicePlane, size_px: int, fov_mm: float) -> None:
        self.plane, self.size, self.px = plane, size_px, fov_mm / size_px

    def to_px(self, points_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        rel = np.atleast_2d(points_mm) - self.plane.centre_mm
        half = self.size / 2 - 0.5
        return np.stack([rel @ self.plane.right / self.px + half, rel @ self.plane.down / self.px + half], axis=1)

    def points(self) -> NDArray[np.float64]:
        g = (np.arange(self.size) - (self.size / 2 - 0.5)) * self.px
        cc, rr = np.meshgrid(g, g)
        return self.plane.centre_mm + cc[..., None] * self.plane.right + rr[..., None] * self.plane.down

    def segment(self, img, a, b, colour, thickness=1) -> None:
        p = np.round(self.to_px(np.vstack([a, b])) * 16).astype(np.int64)
        cv2.line(img, tuple(int(v) for v in p[0]), tuple(int(v) for v in p[1]), colour, thickness, cv2.LINE_AA, 4)


def _slice(ct: Volume, canvas: _Canvas, window: tuple[float, float]) -> NDArray[np.uint8]:
    pts = canvas.points().reshape(-1, 3)
    ijk = apply(ct.voxel_from_patient, pts)
    hu = ndimage.map_coordinates(np.asarray(ct.data, np.float32), ijk[:, ::-1].T, order=1, mode="constant", cval=-1000.0)
    level, width = window
    g = np.clip((hu - (level - width / 2)) / width, 0, 1).reshape(canvas.size, canvas.size)
    return cv2.cvtColor((g * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def render_ct_views(
    ct: Volume,
    *,
    axis_ct: Line3D,
    centre_mm: ArrayLike,
    cone_half_angle_deg: float,
    plan: list[PlannedTrajectory] | None = None,
    size_px: int = 360,
    fov_mm: float = 180.0,
    window: tuple[float, float] = (400.0, 1800.0),
    length_mm: float = 120.0,
) -> dict[str, NDArray[np.uint8]]:
    """BGR images (size_px, size_px, 3) by plane name; the axis is drawn from 40 mm before ``centre_mm`` to ``length_mm`` past it.

    In the oblique slice everything drawn is projected onto its plane; in the
    orthogonal slices the axis and plan are projected too, and the axis's
    crossing of the slice is ringed.
    """
    c = np.asarray(centre_mm, dtype=np.float64)
    start = axis_ct.closest_point(c) - 40.0 * axis_ct.direction
    end = axis_ct.closest_point(c) + length_mm * axis_ct.direction
    out: dict[str, NDArray[np.uint8]] = {}
    for plane in slice_planes(axis_ct, c):
        canvas = _Canvas(plane, size_px, fov_mm)
        img = _slice(ct, canvas, window)
        for t in plan or []:
            canvas.segment(img, t.entry_mm, t.target_mm, PLAN_BGR, 1)
            td = _unit(t.target_mm - t.entry_mm)
            across = plane.down if plane.name == "oblique" else np.cross(td, _plane_normal(plane))
            if np.linalg.norm(across) > 1e-6:
                across = _unit(across - (across @ td) * td)
                for sgn in (-1.0, 1.0):
                    canvas.segment(img, t.entry_mm + sgn * t.radius_mm * across, t.target_mm + sgn * t.radius_mm * across, PLAN_BGR, 1)
        # Error cone about the axis, opening from the working point, in the slice's plane.
        n = _plane_normal(plane)
        side = np.cross(axis_ct.direction, n)
        if np.linalg.norm(side) > 1e-6:
            side = _unit(side)
            apex = axis_ct.closest_point(c)
            for sgn in (-1.0, 1.0):
                tip = end + sgn * side * np.tan(np.radians(cone_half_angle_deg)) * length_mm
                canvas.segment(img, apex, tip, CONE_BGR, 1)
        canvas.segment(img, start, end, (0, 0, 0), 5)
        canvas.segment(img, start, end, AXIS_BGR, 3)
        denom = axis_ct.direction @ n
        if plane.name != "oblique" and abs(denom) > 1e-6:
            hit = axis_ct.point_mm + ((c - axis_ct.point_mm) @ n / denom) * axis_ct.direction
            p = canvas.to_px(hit)[0]
            cv2.circle(img, (int(round(p[0])), int(round(p[1]))), 6, AXIS_BGR, 1, cv2.LINE_AA)
        _label(img, plane)
        out[plane.name] = img
    return out


def _plane_normal(plane: SlicePlane) -> NDArray[np.float64]:
    return _unit(np.cross(plane.right, plane.down))


def _label(img: NDArray[np.uint8], plane: SlicePlane) -> None:
    h, w = img.shape[:2]
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(img, plane.name, (6, 18), font, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    left, right, top, bottom = plane.labels
    for text, org in ((left, (4, h // 2)), (right, (w - 14, h // 2)), (top, (w // 2, 32)), (bottom, (w // 2, h - 6))):
        if text:
            cv2.putText(img, text, org, font, 0.45, (200, 200, 200), 1, cv2.LINE_AA)


def compose_views(views: dict[str, NDArray[np.uint8]], *, caption: str = "", verdict: dict | None = None) -> NDArray[np.uint8]:
    """2 x 2 mosaic (axial, coronal / sagittal, oblique) with a legend strip, and the verdict above it when given.

    ``verdict``: ``{"trajectory", "breach", "min_clearance_mm", "min_clearance_along_mm" (optional)}``, a
    conformance result as the CLI report and ``drillnav/axis/ct`` give it; drawn as a wide bar, vermillion for a
    breach and bluish green when clear, so it is read before the slices.
    """
    order = [views[k] for k in ("axial", "coronal", "sagittal", "oblique")]
    grid = np.vstack([np.hstack(order[:2]), np.hstack(order[2:])])
    w = grid.shape[1]
    legend = np.zeros((30, w, 3), np.uint8)
    x = 8
    for name, colour in (("drill axis", AXIS_BGR), ("error cone", CONE_BGR), ("plan, corridor", PLAN_BGR)):
        cv2.line(legend, (x, 15), (x + 30, 15), colour, 4, cv2.LINE_AA)
        cv2.putText(legend, name, (x + 38, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
        x += 48 + int(cv2.getTextSize(name, cv2.FONT_HERSHEY_SIMPLEX, 0.55, 1)[0][0]) + 16
    if caption:
        cv2.putText(legend, caption, (x + 10, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (200, 200, 200), 1, cv2.LINE_AA)
    parts = [grid, legend]
    if verdict is not None:
        bar = np.zeros((44, w, 3), np.uint8)
        breach = bool(verdict.get("breach"))
        bar[:] = ALARM_BGR if breach else OK_BGR
        mc = verdict.get("min_clearance_mm")
        text = f"{'BREACH' if breach else 'CLEAR'} ({verdict.get('trajectory', '?')})"
        text += ": axis misses the bone" if mc is None else f": min clearance {mc:.1f} mm"
        if verdict.get("min_clearance_along_mm") is not None:
            text += f" at {verdict['min_clearance_along_mm']:.0f} mm into bone"
        cv2.putText(bar, text, (10, 31), cv2.FONT_HERSHEY_SIMPLEX, 0.9, (255, 255, 255), 2, cv2.LINE_AA)
        parts.insert(0, bar)
    return np.vstack(parts)
