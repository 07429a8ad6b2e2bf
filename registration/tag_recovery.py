"""Recovery of a tag the ArUco detector missed, from where the registration predicts it, with its identity verified.

ArUco needs a tag's whole black border and a clean read of its code: a gloved finger over one corner, or a
saturated highlight on a glossy tag, loses the tag although most of it is in plain view. When the registration
(``carm_from_drill``) and the marker's pose in fluoroscopy predict a missing tag's four corners, the tag is looked
for there:

1. Each of its four border edges is searched across its predicted line (within ``tolerance_px``): the offset where
   the profiles step from the bright base outside to the black border inside (the contrast between narrow boxes of
   samples either side, or wide ones where a blurred step spreads beyond the narrow), taken over the edge's samples
   by a high percentile so that an occluded part does not decide it. Then each sample's step is placed to sub-pixel
   (:mod:`.tag_edges`, as the locator refines detected tags) and kept only when it looks like a clean border step
   (its contrast near the edge's, its dark side unclipped, its bright side clipped only beyond the upper half of
   the step's gradient); a line is fitted to the kept samples, trimming the
   outliers, and needs ``min_edge_fraction`` of the edge. An edge that runs just inside the frame's edge has
   no profile wholly in the frame: its samples count where the step, its gradient and the levels either side are. The corners are the lines' intersections, so a hidden
   corner comes from its two edges' extensions. A tag with one edge hidden (a highlight or a finger over most of
   it, or the edge out of the frame) is placed, given the camera and the tag's size (``square``), by its pose
   fitted to the other three edges' steps (:mod:`.tag_square_fit`), when that fit places every corner within
   ``SQUARE_FIT_MAX_CORNER_SIGMA_PX``.
2. The identity is verified by reading the code cells that can be read: a saturated cell, a cell beside a
   saturated one (a highlight's halo lifts a black cell), a cell whose samples straddle two levels (an occluder's
   boundary) or one in the middle between the black border's and the white base's levels is unknown, not a vote.
   Where the white base is itself at the clip (an over-exposed frame, ``CLIPPED_BASE``), every white cell clips
   with no highlight on it: a saturated cell is then unknown only beside a sign of one (a cell of the tag between
   the two levels, or a border cell reading white).
   Something lying over the tag lifts black cells without saturating them: a light glove over a corner (a flat
   level a little under the white base's: on the twin a glove read 108 against the base's 130 and the border's 44,
   over the middle) and a highlight's wide halo. Where a border cell reads white (the border is black) or a cell of
   the tag is brighter than the white base (by ``GLARE_LIFT`` of the contrast), the cells beside it that read white
   are unknown (``read_code(covers=True)``; a black read still counts: neither darkens a white cell). Of the 233
   tags the study's frames missed whose markers fluoroscopy posed (the groups of seeds in docs/accuracy.md), read at
   their true corners, 49 had black cells read white (41 of them one or two cells), and 153 were recovered; with the
   rule 13 and 189, none lost (docs/identity_and_error.md, "Cells beside a glove or a highlight's halo"). Only
   the recovery reads so. ArUco's decoded tags are checked for a misread on every cell
   (:meth:`.VideoMarkerLocator._misread`): a real photograph's small blurred cells lose white reads to the rule, and
   rightly decoded tags were set aside. Outlines named among the posed (:mod:`.tag_hypotheses`) read as before: with
   the rule there, the docs table's seeds refused 64 -> 70 registrations and one went 4.44 -> 150.78 mm (flagged).
   The search (:mod:`.tag_search`) reads as before too: not measured with the rule.
   Accepted only when at least ``min_cells`` cells are read, at least ``min_agreement`` of them agree with the
   expected id's code, the border reads black, and the nearest other id of the dictionary (at the same rotation)
   disagrees with what was read in at least ``min_margin_cells`` more cells than the expected id does.
   A glare spot on a glossy tag can leave fewer cells than that, and an id from outside the marker set can come
   within that margin of many cells read: then, when the ids that may lie there are known (``rivals``: the marker
   set's other tags of the dictionary not seen elsewhere in the frame nor placed elsewhere by the registration;
   empty when none can be there), at least ``min_cells_among_rivals`` cells read, ``min_agreement`` of them
   agreeing, every rival at every rotation disagreeing in at least ``min_margin_cells`` more cells than the
   expected id, and no other id of the dictionary agreeing with as many cells as the expected one, suffice. The
   place itself is the rest of the evidence: a black-bordered square whose four edges lie within ``tolerance_px``
   of where the registration predicts this marker's tag.
   Identity by place (``placed_here``): when the prediction comes from a registration that places the markers
   posed in fluoroscopy (with its mirror open, under either solution), and this marker is one of them, no marker
   that registration does not place can lie where this one is; ``rivals`` are then the posed markers it places
   here too (under either solution), and with none the cells read need only agree (``min_agreement`` of them),
   however few a highlight leaves.

A foreign tag at the predicted place, a blank patch, and a tag farther than the tolerance from its prediction
are refused, each with its reason.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from .camera import PinholeCamera
from .tag_edges import edge_corners, edge_profiles, fit_edge_lines, step_positions
from .tag_square_fit import SquareFit
from .transforms import apply, invert

__all__ = ["TagRecovery", "CodeRead", "BorderSteps", "recover_tag", "fit_tag_edges", "border_steps", "read_code", "predict_tag_corners", "dictionary_codes",
           "share_in_frame", "RECOVERED_CORNER_SIGMA_PX", "MIN_SHARE_IN_FRAME", "SQUARE_FIT_MAX_CORNER_SIGMA_PX"]

# A recovered tag's corners are noisier than a detected one's: up to one corner is an extrapolation of two
# partly hidden edges. Measured against the twin's truth (tests/test_tag_recovery.py, benchmarks/tag_detection.py
# --recover): see docs/identity_and_error.md, "Tags recovered from their prediction".
RECOVERED_CORNER_SIGMA_PX = 0.5

# A tag with one or two edges hidden is placed by its pose fitted to the steps left (:mod:`.tag_square_fit`) only
# when that fit states every corner within this. Its statement comes from the steps' scatter alone, while blur and
# defocus shift whole edges: under every camera degradation (twin seeds 5000-5030, the surgeon's markers, predicted
# from the true pose) the 26 tags so placed had 0.39 px RMS corner error (1.49 px at worst, where 0.36 px was
# stated); the 22 stated within 0.25 px, 0.32 px RMS (0.82 px at worst), under RECOVERED_CORNER_SIGMA_PX.
SQUARE_FIT_MAX_CORNER_SIGMA_PX = 0.25

# A tag cut by the frame's edge is looked for where it is predicted when at least this share of it is in the frame:
# its edges and code cells in the frame are used, a corner outside is the crossing of two edges' lines.
MIN_SHARE_IN_FRAME = 0.6

# A cell whose mean grey level is at least this is clipped (8 bits): a highlight's plateau at 255. A tag's white
# cells can lie near 250 in a bright field (the print is whiter than the base), and noise lifts single pixels.
SATURATED = 253.5
# A white base this bright (its median, 8 bits) is itself at the clip: the frame is over-exposed, and a tag's white
# cells (printed whiter than the base) clip with no highlight on them. Then only a clipped cell beside a cell of the
# tag more than GLARE_LIFT of the border-to-base contrast from both levels (a highlight's halo), or beside a border
# cell reading white, is taken for a highlight.
CLIPPED_BASE = 245.0
GLARE_LIFT = 0.15
# An edge with fewer than this share of its profiles wholly in the frame runs just inside the frame's edge: its
# profiles count where the step's boxes lie in the frame (``border_steps``).
HUGGING_SHARE = 0.3
# Box widths (samples at ``step_px``, 0.5 px) either side of a candidate border step in the coarse search: 2 px, and
# 4 px for a step that defocus or motion spreads wider than the narrow boxes reach (``border_steps``).
NARROW_GAP, WIDE_GAP = 4, 8


@lru_cache(maxsize=8)
def dictionary_codes(dictionary: str) -> NDArray[np.uint8]:
    """Every id's code cells (n_ids, s, s) of an ArUco dictionary at its first rotation, 1 = white (as OpenCV draws it)."""
    if not hasattr(cv2.aruco, dictionary):
        raise ValueError(f"unknown ArUco dictionary '{dictionary}' (e.g. DICT_6X6_250)")
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    size = d.markerSize
    codes = np.array([cv2.aruco.Dictionary.getBitsFromByteList(d.bytesList[i : i + 1], size) for i in range(len(d.bytesList))], dtype=np.uint8)
    codes.setflags(write=False)
    return codes


@dataclass(frozen=True, kw_only=True)
class TagRecovery:
    """What :func:`recover_tag` found.

    corners_px : (4, 2) the tag's corners (OpenCV order), None when refused.
    reason : why it was refused ("" when accepted).
    cells_read : code cells read (neither saturated, occluded nor ambiguous), of the s x s.
    cells_agreeing : of those, the cells that agree with the expected id's code.
    nearest_other_id, nearest_other_agreeing : the other id of the dictionary that agrees best with the cells read, and in how many.
    edge_fraction : (4,) share of each edge's samples its line was fitted to.
    """

    corners_px: NDArray[np.float64] | None
    reason: str
    cells_read: int = 0
    cells_agreeing: int = 0
    nearest_other_id: int = -1
    nearest_other_agreeing: int = 0
    edge_fraction: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    @property
    def accepted(self) -> bool:
        return self.corners_px is not None


def predict_tag_corners(*, carm_from_drill: NDArray[np.float64], carm_from_marker: NDArray[np.float64], tag_corners_marker_mm: NDArray[np.float64],
                        camera: PinholeCamera) -> NDArray[np.float64] | None:
    """A marker's tag corners (4, 2) px in the camera image, or None when the tag is behind the camera.

    carm_from_drill, carm_from_marker : (4, 4) the registration and the marker's pose in frame C.
    tag_corners_marker_mm : (4, 3) the tag's corners in the marker frame (``MarkerDesign.tag_corners_mm()``, OpenCV order).
    """
    pts_d = apply(invert(carm_from_drill) @ carm_from_marker, np.asarray(tag_corners_marker_mm, dtype=np.float64))
    if np.any(pts_d[:, 2] <= 1.0):
        return None
    return camera.project(pts_d)


def _percentile_over_samples(values: NDArray[np.float64], valid: NDArray[np.bool_], q: float) -> NDArray[np.float64]:
    """``np.nanpercentile(values, q, axis=1)`` (linear interpolation) over the samples where ``valid`` (e, s) or
    (e, s, o), for values (e, s, o); -inf where no sample is valid. Vectorised: nanpercentile loops over every
    (e, o) in Python."""
    valid = np.broadcast_to(valid[..., None] if valid.ndim == 2 else valid, values.shape)
    ordered = np.sort(np.where(valid, values, np.inf), axis=1)                        # the invalid ones last
    n = valid.sum(axis=1)                                                             # (e, o)
    pos = (np.maximum(n, 1) - 1) * (q / 100.0)
    lo = np.floor(pos).astype(int)
    hi = np.minimum(lo + 1, np.maximum(n, 1) - 1)
    shape = (ordered.shape[0], ordered.shape[2])
    lo_v = np.take_along_axis(ordered, np.broadcast_to(lo, shape)[:, None, :], axis=1)[:, 0]
    hi_v = np.take_along_axis(ordered, np.broadcast_to(hi, shape)[:, None, :], axis=1)[:, 0]
    with np.errstate(invalid="ignore"):  # inf - inf where no sample is valid; replaced below
        out = lo_v + (pos - lo) * (hi_v - lo_v)
    return np.where(n > 0, out, -np.inf)


def share_in_frame(corners_px: NDArray[np.float64], *, width: int, height: int) -> float:
    """The share of a tag's area (corners (4, 2) px, OpenCV order) that lies in a width x height frame (a 10 x 10
    grid of points bilinear over the quadrilateral)."""
    q = np.asarray(corners_px, dtype=np.float64)
    u = (np.arange(10) + 0.5) / 10
    a, b = np.meshgrid(u, u, indexing="ij")
    a, b = a.reshape(-1, 1), b.reshape(-1, 1)
    pts = (1 - a) * (1 - b) * q[0] + a * (1 - b) * q[1] + a * b * q[2] + (1 - a) * b * q[3]
    return float(np.mean((pts[:, 0] >= 0) & (pts[:, 1] >= 0) & (pts[:, 0] <= width - 1) & (pts[:, 1] <= height - 1)))


def _box_mean(values: NDArray[np.float32], width: int) -> NDArray[np.float64]:
    """Means over ``width`` consecutive samples along the last axis (..., o) -> (..., o - width + 1)."""
    c = np.cumsum(np.concatenate([np.zeros(values.shape[:-1] + (1,)), values], axis=-1), axis=-1)
    return (c[..., width:] - c[..., :-width]) / width


def recover_tag(
    gray: NDArray[np.float32],
    predicted_px: NDArray[np.float64],
    *,
    aruco_id: int,
    dictionary: str = "DICT_6X6_250",
    tolerance_px: float = 8.0,
    samples: int = 48,
    step_px: float = 0.5,
    min_edge_fraction: float = 0.3,
    min_cells: int = 20,
    min_agreement: float = 0.9,
    min_margin_cells: int = 4,
    min_contrast: float = 30.0,
    rivals: Sequence[int] | None = None,
    min_cells_among_rivals: int = 8,
    placed_here: bool = False,
    partial: bool = False,
    square: Callable[[BorderSteps], SquareFit | None] | None = None,
) -> TagRecovery:
    """Find the tag ``aruco_id`` of ``dictionary`` near its predicted corners (4, 2) px (OpenCV order) in ``gray`` (H, W) float32.

    ``tolerance_px``: how far (px, along each edge's normal) an edge may lie from its prediction. ``partial``: a
    tag partly out of the frame is looked for on what of it is in the frame (its cells outside are unread; a
    corner outside is the crossing of its edges' lines). ``square``: a tag with one or two edges hidden is placed by its
    pose fitted to the steps left (:func:`fit_tag_edges`). ``placed_here``: the prediction is where a registration puts
    this marker, posed in fluoroscopy, and ``rivals`` are the markers that registration places here too (see the module
    docstring, "identity by place"). See the module docstring for the method and the acceptance rule.
    """
    pred = np.asarray(predicted_px, dtype=np.float64)
    if pred.shape != (4, 2) or not np.isfinite(pred).all():
        raise ValueError(f"predicted tag corners must be a finite (4, 2) array, got shape {pred.shape}")
    codes = dictionary_codes(dictionary)
    if not 0 <= aruco_id < len(codes):
        raise ValueError(f"ArUco id {aruco_id} is not in {dictionary} (0-{len(codes) - 1})")
    if rivals is not None and any(not 0 <= int(r) < len(codes) for r in rivals):
        raise ValueError(f"rival ArUco ids {sorted(int(r) for r in rivals if not 0 <= int(r) < len(codes))} are not in {dictionary} (0-{len(codes) - 1})")
    got = fit_tag_edges(gray, pred, tolerance_px=tolerance_px, samples=samples, step_px=step_px, min_edge_fraction=min_edge_fraction,
                        min_contrast=min_contrast, partial=partial, square=square)
    if not got.accepted:
        return got
    corners, frac_t = got.corners_px, got.edge_fraction
    return _verify(gray, corners, codes, aruco_id, min_cells=min_cells, min_agreement=min_agreement, min_margin_cells=min_margin_cells,
                   min_contrast=min_contrast, edge_fraction=frac_t, rivals=rivals, min_cells_among_rivals=min_cells_among_rivals, placed_here=placed_here,
                   partial=partial)


@dataclass(frozen=True, kw_only=True)
class BorderSteps:
    """The border steps found along a tag's four edges (step 1 of the module docstring), before any line is fitted.

    points_px : (4, s, 2) each sample's step (edge k runs from corner k to k + 1).
    kept : (4, s) the clean steps on their edge's line (outliers trimmed); none on an edge with no border step.
    fraction : (4,) share of each edge's samples kept. spans : (4,) share of each edge the kept samples span.
    """

    points_px: NDArray[np.float64]
    kept: NDArray[np.bool_]
    fraction: NDArray[np.float64]
    spans: NDArray[np.float64]


def fit_tag_edges(gray: NDArray[np.float32], predicted_px: NDArray[np.float64], *, tolerance_px: float = 8.0, samples: int = 48,
                  step_px: float = 0.5, min_edge_fraction: float = 0.3, min_contrast: float = 30.0, partial: bool = False,
                  square: Callable[[BorderSteps], SquareFit | None] | None = None, max_corner_shift_px: float | None = None) -> TagRecovery:
    """A tag's four border edges found near ``predicted_px`` (4, 2) and their corners, identity not judged (step 1 of
    the module docstring): ``corners_px`` None with the reason when an edge is not found.

    ``partial``: a tag partly out of the frame is fitted on what of each edge is in it (each edge still needs
    ``min_edge_fraction`` of its samples); otherwise such a tag is refused.

    ``square``: when one edge is not found (a glare spot or a finger over most of it), or two are (a glove or a
    highlight over a corner hides most of both edges that meet there), the tag's pose fitted to every clean step left
    (:func:`.tag_square_fit.fit_square_to_edges` with the camera and the tag's size) gives the corners, where the fit
    states them within its limit; None (the default) refuses such a tag. On the operating-room twin with markers
    stuck flat (48 seeds, AP+lateral two views) the second case took the median 1.11 -> 1.08 mm, 50 registrations
    nearer the truth and 22 farther (docs/identity_and_error.md).

    ``max_corner_shift_px``: how far the fitted corners may lie from ``predicted_px`` (None: 1.5 ``tolerance_px``).

    Shared by :func:`recover_tag` (a predicted tag) and :mod:`.tag_search` (a candidate outline).
    """
    pred = np.asarray(predicted_px, dtype=np.float64)
    limit = 1.5 * tolerance_px if max_corner_shift_px is None else float(max_corner_shift_px)
    got = border_steps(gray, pred, tolerance_px=tolerance_px, samples=samples, step_px=step_px, min_contrast=min_contrast, partial=partial,
                       allow_one_missing=square is not None)
    if isinstance(got, str):
        return TagRecovery(corners_px=None, reason=got)
    fraction = got.fraction
    frac_t = tuple(float(f) for f in fraction)
    good = (fraction >= min_edge_fraction) & (got.spans >= 0.3)
    if good.all():
        point, direction, _, _ = fit_edge_lines(got.points_px[None], got.kept[None])
        corners, crossed = edge_corners(point, direction)
        corners, crossed = corners[0], bool(crossed[0])
    elif square is not None and good.sum() >= 2:
        fit = square(got)
        if fit is None:
            k = int(np.argmin(fraction))
            return TagRecovery(corners_px=None, reason=f"edge {k}: a clean border step along only {100 * fraction[k]:.0f} % of it, "
                               "and the other edges do not place it", edge_fraction=frac_t)
        corners, crossed = fit.corners_px, True
    else:
        k = int(np.argmin(fraction))
        return TagRecovery(corners_px=None, reason=f"edge {k}: a clean border step along only {100 * fraction[k]:.0f} % of it", edge_fraction=frac_t)
    if not crossed or np.linalg.norm(corners - pred, axis=1).max() > limit:
        return TagRecovery(corners_px=None, reason=f"edges found but their corners lie over {limit:.0f} px from the prediction", edge_fraction=frac_t)
    return TagRecovery(corners_px=corners, reason="", edge_fraction=frac_t)


def border_steps(gray: NDArray[np.float32], pred: NDArray[np.float64], *, tolerance_px: float, samples: int, step_px: float, min_contrast: float,
                 partial: bool, allow_one_missing: bool = False) -> BorderSteps | str:
    """The clean border steps along each edge of a tag predicted at ``pred`` (4, 2), or the reason none can be had.

    ``allow_one_missing``: one edge with no border step within the tolerance is returned with no step kept
    (otherwise the tag is refused with that edge's reason).
    """
    side = np.linalg.norm(np.roll(pred, -1, axis=0) - pred, axis=1)
    if side.min() < 12.0:
        return f"predicted tag too small ({side.min():.1f} px side)"
    # 1. Coarse: per edge, the offset (within the tolerance) where the samples step from bright outside to dark inside,
    # its contrast the larger of two measures: between narrow boxes of samples either side, and between wide ones (a
    # step that defocus or motion spreads beyond the narrow boxes).
    gap = WIDE_GAP  # samples either side of a candidate step, the wide boxes'
    reach = tolerance_px + gap * step_px + 1.0
    offsets = np.arange(-reach, reach + step_px / 2, step_px)
    along = np.linspace(0.06, 0.94, samples)
    prof = edge_profiles(gray, pred[None], along=along, offsets_px=offsets)
    if not prof.inside[0] and not partial:
        return "the predicted tag's edges leave the frame"
    seen = prof.sample_inside[0]                                                      # (4, s)
    vals = prof.values[0].astype(np.float64)                                          # (4, s, o)
    # Candidate step b between offsets[b] and offsets[b + 1], b = gap - 1 .. o - 1 - gap: the mean of g samples
    # outside minus the mean of g inside, the larger of the narrow and the wide boxes'.
    n_cand = len(offsets) - 2 * gap + 1
    contrast = np.full(vals.shape[:-1] + (n_cand,), -np.inf)                          # (4, s, o')
    for g in (NARROW_GAP, WIDE_GAP):
        box = _box_mean(vals, g)                                                      # box[j]: mean of vals[j : j + g]
        contrast = np.maximum(contrast, box[..., gap : gap + n_cand] - box[..., gap - g : gap - g + n_cand])
    cand = offsets[gap - 1 : gap - 1 + n_cand] + step_px / 2
    in_tol = np.abs(cand) <= tolerance_px
    # A high percentile over the edge's samples: a step must run along most of what is visible of the edge. A
    # sample clipped along most of its profile (a highlight over the border) shows nothing, and is not counted.
    # A sample whose profile leaves the frame counts only where both of a candidate's boxes lie in it, and only on
    # an edge with too few profiles wholly in the frame (one that runs just inside the frame's edge): elsewhere
    # the whole profiles suffice and nothing changes.
    hugging = seen.mean(axis=1) < HUGGING_SHARE                                       # (4,)
    box_in = _box_mean(prof.point_inside[0].astype(np.float64), gap) > 1.0 - 1e-9     # (4, s, o - gap + 1)
    cand_in = box_in[..., gap:] & box_in[..., : box_in.shape[-1] - gap]               # (4, s, o')
    usable = np.where(hugging[:, None, None], cand_in, seen[..., None])               # (4, s, o')
    blind = (vals >= SATURATED).mean(axis=-1) > 0.5                                   # (4, s)
    edge_score = _percentile_over_samples(contrast, usable & ~blind[..., None], 60.0)  # (4, o'), -inf where none is seen
    edge_score[:, ~in_tol] = -np.inf
    best = np.argmax(edge_score, axis=1)
    edge_contrast = edge_score[np.arange(4), best]
    found = edge_contrast >= min_contrast
    if found.sum() < (3 if allow_one_missing else 4):
        k = int(np.argmin(edge_contrast))
        return f"no border step within {tolerance_px:.0f} px of edge {k} (contrast {edge_contrast[k]:.0f})"
    coarse = cand[best]                                                               # (4,)
    # 2. Fine: every sample's step near its edge's coarse offset, kept when it is a clean border step.
    # The window holds the whole step: +-3 px for a sharp edge, wider under motion blur (the gradient's upper half
    # spans the blur), where a narrow window would cut the step and pull it towards the coarse offset.
    grad = np.clip(np.diff(vals, axis=-1), 0.0, None)
    step_width = np.median((grad > 0.5 * grad.max(axis=-1, keepdims=True)).sum(axis=-1), axis=1) * step_px  # (4,)
    window = float(np.clip(step_width[found].max() + 1.0, 3.0, tolerance_px))
    j0 = np.searchsorted(offsets, coarse - window)
    width = int(round(2 * window / step_px)) + 1
    idx = np.clip(j0[:, None] + np.arange(width)[None, :], 0, len(offsets) - 1)       # (4, width)
    sub_vals = np.take_along_axis(vals, np.broadcast_to(idx[:, None, :], (4, samples, width)), axis=2)
    sub_off = offsets[idx]                                                            # (4, width)
    pos = np.empty((4, samples))
    stepped = np.empty((4, samples), dtype=bool)
    for k in range(4):  # four small calls: each edge has its own offsets
        pos[k], stepped[k] = step_positions(sub_vals[k], sub_off[k], falling_inwards=True)
    # Levels 1.5-3 px either side of each sample's step (bilinear along the profile).
    lv_out = _levels_at(vals, offsets, pos, (1.5, 3.0))
    lv_in = _levels_at(vals, offsets, pos, (-3.0, -1.5))
    step_contrast = lv_out - lv_in
    # On a hugging edge, a sample is seen when the upper half of its step's gradient (where the step is placed from,
    # as wide as the blur) and the levels either side lie in the frame: beyond the frame the profile is the edge
    # pixel replicated, which would cut the gradient short and pull the step inwards.
    # The frame is convex: both ends of that stretch in it put the whole stretch in it.
    half = np.maximum(3.5, step_width / 2.0 + 1.0)                                    # (4,)
    reach_out = pos[..., None] + np.array([-1.0, 1.0]) * half[:, None, None]         # (4, s, 2)
    ends = prof.base_px[0][:, :, None, :] + reach_out[..., None] * prof.normal[0][:, None, None, :]  # (4, s, 2, 2)
    h, w = gray.shape
    ends_in = ((ends >= 0.0).all(axis=-1) & (ends[..., 0] <= w - 1) & (ends[..., 1] <= h - 1)).all(axis=-1)  # (4, s)
    seen = np.where(hugging[:, None], ends_in, seen)
    clean = found[:, None] & seen & stepped & (step_contrast >= 0.5 * edge_contrast[:, None]) & (step_contrast <= 2.0 * edge_contrast[:, None] + 20.0)
    # A clipped black side is a highlight over the border. A clipped bright side (an over-exposed base) is harmless
    # unless the clip cuts into the upper half of the step's gradient, which pulls the step inwards.
    clean &= (_levels_at(vals, offsets, pos, (-3.5, -1.0), reduce=np.max) < SATURATED) & ~_clip_cuts_step(sub_vals)
    # Levels like the edge's own: an occluder (a glove over the border) steps to black from a duller grey, and
    # where it ends the border's step is displaced by the occluder's boundary: its neighbours are dropped too.
    ref_out = np.array([np.median(lv_out[k][clean[k]]) if clean[k].any() else np.inf for k in range(4)])
    ref_in = np.array([np.median(lv_in[k][clean[k]]) if clean[k].any() else -np.inf for k in range(4)])
    clean &= (lv_out >= ref_out[:, None] - 0.25 * edge_contrast[:, None]) & (lv_in <= ref_in[:, None] + 0.25 * edge_contrast[:, None])
    clean = ~cv2.dilate((~clean).astype(np.uint8), np.ones((1, 5), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    edge = prof.base_px[0] + pos[..., None] * prof.normal[0][:, None, :]             # (4, s, 2)
    keep = clean.copy()
    for _ in range(4):  # trim the outliers: a sample off the line by more than 3 robust sigmas (at least 0.4 px)
        fitted = keep.sum(axis=1) >= 2
        if (~fitted & found).any() and not allow_one_missing:
            break
        _, _, off_line, _ = fit_edge_lines(edge[None], keep[None])
        r = np.abs(off_line[0])
        med = np.array([np.median(r[k][keep[k]]) if fitted[k] else 0.0 for k in range(4)])
        cut = np.maximum(3.0 * 1.4826 * med, 0.4)
        new_keep = clean & (r <= cut[:, None]) & fitted[:, None]
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    spans = np.array([np.ptp(along[keep[k]]) if keep[k].sum() >= 2 else 0.0 for k in range(4)])
    return BorderSteps(points_px=edge, kept=keep, fraction=keep.mean(axis=1), spans=spans)


def _clip_cuts_step(profiles: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(4, s, w) profiles (offsets growing outwards, bright outside) -> (4, s): the clip at the bright side cuts
    into the upper half of the step's gradient, where :func:`.tag_edges.step_positions` takes the step from.

    A blurred step's gradient is symmetric about its peak; a clip that cuts it leaves the upper half's outer side
    shorter than its inner side (by over one sample) and the profile clipped just past it.
    """
    grad = np.clip(np.diff(profiles, axis=-1), 0.0, None)
    n = grad.shape[-1]
    peak = np.argmax(grad, axis=-1)
    upper = grad >= 0.5 * np.take_along_axis(grad, peak[..., None], axis=-1)
    idx = np.arange(n)
    # The contiguous run of the upper half around the peak: its first and last intervals.
    below_in = ~upper & (idx < peak[..., None])
    below_out = ~upper & (idx > peak[..., None])
    first = np.where(below_in.any(axis=-1), n - 1 - np.argmax(below_in[..., ::-1], axis=-1) + 1, 0)
    last = np.where(below_out.any(axis=-1), np.argmax(below_out, axis=-1) - 1, n - 1)
    after = np.minimum(last[..., None] + 1 + np.arange(3), profiles.shape[-1] - 1)    # the profile's next samples
    clipped_after = (np.take_along_axis(profiles, after, axis=-1) >= SATURATED).any(axis=-1)
    return clipped_after & ((last - peak) < (peak - first) - 1)


def _levels_at(vals: NDArray[np.float64], offsets: NDArray[np.float64], pos: NDArray[np.float64], span: tuple[float, float], *, reduce=np.mean) -> NDArray[np.float64]:
    """Per profile (4, s), ``reduce`` of the profile's grey levels at offsets ``pos + span[0] .. pos + span[1]`` (interpolated)."""
    rel = np.linspace(span[0], span[1], 4)
    at = pos[..., None] + rel                                                         # (4, s, 4)
    fidx = np.clip((at - offsets[0]) / (offsets[1] - offsets[0]), 0, len(offsets) - 1.001)
    i0 = np.floor(fidx).astype(int)
    t = fidx - i0
    v = np.take_along_axis(vals, i0, axis=2) * (1 - t) + np.take_along_axis(vals, i0 + 1, axis=2) * t
    return reduce(v, axis=2)


@dataclass(frozen=True, kw_only=True)
class CodeRead:
    """The code cells read through a tag's corners (:func:`read_code`).

    bits : (s * s,) uint8, 1 = white, row by row as ``dictionary_codes`` holds them.
    known : (s * s,) bool, the cells read (not saturated, beside a highlight, occluded or ambiguous).
    reason : why the tag could not be read at all ("" when it was; ``bits`` and ``known`` are then empty).
    """

    bits: NDArray[np.uint8]
    known: NDArray[np.bool_]
    reason: str = ""


@lru_cache(maxsize=4)
def _cell_grid(n: int) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """For a tag n cells across (black border included), cells -1 .. n (the white base's ring outside the tag, the
    black border, the code): their indices (n + 2,), 3 x 3 sample points in each cell in grid units (m, 1, 2)
    float32, and the masks (n + 2, n + 2) of the base beside each edge (not the diagonal corners), the border and the
    code. Read only (cached)."""
    idx = np.arange(-1, n + 1)
    sub = np.array([-0.25, 0.0, 0.25])
    cu = (idx[None, :, None, None] + 0.5 + sub[None, None, None, :]) * np.ones((len(idx), 1, 3, 1))  # column coordinate
    cv = (idx[:, None, None, None] + 0.5 + sub[None, None, :, None]) * np.ones((1, len(idx), 1, 3))  # row coordinate
    pts = np.stack([np.broadcast_to(cu, (len(idx), len(idx), 3, 3)), np.broadcast_to(cv, (len(idx), len(idx), 3, 3))], axis=-1)
    pts = np.ascontiguousarray(pts.reshape(-1, 1, 2), dtype=np.float32)
    r, c = np.meshgrid(idx, idx, indexing="ij")
    ring = ((r == -1) | (r == n)) ^ ((c == -1) | (c == n))
    border = (((r == 0) | (r == n - 1)) & (c >= 0) & (c < n)) | (((c == 0) | (c == n - 1)) & (r >= 0) & (r < n))
    code = (r >= 1) & (r <= n - 2) & (c >= 1) & (c <= n - 2)
    for a in (idx, pts, ring, border, code):
        a.setflags(write=False)
    return idx, pts, ring, border, code


def read_code(gray: NDArray[np.float32], corners: NDArray[np.float64], *, code_size: int, min_contrast: float = 30.0,
              partial: bool = False, covers: bool = False) -> CodeRead:
    """Read the s x s code cells of the tag whose corners (4, 2) px (the first taken as the tag's top-left) are given,
    with the rules of the module docstring (step 2): the white base around it, a black border, each cell judged
    against the levels of both. ``partial``: a tag partly out of the frame is read on its cells in the frame (the
    others unread; the levels from the base and border cells in the frame); otherwise it is refused. ``covers``: the cells
    reading white beside a sign of something over the tag (a border cell reading white, a cell brighter than the white
    base) are unknown too (step 2)."""
    s = code_size
    none = CodeRead(bits=np.zeros(0, np.uint8), known=np.zeros(0, bool), reason="")
    n = s + 2  # cells across the tag, black border included
    grid = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]], dtype=np.float32)
    h = cv2.getPerspectiveTransform(grid, corners.astype(np.float32))
    idx, pts, ring, border, code = _cell_grid(n)
    img_pts = cv2.perspectiveTransform(pts, h).reshape(-1, 2)
    height, width = gray.shape
    in_frame = ((img_pts >= 0).all(axis=1) & (img_pts[:, 0] <= width - 1) & (img_pts[:, 1] <= height - 1)).reshape(len(idx), len(idx), 9).all(axis=2)
    if not in_frame.all() and not partial:
        return replace(none, reason="the tag's surroundings leave the frame")
    v = cv2.remap(gray, img_pts[:, 0].reshape(1, -1), img_pts[:, 1].reshape(1, -1), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE).reshape(len(idx), len(idx), 9).astype(np.float64)
    mean, vmax, vmin = v.mean(axis=2), v.max(axis=2), v.min(axis=2)
    ring, border = ring & in_frame, border & in_frame
    if ring.sum() < 6 or border.sum() < 10:
        return replace(none, reason=f"too little of the tag's surroundings in the frame ({int(ring.sum())} base and {int(border.sum())} border cells)")
    white, black = float(np.median(mean[ring])), float(np.median(mean[border]))
    contrast = white - black
    if contrast < min_contrast:
        return replace(none, reason=f"no tag there: the border is not darker than its surroundings (contrast {contrast:.0f})")
    mid = 0.5 * (white + black)
    unknown = (np.abs(mean - mid) < 0.2 * contrast) | (vmax - vmin > 0.5 * contrast)
    bit = mean > mid
    # A clipped cell is unknown, and so is a cell beside a clipped one that reads white: a highlight only adds
    # light, so its halo can lift a black cell to white but never darken a white one (a black read there still counts).
    sat = mean >= SATURATED
    if white >= CLIPPED_BASE:
        # An over-exposed frame clips the white base and every white cell with it: a clipped cell is then no sign of
        # a highlight unless one shows beside it: a cell of the tag at neither level (a black one lifted, the halo), or
        # a border cell reading white (the highlight itself: the border is black).
        grey = (code | border) & in_frame & (mean > black + GLARE_LIFT * contrast) & (mean < white - GLARE_LIFT * contrast)
        sat &= cv2.dilate((grey | (border & bit)).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    halo = cv2.dilate(sat.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    unknown |= sat | (halo & bit) | ~in_frame
    read_border = border & ~unknown
    if read_border.sum() < 10 or (~bit[read_border]).mean() < 0.75:
        return replace(none, reason=f"no tag border there: {int((~bit[read_border]).sum())} of {int(read_border.sum())} border cells read black")
    if covers:
        # Something lies over the tag where a border cell reads white (the border is black) or a cell is brighter than
        # the white base: a light glove or a highlight, which lifts the black cells beside it to white.
        over = border & bit & ~unknown
        if white < CLIPPED_BASE:
            over |= (code | border) & in_frame & (mean > white + GLARE_LIFT * contrast)
        unknown |= cv2.dilate(over.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & bit
    return CodeRead(bits=bit[code].astype(np.uint8), known=~unknown[code])


def _verify(gray, corners, codes, aruco_id: int, *, min_cells: int, min_agreement: float, min_margin_cells: int, min_contrast: float,
            edge_fraction, rivals: Sequence[int] | None = None, min_cells_among_rivals: int = 8, placed_here: bool = False,
            partial: bool = False) -> TagRecovery:
    """Read the tag's cells through the homography of ``corners`` and judge its identity (see the module docstring)."""
    got = read_code(gray, corners, code_size=codes.shape[1], min_contrast=min_contrast, partial=partial, covers=True)
    if got.reason:
        return TagRecovery(corners_px=None, reason=got.reason, edge_fraction=edge_fraction)
    known, read = got.known, got.bits
    flat = codes.reshape(len(codes), -1)
    agree = ((flat == read[None, :]) & known[None, :]).sum(axis=1)
    n_read = int(known.sum())
    mine = int(agree[aruco_id])
    agree[aruco_id] = -1
    other = int(np.argmax(agree))
    common = dict(cells_read=n_read, cells_agreeing=mine, nearest_other_id=other, nearest_other_agreeing=int(agree[other]), edge_fraction=edge_fraction)
    if mine < min_agreement * n_read:
        return TagRecovery(corners_px=None, reason=f"{mine} of {n_read} code cells agree with id {aruco_id} (at least {100 * min_agreement:.0f} % needed)", **common)
    if n_read >= min_cells and mine - int(agree[other]) >= min_margin_cells:
        return TagRecovery(corners_px=corners, reason="", **common)
    if n_read >= min_cells and rivals is None:
        return TagRecovery(corners_px=None, reason=f"id {other} fits the cells read nearly as well ({int(agree[other])} vs {mine} of {n_read})", **common)
    if placed_here and rivals is not None and not set(int(r) for r in rivals) - {aruco_id}:
        # Identity by place: the marker is posed in fluoroscopy where its tag is found, and no other marker the
        # registration places can be here; the cells read (however few under a glare) only have to agree.
        return TagRecovery(corners_px=corners, reason="", **common)
    # Fewer cells than the dictionary-wide rule needs, or an id from outside the set near them: judged among the
    # ids that may lie there.
    if rivals is None or n_read < min_cells_among_rivals:
        return TagRecovery(corners_px=None, reason=f"only {n_read} code cells readable (at least {min_cells} needed"
                           + (f", or {min_cells_among_rivals} with the marker set's tags known)" if rivals is not None else ")"), **common)
    if int(agree[other]) >= mine:
        return TagRecovery(corners_px=None, reason=f"id {other} fits the {n_read} cells read as well as id {aruco_id}", **common)
    rival_ids = sorted({int(r) for r in rivals} - {aruco_id})
    if not rival_ids:
        return TagRecovery(corners_px=corners, reason="", **common)
    rival_codes = np.stack([np.rot90(codes[r], k).reshape(-1) for r in rival_ids for k in range(4)])
    rival_agree = ((rival_codes == read[None, :]) & known[None, :]).sum(axis=1)
    best = int(np.argmax(rival_agree))
    if mine - int(rival_agree[best]) < min_margin_cells:
        return TagRecovery(corners_px=None, reason=f"the marker set's id {rival_ids[best // 4]} fits the {n_read} cells read nearly as well "
                           f"({int(rival_agree[best])} vs {mine})", **common)
    return TagRecovery(corners_px=corners, reason="", **common)
