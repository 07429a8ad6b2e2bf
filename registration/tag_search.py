"""Tags the ArUco detector made no candidate of, found with no prediction: a tag's outline with a part hidden.

ArUco takes a tag only where its black border thresholds to a closed four-sided outline. A gloved finger over
one corner, or a highlight over part of the border, leaves a dark region shaped like a square with a bite out of
it: its outline has five or more sides, ArUco makes no candidate of it, and where no registration predicts the
tag (the first frame; a frame that shares no tag with fluoroscopy) :mod:`.tag_recovery` has nowhere to look.

Here the frame is thresholded as ArUco does (locally, at half resolution, a thin bridge between regions opened),
and each dark region's convex hull, which closes over the code's white cells and over the bite, is simplified to
a polygon. A four-sided hull is a candidate as it is. A hull of 5 to 7 sides gives the quadrilaterals that four of
its sides make, their corners where consecutive sides' lines cross (a hidden corner lies beyond the bite), kept
when the hull lies within the quadrilateral and fills at least ``MIN_FILL`` of it: the ``QUADS_PER_HULL`` best
filled, since the best filled is not always the tag (a glove over one corner leaves a short stretch of the edge
beyond it, and dropping that stretch's side instead of the glove's fills better). Then, for each candidate:

1. its four border edges are fitted as a predicted tag's are (:func:`.tag_recovery.fit_tag_edges`);
2. its code is read at each of its four rotations (:func:`.tag_recovery.read_code`) and judged over every id of
   the dictionary at every rotation: accepted only when at least ``min_cells`` cells are read, at least
   ``min_agreement`` of them agree with the best (id, rotation), no other (id, rotation) comes within
   ``min_margin_cells`` of it, and that id is one of those asked for. Where an id from outside the marker set comes
   that near (a highlight leaves 20-odd cells, and among 250 ids x 4 rotations one often agrees in all but two or
   three), the caller's ``rivals`` (the marker set's ids in that dictionary: the only tags in the field) judge
   instead: the best (id, rotation) still agrees in more cells than any other of the dictionary, and every rival
   at each rotation, and the best id at its other three, in at least ``min_margin_cells`` fewer.

A tag partly out of the frame is looked for on what of it is in the frame (its edges and cells in the frame). Its
dark region runs along the frame's edge, and the ends of that stretch are kept as vertices of the simplified hull
(where the tag's sides leave the frame), in a second outline beside the closed hull's: dropping the stretch's side
then puts the corner beyond the edge where the sides' lines cross, as for a bite. Only its quadrilaterals with a
corner beyond the edge are added (the rest would only crowd the candidates: the frame's background touches the edge
in many places).

No place vouches for a tag found this way, so it needs the dictionary-wide rule's 20 cells read even when the marker
set's ids judge it (the fewer-cells rule of :mod:`.tag_recovery`, 8 cells among the marker set's tags, needs a
predicted place and is not used).

Pure math: numpy and OpenCV's image functions.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .tag_recovery import TagRecovery, dictionary_codes, fit_tag_edges, read_code

__all__ = ["FoundTag", "tag_candidates", "identify_quad", "search_tags", "MIN_FILL", "QUADS_PER_HULL", "MAX_CANDIDATES"]

MIN_FILL = 0.7           # a candidate quadrilateral's area the dark region's hull must fill
THRESHOLD_WINDOWS = (19, 31)  # px at half resolution: ArUco's adaptive-threshold windows for tags 40-200 px across
MAX_HULL_SIDES = 7       # a square with one bite: 5-6 sides; more is not a tag
QUADS_PER_HULL = 3       # the best-filled quadrilaterals of one hull tried as candidates
# Candidates are taken largest first and the frame's background makes many large ones: on the operating-room twin
# (seeds 7001-7010, frames with every tag degraded) a gloved tag's right quadrilateral ranked up to 31st.
MAX_CANDIDATES = 64
SAME_QUAD_PX = 6.0       # two candidates whose corners all lie this close (px, at some rotation) are one
# How far the edges fitted to a candidate outline may put a corner from it, to be fitted once more from there (a
# bite's corner is loose: :func:`_fit_outline`); within 1.5 times the edge tolerance the first fit stands.
BITE_CORNER_SHIFT_PX = 24.0


@dataclass(frozen=True, kw_only=True)
class FoundTag:
    """A tag found by :func:`search_tags`.

    corners_px : (4, 2) sub-pixel corners, OpenCV order (TL, TR, BR, BL).
    cells_read, cells_agreeing : code cells read, and those agreeing with ``aruco_id``.
    runner_up_agreeing : the cells agreeing with the best other (id, rotation) of the dictionary.
    """

    aruco_id: int
    corners_px: NDArray[np.float64]
    cells_read: int
    cells_agreeing: int
    runner_up_agreeing: int


def _signed_area(poly: NDArray[np.float64]) -> float:
    """Twice the signed area (n, 2); positive for OpenCV's corner order (clockwise on screen, y down)."""
    x, y = poly[:, 0], poly[:, 1]
    return float(x[:-1] @ y[1:] - x[1:] @ y[:-1] + x[-1] * y[0] - x[0] * y[-1])


def _quads_of_hull(hull: NDArray[np.float64]) -> list[tuple[float, NDArray[np.float64]]]:
    """(fill, quad (4, 2)) for each quadrilateral four of the hull's sides (n, 2) make that holds the hull and is
    filled by it to ``MIN_FILL``; best filled first."""
    n = len(hull)
    if n == 4:
        return [(1.0, hull)]
    start = hull
    direction = np.roll(hull, -1, axis=0) - hull
    sides = np.array(list(itertools.combinations(range(n), 4)))                      # (c, 4), each in the hull's order
    p, d = start[sides], direction[sides]                                             # (c, 4, 2)
    p0, d0 = np.roll(p, 1, axis=1), np.roll(d, 1, axis=1)                             # the side before each
    # Corner j, where side j-1's line meets side j's: p0 + t d0 = p + u d.
    den = d0[..., 0] * d[..., 1] - d0[..., 1] * d[..., 0]
    ok = (np.abs(den) > 1e-9).all(axis=1)
    t = ((p - p0)[..., 0] * d[..., 1] - (p - p0)[..., 1] * d[..., 0]) / np.where(ok[:, None], den, 1.0)
    quads = p0 + t[..., None] * d0                                                    # (c, 4, 2); parallel sides: not ok
    # Convex with OpenCV's winding (the hull's own): every turn the same way as the hull's.
    e = np.roll(quads, -1, axis=1) - quads
    turn = e[..., 0] * np.roll(e, -1, axis=1)[..., 1] - e[..., 1] * np.roll(e, -1, axis=1)[..., 0]
    sign = np.sign(_signed_area(hull))
    ok &= (sign * turn > 0).all(axis=1)
    x, y = quads[..., 0], quads[..., 1]
    quad_area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))
    area = 0.5 * abs(_signed_area(hull))
    with np.errstate(divide="ignore", invalid="ignore"):
        fill = np.where(quad_area > 0, area / quad_area, 0.0)
    ok &= fill >= MIN_FILL
    # The hull within the quadrilateral (2 px of slack): on the inner side of each of its edges.
    length = np.linalg.norm(e, axis=2)                                                # (c, 4)
    rel = hull[None, None, :, :] - quads[:, :, None, :]                               # (c, 4, n, 2)
    inner = sign * (e[..., None, 0] * rel[..., 1] - e[..., None, 1] * rel[..., 0]) / np.maximum(length, 1e-9)[..., None]
    ok &= (inner >= -2.0).all(axis=(1, 2))
    order = np.argsort(-np.where(ok, fill, -1.0))
    return [(float(fill[i]), quads[i]) for i in order if ok[i]]


def _best_quads(poly: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """The ``QUADS_PER_HULL`` best-filled quadrilaterals (4, 2) of a simplified hull (n, 2); none for a hull of under 4
    or over ``MAX_HULL_SIDES`` sides."""
    if not 4 <= len(poly) <= MAX_HULL_SIDES:
        return []
    return [q for _, q in _quads_of_hull(poly)[:QUADS_PER_HULL]]


def _outlines(hull: NDArray[np.int32], epsilon_px: float, *, width: int, height: int) -> list[NDArray[np.float64]]:
    """A convex hull (m, 2) px of a region in a ``width`` x ``height`` frame simplified to polygons (n, 2)
    (Douglas-Peucker, ``epsilon_px``): the closed hull's; and where the hull runs along the frame's edge, also one
    that keeps the ends of its longest stretch there as vertices. Those ends are where a tag's sides leave the frame;
    simplifying the closed hull merges them into one vertex on the edge when the tag is cut near a corner, in place
    of the corner beyond the edge that the sides' lines meet at. Where a tag's sides show only a few pixels beside
    the edge their lines are loose, and the closed hull's outline can be the better: both are tried."""
    pts = hull.reshape(-1, 2).astype(np.int32)
    closed = cv2.approxPolyDP(pts.reshape(-1, 1, 2), epsilon_px, True).reshape(-1, 2).astype(np.float64)
    m = len(pts)
    nxt = np.roll(pts, -1, axis=0)
    along = ((pts[:, 0] == 0) & (nxt[:, 0] == 0)) | ((pts[:, 0] == width - 1) & (nxt[:, 0] == width - 1)) \
        | ((pts[:, 1] == 0) & (nxt[:, 1] == 0)) | ((pts[:, 1] == height - 1) & (nxt[:, 1] == height - 1))
    length = np.abs(nxt - pts).sum(axis=1) * along
    if m < 3 or length.max() < 2:
        return [closed]
    start = (int(np.argmax(length)) + 1) % m                # the stretch's far end, then round the hull to its near end
    chain = np.roll(pts, -start, axis=0)
    return [closed, cv2.approxPolyDP(chain.reshape(-1, 1, 2), epsilon_px, False).reshape(-1, 2).astype(np.float64)]


def _in_frame(quad: NDArray[np.float64], *, width: int, height: int, slack_px: float = 1.0) -> bool:
    """Whether every corner of a quadrilateral (4, 2) px lies in a ``width`` x ``height`` frame (``slack_px`` beyond it)."""
    return bool(((quad >= -slack_px) & (quad <= np.array([width - 1, height - 1]) + slack_px)).all())


def _same_as_any(quad: NDArray[np.float64], kept: NDArray[np.float64]) -> bool:
    """Whether a candidate (4, 2) px is one of ``kept`` (m, 4, 2), same winding: at some rotation every corner within
    ``SAME_QUAD_PX``."""
    if not len(kept):
        return False
    turns = np.stack([np.roll(quad, -k, axis=0) for k in range(4)])                 # (4, 4, 2)
    worst = np.linalg.norm(kept[:, None] - turns[None], axis=3).max(axis=2)          # (m, 4)
    return bool((worst <= SAME_QUAD_PX).any())


def tag_candidates(gray: NDArray[np.uint8], *, min_side_px: float = 24.0, max_candidates: int = MAX_CANDIDATES, half_above_px: int = 800,
                   exclude_px: Sequence[NDArray[np.float64]] = (), beyond_edge: bool = True) -> list[NDArray[np.float64]]:
    """Candidate tag outlines (4, 2) px, full resolution, OpenCV winding, in a grayscale frame (H, W) uint8: four-sided
    dark regions and dark regions with a bite (see the module docstring), at most ``max_candidates``, largest first.

    A frame wider than ``half_above_px`` is thresholded at half resolution (as the locator detects), a smaller one
    at its own. A candidate whose centre lies on one of ``exclude_px`` ((4, 2) corners of tags already found) is
    left out before the count. ``beyond_edge``: also the quadrilaterals of a hull cut by the frame's edge whose
    corner lies beyond it (see the module docstring); they are for a tag whose edges the fit then finds, and an
    outline's corners alone place them loosely."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"expected a grayscale (H, W) uint8 frame, got {gray.dtype} {gray.shape}")
    h, w = gray.shape
    small = cv2.resize(gray, (w // 2, h // 2), interpolation=cv2.INTER_AREA) if w > half_above_px else gray
    sx, sy = w / small.shape[1], h / small.shape[0]
    found: list[tuple[float, NDArray[np.float64]]] = []
    for window in THRESHOLD_WINDOWS:
        dark = cv2.adaptiveThreshold(small, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV, window, 7)
        dark = cv2.morphologyEx(dark, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        contours, _ = cv2.findContours(dark, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
        for contour in contours:
            hull = cv2.convexHull(contour)
            perimeter = cv2.arcLength(hull, True)
            if perimeter < 4 * min_side_px / sx:
                continue
            closed, *at_edge = _outlines(hull.reshape(-1, 2), 0.02 * perimeter, width=small.shape[1], height=small.shape[0])
            quads = _best_quads(closed)
            if beyond_edge:  # the edge-kept outline is for a corner beyond the edge: its quadrilaterals in the frame add nothing
                quads += [q for poly in at_edge for q in _best_quads(poly) if not _in_frame(q, width=small.shape[1], height=small.shape[0])]
            for quad in quads:
                quad = (quad + 0.5) * (sx, sy) - 0.5
                if _signed_area(quad) < 0:
                    quad = quad[::-1].copy()
                side = np.linalg.norm(np.roll(quad, -1, axis=0) - quad, axis=1)
                if side.min() < min_side_px or side.max() > 4.0 * side.min():
                    continue
                found.append((abs(_signed_area(quad)), quad))
    found.sort(key=lambda t: -t[0])
    taken = [np.asarray(q, dtype=np.float32).reshape(-1, 1, 2) for q in exclude_px]
    kept: list[NDArray[np.float64]] = []
    for _, quad in found:
        centre = tuple(float(c) for c in quad.mean(axis=0))
        if any(cv2.pointPolygonTest(t, centre, False) >= 0 for t in taken):
            continue
        if not _same_as_any(quad, np.asarray(kept).reshape(-1, 4, 2)):
            kept.append(quad)
        if len(kept) == max_candidates:
            break
    return kept


def identify_quad(gray: NDArray[np.float32], corners: NDArray[np.float64], *, dictionary: str, wanted: Sequence[int], min_cells: int = 20,
                  min_agreement: float = 0.9, min_margin_cells: int = 4, min_contrast: float = 30.0, partial: bool = False,
                  rivals: Sequence[int] | None = None) -> FoundTag | None:
    """The tag whose fitted corners (4, 2) px (OpenCV winding, any rotation) are given, when its code names one of
    ``wanted`` (ArUco ids of ``dictionary``) by the rule of the module docstring; None otherwise. ``partial``: read
    on the cells in the frame (:func:`.tag_recovery.read_code`). ``rivals``: the ArUco ids that may lie in the field
    (the marker set's, in ``dictionary``); None: any id of the dictionary (the dictionary-wide rule alone)."""
    codes = dictionary_codes(dictionary)
    flat = codes.reshape(len(codes), -1)
    agree = []
    for k in range(4):
        read = read_code(gray, np.roll(corners, -k, axis=0), code_size=codes.shape[1], min_contrast=min_contrast, partial=partial)
        if read.reason:
            return None
        agree.append(((flat == read.bits[None, :]) & read.known[None, :]).sum(axis=1))
        n_read = int(read.known.sum())
    table = np.stack(agree)                                                           # (4 rotations, ids)
    if n_read < min_cells:
        return None
    k, best = np.unravel_index(int(np.argmax(table)), table.shape)
    mine = int(table[k, best])
    table[k, best] = -1
    runner_up = int(table.max())
    if best not in set(int(i) for i in wanted) or mine < min_agreement * n_read or runner_up >= mine:
        return None
    if mine - runner_up < min_margin_cells:
        # An id from outside the set (or this id at another rotation) comes near: judged among those that may lie here.
        if rivals is None:
            return None
        near = table[:, sorted({int(r) for r in rivals} | {int(best)})]
        if mine - int(near.max()) < min_margin_cells:
            return None
    return FoundTag(aruco_id=int(best), corners_px=np.roll(corners, -int(k), axis=0), cells_read=n_read, cells_agreeing=mine, runner_up_agreeing=runner_up)


def _fit_outline(gray: NDArray[np.float32], quad: NDArray[np.float64], *, tolerance_px: float) -> TagRecovery:
    """The border edges of a candidate outline (4, 2) px fitted (:func:`.tag_recovery.fit_tag_edges`), once more from
    where they put the corners when that is farther than the fit allows but within ``BITE_CORNER_SHIFT_PX``.

    A bite's corner, where two of the hull's sides cross, lies where the sides of the bite point, not always where the
    tag's edges meet: a glove's edge that runs in at a slant bends the side beside it (seed 11700, flat markers: a
    hidden corner placed 14-17 px off). The edges near the other corners are found all the same and cross at the
    hidden corner; fitted again from there, every edge must show its border step where the tag now lies.
    """
    first = fit_tag_edges(gray, quad, tolerance_px=tolerance_px, partial=True, max_corner_shift_px=BITE_CORNER_SHIFT_PX)
    if not first.accepted or np.linalg.norm(first.corners_px - quad, axis=1).max() <= 1.5 * tolerance_px:
        return first
    return fit_tag_edges(gray, first.corners_px, tolerance_px=tolerance_px, partial=True)


def search_tags(gray: NDArray[np.uint8], *, dictionary: str, wanted: Sequence[int], exclude_px: Sequence[NDArray[np.float64]] = (),
                tolerance_px: float = 6.0, half_above_px: int = 800, rivals: Sequence[int] | None = None) -> list[FoundTag]:
    """The tags of ``wanted`` (ArUco ids of ``dictionary``) found in a grayscale frame (H, W) uint8 without a prediction.

    ``exclude_px``: (4, 2) corners of tags already found; a candidate whose centre lies on one is skipped.
    ``tolerance_px``: how far each fitted edge may lie from the candidate's outline (the outline comes from a
    half-resolution threshold, and a bite's corner from two edges' extensions). ``half_above_px``: see
    :func:`tag_candidates`. ``rivals``: the ArUco ids that may lie in the field (the marker set's, in
    ``dictionary``; see :func:`identify_quad`); None: the dictionary-wide rule alone. One tag per id.
    """
    wanted = [int(i) for i in wanted]
    if not wanted:
        return []
    gray_f = gray.astype(np.float32)
    code_size = dictionary_codes(dictionary).shape[1]
    taken: list[NDArray[np.float32]] = []  # tags found from earlier candidates (``exclude_px`` are left out by tag_candidates)
    found: dict[int, FoundTag] = {}
    for quad in tag_candidates(gray, half_above_px=half_above_px, exclude_px=exclude_px):
        centre = tuple(float(c) for c in quad.mean(axis=0))
        if any(cv2.pointPolygonTest(t, centre, False) >= 0 for t in taken):
            continue
        # A cheap look first: the outline's border reads black against a white base (a bite costs a few cells).
        if read_code(gray_f, quad, code_size=code_size, partial=True).reason:
            continue
        edges = _fit_outline(gray_f, quad, tolerance_px=tolerance_px)
        if not edges.accepted:
            continue
        tag = identify_quad(gray_f, edges.corners_px, dictionary=dictionary, wanted=[i for i in wanted if i not in found], partial=True,
                           rivals=rivals)
        if tag is not None:
            found[tag.aruco_id] = tag
            taken.append(tag.corners_px.astype(np.float32).reshape(-1, 1, 2))
    return [found[i] for i in sorted(found)]
