"""Where a ring seen open lies: its wire's shadow measured across the ring, at points all around it.

A marker's BBs lie within 15 mm of its centre; its wire ring runs at 24 mm, and its shadow is a thin bright ellipse
some 700 px around. Seen open (face-on or tilted, not edge-on) it measures the marker's scale in the image, its depth
along the beam, over a radius half as large again as the BBs' and at many points instead of seven: the part of a
marker's pose one view fixes worst, and the one a constellation of markers stuck flat and seen face-on needs to fix its
tilt across the beam. Given a pose that already places the marker within a few pixels (a joint solve), the image is
sampled across the predicted ellipse at ``ANCHORS`` points around it, each over a short arc, and the profile is slid
against the marker's own predicted profile there (its wire, each ray weighted by its path length through it; the
straight-line trend of the anatomy beneath taken out): the shift that matches best, refined to a fraction of a pixel, is
how far the wire lies across the predicted ellipse at that point. Each is a row of the joint solve like an edge-on
ring's stroke (:mod:`.edge_on_ring`): the anchor's image along the ellipse's normal, with its noise.

Pure math: numpy, scipy and OpenCV's sampling.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .carm import CArmView
from .edge_on_ring import ncc_with_trend
from .markers import MarkerDesign
from .transforms import apply

__all__ = ["RingOutline", "measure_ring_outline", "ANCHORS", "OPEN_RING_RATIO", "OUTLINE_SIGMA_PX"]

# A ring whose projected ellipse is at least this open (minor over major half-axis) is measured around its outline;
# flatter ones (down to EDGE_ON_STROKE_RATIO) are strokes, and in between the wire's two sides crowd each other.
OPEN_RING_RATIO = 0.35
ANCHORS = 32
# Each anchor's profile is averaged over this much of the ring either side of it (px along the ellipse).
ARC_HALF_PX = 4.0
# How far across the ellipse the wire is looked for (px, either sense), the profile's step and its margin either
# side of the wire (px).
SEARCH_PX = 5.0
STEP_PX = 0.25
MARGIN_PX = 4.0
# A point is taken where its profile matches the predicted one this well (normalised correlation). Where another
# edge crosses the profile (a collimator's shadow, a K-wire, a retractor, a BB) the match still reaches 0.8-0.98 a
# pixel or more off: on the study's degraded scenes (every degradation but the real CT, seeds 31000-31003, every view
# pair, 2263 points measured at the true poses), points matched at 0.8-0.95 erred by 2.0-3.2 px rms, at 0.95-0.98 by
# 0.42 px, at 0.98 or more by 0.07 px (2071 points, none over 0.5 px). Taken down to 0.8, a point a K-wire crosses
# moved up to 1.0 px (tests/test_ring_outline.py).
MIN_CORRELATION = 0.98
# The blurs (px, 1 sigma, a Gaussian's) the wire's profile is matched at, the ring's best taken: with the bare profile
# alone, a detector blurring the twin's images 1.5 px more matched at a median 0.93-0.95, and no point was taken.
TEMPLATE_BLURS_PX = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5)
# The noise (px, 1 sigma) of one point across the ellipse.
OUTLINE_SIGMA_PX = 0.5


@dataclass(frozen=True, kw_only=True)
class RingOutline:
    """An open ring's wire measured across its ellipse at points around it.

    anchors_mm : (K, 3) the points of the ring (marker frame) whose images the measurements place.
    normals : (K, 2) the unit image directions across the ellipse there (outwards).
    offsets_px : (K,) where each anchor's image lies along its normal (``normal @ uv``), as measured.
    predicted_px : (K,) the same at the pose the ring was measured from.
    correlations : (K,) the normalised correlation of each measured and predicted profile at the match.
    sigmas_px : (K,) each measurement's noise (1 sigma) along its normal.
    """

    anchors_mm: NDArray[np.float64]
    normals: NDArray[np.float64]
    offsets_px: NDArray[np.float64]
    predicted_px: NDArray[np.float64]
    correlations: NDArray[np.float64]
    sigmas_px: NDArray[np.float64]


def measure_ring_outline(image_log: NDArray[np.floating], view: CArmView, carm_from_marker: NDArray[np.float64], design: MarkerDesign, *,
                         distortion_px: NDArray[np.float64] | None = None, avoid_px: NDArray[np.float64] | None = None,
                         avoid_radius_px: float | NDArray[np.float64] = 0.0, anchors: int = ANCHORS, search_px: float = SEARCH_PX) -> RingOutline | None:
    """``design``'s ring in the image (log attenuation, bright where dense) near where ``carm_from_marker`` (4, 4) puts
    it (moved by the view's intensifier ``distortion_px`` (2,) where estimated), measured across its ellipse at
    ``anchors`` points around it: those inside the image, farther than ``avoid_radius_px`` (a number, or (M,) one per
    point) from every point of ``avoid_px`` (M, 2) (other shadows: the marker's neighbours), matched unambiguously.
    None where the ring is not open (:data:`OPEN_RING_RATIO`) or no point is taken."""
    def image_of(points_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        return view.distorted_px(view.project(apply(carm_from_marker, points_mm)), distortion_px)

    t = np.linspace(0, 2 * np.pi, anchors, endpoint=False)
    r, c = design.ring_radius_mm, np.asarray(design.ring_center_mm, dtype=np.float64)

    def ring_at(angles: NDArray[np.float64]) -> NDArray[np.float64]:
        return c + r * np.stack([np.cos(angles), np.sin(angles), np.zeros(len(angles))], axis=1)

    ring_mm = ring_at(t)
    ring_px = image_of(ring_mm)
    spread = np.linalg.svd(ring_px - ring_px.mean(axis=0), compute_uv=False)
    if spread[0] <= 0 or spread[1] < OPEN_RING_RATIO * spread[0]:
        return None
    # The ellipse's tangent at each anchor from the ring's points just either side of it; its normal outwards.
    d = 0.05 * 2 * np.pi / anchors
    centre_px = image_of(c[None])[0]

    def normals_at(angles: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        step = image_of(ring_at(angles + d)) - image_of(ring_at(angles - d))
        speed = np.linalg.norm(step, axis=1) / (2 * d)  # px per radian of the ring
        along = step / np.linalg.norm(step, axis=1, keepdims=True)
        out = np.stack([along[:, 1], -along[:, 0]], axis=1)
        return out * np.sign(np.sum(out * (image_of(ring_at(angles)) - centre_px), axis=1))[:, None], speed

    normal, speed = normals_at(t)
    image = np.ascontiguousarray(image_log, dtype=np.float32)
    rows, cols = image.shape
    steps = int(round(search_px / STEP_PX))
    # The wire's shadow across it: each ray's path length through the wire (px at the marker), the same at every anchor.
    wire = 0.5 * design.ring_wire_diameter_mm * float(view.magnification(carm_from_marker[:3, 3][None])[0]) / float(view.pixel_spacing_mm[1])
    s_tmpl = np.arange(-(wire + MARGIN_PX), wire + MARGIN_PX + 1e-9, STEP_PX)
    tmpl = 2.0 * np.sqrt(np.maximum(wire * wire - s_tmpl * s_tmpl, 0.0))
    s_data = np.arange(len(s_tmpl) + 2 * steps) * STEP_PX + s_tmpl[0] - steps * STEP_PX
    u = np.arange(-ARC_HALF_PX, ARC_HALF_PX + 1e-9, 1.0)
    # Each profile is averaged along the ellipse itself, across it at each of its points: along a straight tangent the
    # curve falls inside by its sagitta (u^2 / 2R), and the averaged wire's centre with it: on the clean flat scenes'
    # rings, 0.023 px inwards on average from poses 2-3 mm off and 0.039 px at the true poses; along the ellipse,
    # 0.000 and 0.016 px.
    arc = (t[:, None] + u[None, :] / speed[:, None]).ravel()
    along_px = image_of(ring_at(arc)).reshape(len(t), len(u), 2)
    along_normal = normals_at(arc)[0].reshape(len(t), len(u), 2)
    # Every anchor's grid (K, U, S, 2) sampled at once; an anchor near another shadow or reaching outside the image is out.
    grid = along_px[:, :, None] + s_data[None, None, :, None] * along_normal[:, :, None]
    ok = np.all((grid[..., 0] >= 1) & (grid[..., 1] >= 1) & (grid[..., 0] <= cols - 2) & (grid[..., 1] <= rows - 2), axis=(1, 2))
    if avoid_px is not None and len(avoid_px):
        near = np.linalg.norm(ring_px[:, None] - np.asarray(avoid_px, dtype=np.float64)[None], axis=2) < avoid_radius_px
        ok &= ~np.any(near, axis=1)
    if not np.any(ok):
        return None
    flat = grid[ok].reshape(-1, len(s_data), 2)
    samples = cv2.remap(image, flat[..., 0].astype(np.float32), flat[..., 1].astype(np.float32), cv2.INTER_LINEAR)
    profiles = samples.astype(np.float64).reshape(int(ok.sum()), len(u), len(s_data)).mean(axis=1)
    # The image's blur (the detector's, the focal spot's penumbra) is the ring's own: the wire's profile blurred as the
    # anchors, taken together, match best.
    ncc = max((ncc_with_trend(profiles, _blurred(tmpl, b), steps) for b in TEMPLATE_BLURS_PX), key=lambda n: float(np.median(n.max(axis=1))))
    j = np.argmax(ncc, axis=1)
    best = ncc[np.arange(len(j)), j]
    inner = (j > 0) & (j < ncc.shape[1] - 1) & (best >= MIN_CORRELATION)
    jc = np.clip(j, 1, ncc.shape[1] - 2)
    a, b, c3 = (ncc[np.arange(len(j)), jc + d] for d in (-1, 0, 1))
    curv = a - 2 * b + c3
    frac = np.where(curv < 0, 0.5 * (a - c3) / np.where(curv < 0, curv, -1.0), 0.0)
    shift = (j - steps + np.clip(frac, -0.5, 0.5)) * STEP_PX
    idx = np.nonzero(ok)[0][inner]
    if not len(idx):
        return None
    predicted = np.sum(normal[idx] * ring_px[idx], axis=1)
    return RingOutline(anchors_mm=ring_mm[idx], normals=normal[idx], offsets_px=predicted + shift[inner], predicted_px=predicted,
                       correlations=best[inner], sigmas_px=np.full(len(idx), OUTLINE_SIGMA_PX))


def _blurred(profile: NDArray[np.float64], sigma_px: float) -> NDArray[np.float64]:
    """``profile`` (W,), sampled STEP_PX apart and nil at its ends, blurred by a Gaussian of ``sigma_px`` (its length kept)."""
    if sigma_px <= 0:
        return profile
    half = int(np.ceil(3.0 * sigma_px / STEP_PX))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) * STEP_PX / sigma_px) ** 2)
    return np.convolve(np.pad(profile, half), kernel / kernel.sum(), mode="valid")
