"""Known-component 3D-2D registration of a marker: DRR of its radio-opaque design, gradient information, CMA-ES.

The marker model (tungsten BBs and the wire ring) is projected analytically
into a region of interest of each view (sphere chord lengths for the BBs, the
ring as an anti-aliased projected tube); the similarity is Pluim's gradient
information summed over views; CMA-ES (``cma``) refines the 6-DOF pose from
the point-based solution of :mod:`marker_pose`, as the reference does from its
feature-based initialisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .carm import CArmView
from .markers import MarkerDesign
from .transforms import apply, from_rotvec

__all__ = ["render_marker_drr", "gradient_information", "KcrResult", "refine_marker_pose"]

MU_TUNGSTEN = 7.0


def render_marker_drr(design: MarkerDesign, carm_from_marker: NDArray[np.float64], view: CArmView, roi: tuple[int, int, int, int]) -> NDArray[np.float32]:
    """Line integrals (rows, cols) of the marker's tungsten in ``roi`` = (col0, row0, col1, row1)."""
    c0, r0, c1, r1 = roi
    out = np.zeros((r1 - r0, c1 - c0), np.float32)
    centres = apply(carm_from_marker, design.bb_centers_mm)
    px = view.project(centres) - [c0, r0]
    mag = view.magnification(centres)
    ps = view.pixel_spacing_mm[1]
    yy, xx = np.mgrid[0 : r1 - r0, 0 : c1 - c0].astype(np.float32)
    for (u, v), g, d in zip(px, mag, design.bb_diameters_mm):
        rad = d / 2 * g / ps
        x0, x1 = int(max(u - rad - 2, 0)), int(min(u + rad + 3, c1 - c0))
        y0, y1 = int(max(v - rad - 2, 0)), int(min(v + rad + 3, r1 - r0))
        if x0 >= x1 or y0 >= y1:
            continue
        dist2 = (xx[y0:y1, x0:x1] - u) ** 2 + (yy[y0:y1, x0:x1] - v) ** 2
        out[y0:y1, x0:x1] += MU_TUNGSTEN * 2.0 * np.sqrt(np.maximum(rad * rad - dist2, 0.0)) * ps / g
    ring = view.project(apply(carm_from_marker, design.ring_points_mm(180))) - [c0, r0]
    g = float(np.mean(view.magnification(carm_from_marker[:3, 3])))
    canvas = np.zeros_like(out)
    shift = 4
    pts = np.round(ring * (1 << shift)).astype(np.int32).reshape(-1, 1, 2)
    width = max(1, int(round(design.ring_wire_diameter_mm * g / ps)))
    cv2.polylines(canvas, [pts], True, float(MU_TUNGSTEN * design.ring_wire_diameter_mm * 0.785), width, cv2.LINE_AA, shift)
    return out + canvas


def _gradients(img: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    s = cv2.GaussianBlur(img, (0, 0), 1.0)
    return cv2.Sobel(s, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(s, cv2.CV_32F, 0, 1, ksize=3)


def gradient_information(fixed_grad, moving: NDArray[np.float32]) -> float:
    """Pluim's gradient information: sum of w(angle) * min(|g_f|, |g_m|), w = (cos 2a + 1) / 2."""
    fx, fy = fixed_grad
    mx, my = _gradients(moving)
    nf, nm = np.hypot(fx, fy), np.hypot(mx, my)
    cos = (fx * mx + fy * my) / np.maximum(nf * nm, 1e-6)
    w = cos * cos  # (cos 2a + 1) / 2 = cos^2 a
    return float(np.sum(w * np.minimum(nf, nm)))


@dataclass(frozen=True, kw_only=True)
class KcrResult:
    carm_from_marker: NDArray[np.float64]
    similarity: float
    initial_similarity: float
    evaluations: int
    converged: bool


def refine_marker_pose(
    design: MarkerDesign,
    carm_from_marker0: NDArray[np.float64],
    views: list[CArmView],
    images_log: list[NDArray[np.float32]],
    *,
    sigma_mm: float = 0.5,
    sigma_deg: float = 1.0,
    max_evaluations: int = 300,
    seed: int = 0,
) -> KcrResult:
    """CMA-ES maximisation of the summed gradient information over views, around the initial pose."""
    rois, fixed = [], []
    for view, img in zip(views, images_log):
        px = view.project(apply(carm_from_marker0, design.ring_points_mm(64)))
        c0, r0 = np.floor(px.min(axis=0)).astype(int) - 12
        c1, r1 = np.ceil(px.max(axis=0)).astype(int) + 12
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, view.columns), min(r1, view.rows)
        rois.append((c0, r0, c1, r1))
        roi_img = np.asarray(img[r0:r1, c0:c1], np.float32)
        # Remove the smooth anatomy under the marker so its gradients do not compete.
        fixed.append(_gradients(roi_img - cv2.GaussianBlur(roi_img, (0, 0), 15.0)))
    scale = np.array([np.radians(sigma_deg)] * 3 + [sigma_mm] * 3)

    def pose(x):
        # Perturb about the marker centre, in frame C.
        c = carm_from_marker0[:3, 3]
        delta = from_rotvec(x[:3] * scale[:3], x[3:] * scale[3:])
        delta[:3, 3] += c - delta[:3, :3] @ c
        return delta @ carm_from_marker0

    def cost(x):
        t = pose(np.asarray(x))
        return -sum(gradient_information(f, render_marker_drr(design, t, v, roi)) for f, v, roi in zip(fixed, views, rois))

    initial = -cost(np.zeros(6))
    import cma  # ~2 s of matplotlib and scipy.stats on import: only when a pose is refined

    es = cma.CMAEvolutionStrategy(np.zeros(6), 1.0, {"maxfevals": max_evaluations, "seed": seed + 1, "verbose": -9, "tolx": 1e-3})
    es.optimize(cost)
    best = np.asarray(es.result.xbest)
    return KcrResult(carm_from_marker=pose(best), similarity=float(-es.result.fbest), initial_similarity=initial, evaluations=int(es.result.evaluations), converged=bool(es.result.fbest <= -initial))
