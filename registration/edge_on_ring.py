"""Where an edge-on marker lies across its own line: the wire ring's shadow seen side-on, measured in the image.

A marker stuck on the anterior skin is edge-on in a lateral view: its BBs merge along one line and its ring is a
thin ellipse, a bright stroke about twice the ring's radius long. Its BBs are then seldom identified one by one,
yet the stroke's position across its own length is plain in the image, and it is the marker's depth along the
other view's beam, the part a single face-on view fixes worst. Given a pose that already places the marker within
a few millimetres (a joint solve over the other views and the camera), the image is sampled across the predicted
stroke, each half of it on its own, and the profile is slid against the marker's own predicted profile (its wire
and BBs, each weighted by the length of the ray through it): the shift that matches best, refined to a fraction
of a pixel, is how far the stroke lies across its predicted line. Two halves give two such offsets, which must
agree: the line's position and its angle in the image.

Pure math: numpy, scipy and OpenCV's sampling.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .carm import CArmView
from .markers import MarkerDesign
from .transforms import apply

__all__ = ["RingStroke", "measure_ring_stroke", "ncc_with_trend", "EDGE_ON_STROKE_RATIO", "STROKE_SIGMA_PX"]

# A ring whose projected ellipse is flatter than this (minor over major half-axis) is measured as a stroke. Flatter
# than fluoro_markers' EDGE_ON_MINOR_RATIO (0.12), the detector gives up on its pattern; the stroke is still sharp.
EDGE_ON_STROKE_RATIO = 0.15
# How far across its line the stroke is looked for (px, either sense): a marker placed by one face-on view and the
# camera can sit several millimetres off along that view's beam.
SEARCH_PX = 30.0
# The profile's step across the line (px) and the parabola's refinement below it.
STEP_PX = 0.25
TEMPLATE_EVERY = 3
# The predicted profile's dark margin either side of the stroke, in units of the stroke's half-width.
TEMPLATE_MARGIN = 1.0
# A half-stroke is taken when its profile matches the predicted one this well (normalised correlation) and no
# other shift farther than MIN_SEPARATION_PX matches within SECOND_PEAK_RATIO of it (a neighbour's stroke, a K-wire).
MIN_CORRELATION = 0.7
SECOND_PEAK_RATIO = 0.85
MIN_SEPARATION_PX = 4.0
# The two halves' shifts may differ by this much (px): the predicted line's turn in the image (a degree turns a
# 100 px half-stroke's middle by under 2 px). 6 px was measured and not kept: it took a stroke of a pose 1.6 deg off
# (seed 3000, flat markers; 48 flat seeds' AP+lateral median 0.86 -> 0.80 mm), but also halves one of which lay 2.4-4.6
# px off (seed 13301, first pose: 1.25 mm under a 4.2 mm bound, flagged -> 4.39 mm under 1.85 mm, reliable).
HALF_AGREEMENT_PX = 3.0
# The noise (px, 1 sigma) of a half-stroke whose other half agrees: against the twin's truth, 26 half-strokes of 13
# seeds' flat lateral views, from poses 3 mm off along the AP beam and 1 deg askew, were off by 0.71 px median, 1.17
# px at the 90th percentile, 1.87 px at most.
STROKE_SIGMA_PX = 1.0
# Two halves farther apart than HALF_AGREEMENT_PX, up to this, give their middle: the ring's centre, where a turn of
# the line moves neither, at a noise that counts half their disagreement (one of them may be biased by as much).
CENTRE_AGREEMENT_PX = 8.0
# A half alone (the other outside the image, or matched poorly) is taken when it matches this well, at this noise.
# From poses 3 mm off along the AP beam and 2 deg askew (17 flat seeds' lateral views), of 12 lone halves at 0.85 or
# more 7 were over 1 px off, 2 over 2 px, 4.0 px at most; of 8 under 0.8, 5 were over 2 px and one 17 px.
LONE_MIN_CORRELATION = 0.85
LONE_SIGMA_PX = 2.5
# Where neither half is found along the predicted line, the line turned about the ring's centre by these (deg).
TURN_SEARCH_DEG = (-6.0, -4.0, -2.0, 2.0, 4.0, 6.0)


@dataclass(frozen=True, kw_only=True)
class RingStroke:
    """One half of an edge-on ring's stroke, measured across its line.

    anchor_mm : (3,) the point in the marker frame whose image the measurement places (the middle of the half).
    normal : (2,) the unit image direction across the stroke.
    offset_px : where the anchor's image lies along ``normal`` (``normal @ uv``), as measured.
    predicted_px : the same at the pose the stroke was looked for from.
    correlation : the normalised correlation of the measured and predicted profiles at the match (the lower of two
        halves for the ring's centre).
    sigma_px : the measurement's noise (1 sigma) along ``normal``.
    """

    anchor_mm: NDArray[np.float64]
    normal: NDArray[np.float64]
    offset_px: float
    predicted_px: float
    correlation: float
    sigma_px: float


def _profile_template(view: CArmView, carm_from_marker: NDArray[np.float64], design: MarkerDesign, grid_px: NDArray[np.float64]) -> NDArray[np.float64]:
    """(T, S) the marker's predicted shadow on the grid (T, S, 2) px: each ray's path length (px at the marker) through
    the ring's wire and the BBs."""
    ring = apply(carm_from_marker, design.ring_points_mm(2048))
    ring_px = view.project(ring)
    scale = float(view.magnification(carm_from_marker[:3, 3][None])[0]) / float(view.pixel_spacing_mm[1])  # px per mm at the marker
    pts = grid_px.reshape(-1, 2)
    rw = 0.5 * design.ring_wire_diameter_mm * scale
    # Only rays within the wire's radius of the ring cross it: the search for the nearest ring point stops there
    # (farther ones come back at infinity, and cross nothing), a third of the time of the unbounded search.
    d, _ = cKDTree(ring_px).query(pts, distance_upper_bound=rw)
    out = 2.0 * np.sqrt(np.maximum(rw * rw - d * d, 0.0))
    bb_px = view.project(apply(carm_from_marker, design.bb_centers_mm))
    for c, dia in zip(bb_px, design.bb_diameters_mm):
        r = 0.5 * dia * scale
        q = np.sum((pts - c) ** 2, axis=1)
        out += 2.0 * np.sqrt(np.maximum(r * r - q, 0.0))
    return out.reshape(grid_px.shape[:2])


def ncc_with_trend(data: NDArray[np.float64], tmpl: NDArray[np.float64], steps: int) -> NDArray[np.float64]:
    """Normalised correlation of ``tmpl`` (W,) with every window of ``data`` (..., W + 2 steps), shifts -steps..steps (the
    result (..., 2 steps + 1): one row per profile where ``data`` holds several), each
    with its straight-line trend across the window taken out: the anatomy's slope under a stroke (a bone's edge, the
    soft tissue thickening toward the back) is no part of the ring's shadow. With the mean alone taken out, 37 of 80
    edge-on rings in the flat-marker twin's lateral views (17 seeds, from poses 3 mm off) had a half under
    MIN_CORRELATION; with the trend, 18."""
    w = len(tmpl)
    x = np.linspace(-1.0, 1.0, w)
    basis = np.stack([np.full(w, 1.0 / np.sqrt(w)), x / np.linalg.norm(x)])  # (2, W) orthonormal: mean and slope
    t = tmpl - (basis @ tmpl) @ basis
    tn = np.linalg.norm(t)
    win = np.lib.stride_tricks.sliding_window_view(data, w, axis=-1)[..., : 2 * steps + 1, :]
    win = win - (win @ basis.T) @ basis
    return (win @ t) / np.maximum(np.linalg.norm(win, axis=-1) * tn, 1e-12)


def measure_ring_stroke(image_log: NDArray[np.floating], view: CArmView, carm_from_marker: NDArray[np.float64], design: MarkerDesign, *,
                        search_px: float = SEARCH_PX, lone_half: bool = True) -> tuple[RingStroke, ...]:
    """The halves of ``design``'s ring stroke that the image (log attenuation, bright where dense) shows near where
    ``carm_from_marker`` (4, 4) puts it, each half inside the image and matched unambiguously: both halves where their
    shifts agree within ``HALF_AGREEMENT_PX``; the ring's centre where they differ by up to ``CENTRE_AGREEMENT_PX``;
    one half alone where the other is not found and it matches to ``LONE_MIN_CORRELATION`` (and ``lone_half``); ()
    otherwise, or where the ring is not edge-on (:data:`EDGE_ON_STROKE_RATIO`)."""
    ring_mm = design.ring_points_mm(256)
    ring_px = view.project(apply(carm_from_marker, ring_mm))
    centre = ring_px.mean(axis=0)
    _, _, vt = np.linalg.svd(ring_px - centre, full_matrices=False)
    along = vt[0]
    normal = np.array([-along[1], along[0]])
    half_len = float(np.max(np.abs((ring_px - centre) @ along)))
    half_wid = float(np.max(np.abs((ring_px - centre) @ normal)))
    if half_len <= 0 or half_wid > EDGE_ON_STROKE_RATIO * half_len:
        return ()
    reach = half_wid + 0.5 * float(np.max(design.bb_diameters_mm)) * half_len / design.ring_radius_mm + 3.0
    image = np.ascontiguousarray(image_log, dtype=np.float32)
    out = [st for st, _ in _halves(image, view, carm_from_marker, design, ring_mm, ring_px, centre, along, half_len, reach, search_px)]
    judged = _judged(out, view, carm_from_marker, design, normal, lone_half=lone_half)
    if judged or not out:
        return judged
    # A half found along the predicted line but nothing taken: a pose a few degrees askew turns the stroke in the image,
    # so that its two halves lie apart across that line, or one half's profile, averaged along a line turned from it,
    # smears. (Where no half matches at all, nothing stroke-like lies there: no turned line is tried.) Twin
    # seed 28801 (flat markers, AP+lateral, first pose): marker 5, placed 1.3 mm and 5.6 deg off by the AP view (three
    # BBs, its ring outside the field) and the camera, its stroke turned 3.9 deg from the predicted one; the halves
    # matched at 0.96 each, 8.25 px apart. The line is turned a few degrees either way about the ring's centre; two
    # halves on one line there (their shifts within HALF_AGREEMENT_PX) are taken, at the turn that matches best.
    best: tuple[RingStroke, ...] = ()
    for deg in TURN_SEARCH_DEG:
        a = np.radians(deg)
        turned = np.array([np.cos(a) * along[0] - np.sin(a) * along[1], np.sin(a) * along[0] + np.cos(a) * along[1]])
        found = _halves(image, view, carm_from_marker, design, ring_mm, ring_px, centre, turned, half_len, reach, search_px, template_along=along)
        # Both halves on one line: the same shift from the turned line.
        if len(found) == 2 and abs(found[0][1] - found[1][1]) <= HALF_AGREEMENT_PX:
            if not best or min(h.correlation for h, _ in found) > min(h.correlation for h in best):
                best = tuple(h for h, _ in found)
    return best


def _halves(image: NDArray[np.float32], view: CArmView, carm_from_marker: NDArray[np.float64], design: MarkerDesign, ring_mm: NDArray[np.float64],
            ring_px: NDArray[np.float64], centre: NDArray[np.float64], along: NDArray[np.float64], half_len: float, reach: float, search_px: float,
            *, template_along: NDArray[np.float64] | None = None) -> list[tuple[RingStroke, float]]:
    """Each half of the stroke found across the line through ``centre`` (2,) px along ``along`` (2,), matched
    unambiguously (:data:`MIN_CORRELATION`, :data:`SECOND_PEAK_RATIO`) within ``search_px`` of it, and its shift (px)
    from that line. The predicted profile is taken along ``template_along`` (the predicted stroke's own direction;
    default ``along``)."""
    rows, cols = image.shape
    normal = np.array([-along[1], along[0]])
    tmpl_along = along if template_along is None else template_along
    tmpl_normal = np.array([-tmpl_along[1], tmpl_along[0]])
    steps = int(round(search_px / STEP_PX))
    # The predicted profile spans the stroke and as much again either side, where it is dark: a bright band beside the
    # stroke must count against a match there, not for it; matched on the stroke's own width, seed 11401's lateral
    # view (markers flat) took a band some 40 px wide beside marker 37's stroke, 13 px aside, for the stroke.
    span = (1.0 + TEMPLATE_MARGIN) * reach
    s_tmpl = np.arange(-span, span + 1e-9, STEP_PX)
    s_data = np.arange(-span - steps * STEP_PX, span + steps * STEP_PX + 1e-9, STEP_PX)[: len(s_tmpl) + 2 * steps]
    out = []
    for sign in (-1.0, 1.0):
        # Each half, its ends left out (where the wire turns across the line).
        t = sign * np.arange(0.1 * half_len, 0.9 * half_len, 1.0)
        grid_t = centre[None, None] + t[:, None, None] * along
        grid = grid_t + s_data[None, :, None] * normal
        corners = grid[[0, 0, -1, -1], [0, -1, 0, -1]]
        if np.any(corners < 1) or np.any(corners[:, 0] > cols - 2) or np.any(corners[:, 1] > rows - 2):
            continue  # this half lies partly outside the image
        # The predicted profile, smooth along the stroke: every third row of the sampled grid is enough.
        tmpl_t = centre[None, None] + t[::TEMPLATE_EVERY, None, None] * tmpl_along
        tmpl = _profile_template(view, carm_from_marker, design, tmpl_t + s_tmpl[None, :, None] * tmpl_normal).mean(axis=0)
        samples = cv2.remap(image, grid[..., 0].astype(np.float32), grid[..., 1].astype(np.float32), cv2.INTER_LINEAR)
        data = samples.astype(np.float64).mean(axis=0)
        ncc = ncc_with_trend(data, tmpl, steps)
        k = int(np.argmax(ncc))
        best = float(ncc[k])
        shifts = (np.arange(len(ncc)) - steps) * STEP_PX
        far = np.abs(shifts - shifts[k]) > MIN_SEPARATION_PX
        peaks = far & (ncc >= np.roll(ncc, 1)) & (ncc >= np.roll(ncc, -1))
        if best < MIN_CORRELATION or k in (0, len(ncc) - 1) or (np.any(peaks) and float(ncc[peaks].max()) > SECOND_PEAK_RATIO * best):
            continue
        a, b, c = ncc[k - 1], ncc[k], ncc[k + 1]
        frac = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) < 0 else 0.0
        shift = (k - steps + float(np.clip(frac, -0.5, 0.5))) * STEP_PX
        # The half's middle, as a point of the marker: half way from the ring's centre to that end of the stroke. Across
        # a turned line, the point found is the line's at the half's middle moved by the shift: measured along the
        # turned line's normal, as is the anchor's prediction.
        anchor = _anchor_mm(ring_mm, ring_px, sign * tmpl_along, design)
        anchor_px = view.project(apply(carm_from_marker, anchor[None]))[0]
        predicted = float(normal @ anchor_px)
        on_line = float(normal @ centre)
        out.append((RingStroke(anchor_mm=anchor, normal=normal.copy(), offset_px=on_line + shift if template_along is not None else predicted + shift,
                               predicted_px=predicted, correlation=best, sigma_px=STROKE_SIGMA_PX), shift))
    return out


def _judged(out: list[RingStroke], view: CArmView, carm_from_marker: NDArray[np.float64], design: MarkerDesign, normal: NDArray[np.float64], *,
            lone_half: bool) -> tuple[RingStroke, ...]:
    """The halves found along the predicted line, judged together (see :func:`measure_ring_stroke`)."""
    # Two halves that agree, each at its own noise. Two that disagree a little give the ring's centre, their middle
    # (a turn of the pose about the beam parts the halves, and moves the centre not at all), at a noise that counts
    # the disagreement; farther apart, one matched something else (a neighbour's stroke, the other side of a ring's
    # thin ellipse, a K-wire): tens of pixels off on the twin. A half alone is taken only where it matches well.
    if len(out) == 1:
        lone = out[0]
        return (replace(lone, sigma_px=LONE_SIGMA_PX),) if lone_half and lone.correlation >= LONE_MIN_CORRELATION else ()
    if len(out) != 2:
        return ()
    shifts = [st.offset_px - st.predicted_px for st in out]
    apart = abs(shifts[0] - shifts[1])
    if apart <= HALF_AGREEMENT_PX:
        return tuple(out)
    if apart > CENTRE_AGREEMENT_PX:
        return ()
    centre_mm = np.asarray(design.ring_center_mm, dtype=np.float64)
    predicted = float(normal @ view.project(apply(carm_from_marker, centre_mm[None]))[0])
    return (RingStroke(anchor_mm=centre_mm, normal=normal.copy(), offset_px=predicted + 0.5 * (shifts[0] + shifts[1]), predicted_px=predicted,
                       correlation=min(st.correlation for st in out), sigma_px=float(np.hypot(STROKE_SIGMA_PX, 0.5 * apart))),)


def _anchor_mm(ring_mm: NDArray[np.float64], ring_px: NDArray[np.float64], toward: NDArray[np.float64], design: MarkerDesign) -> NDArray[np.float64]:
    """The point (3,) of the marker's plane half way from the ring's centre to the ring's end whose image lies
    farthest along ``toward`` (2,): the middle of that half of the stroke."""
    k = int(np.argmax(ring_px @ toward))
    c = np.asarray(design.ring_center_mm, dtype=np.float64)
    return c + 0.5 * (ring_mm[k] - c)
