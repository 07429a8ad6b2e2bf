"""Where a tag's outline really is, from the width of its black border.

A tag's corners come from steps across its outer edges (``tag_edges``): black border inside, white base outside.
Any effect that moves a step into the black moves the whole outline in, and the tag looks small: the camera puts
it too far away. The commonest is an over-exposed frame: the blurred step from black to a white base brighter
than the sensor's top is clipped, so its apparent middle lies on the dark side (on the operating-room twin, 100 of
144 study frames have 2 % or more of their pixels at 250 or over; on seeds 10902 and 11002 every tag of such a
frame had its corners 0.2-1.7 px inside their truth, along the tag's diagonals).

The border itself measures it. It is one code cell wide, and where a white code cell lies behind it, it has a
second step, from black to that cell's white, which the same effect moves into the black by the same amount: the
border looks thinner by twice the shift. Its true width is known from the tag's design and the corners'
homography (to the outline's small scale error). So, across the border at every white cell behind it, the outer
step ``a`` and the inner step ``b`` give the shift ``beta = (width - (b - a)) / 2``, and the true outer edge lies at
``a - beta``: how far that is inward of the edge the corners put there is what the outline must move. The median
over every such profile (a few dozen on a tag) is robust to a blood speck or a glove's edge on a few.

Only a tag whose white base is clipped around most of its border is measured, and only across the border where the
white cell behind it is clipped too: there both steps move alike. A glare spot clips the cells under it and not the
base, so its inner steps move and its outer ones do not; a well-exposed tag (whose steps lie where they are, to
about 0.05 px on the twin) is left as it was. On the operating-room twin's study frames (8 scenes, 47 tags) the
corners' RMS error against the truth went from 0.59 to 0.32 px at the median.

Pure math: numpy and OpenCV's remap and ArUco dictionaries.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from .tag_edges import edge_corners, step_positions

__all__ = ["code_cells", "border_shift_px", "moved_outline", "MIN_BORDER_PROFILES", "MIN_CELL_PX", "MAX_SHIFT_CELLS", "CLIPPED_LEVEL",
           "MIN_CLIPPED_SHARE"]

# Profiles a shift needs: a tag with few white cells along its border (or most of them hidden) keeps its corners.
MIN_BORDER_PROFILES = 8
# Below this a code cell is too narrow for two steps to be told apart across it (a far or small tag).
MIN_CELL_PX = 5.0
# A shift over this share of a cell is no exposure's or blur's: a wrong step (a glove's edge, a neighbouring
# cell's step under heavy blur) and the corners are kept.
MAX_SHIFT_CELLS = 0.3
# A grey level at or over this is taken as clipped (8-bit frames).
CLIPPED_LEVEL = 250.0
# The share of a tag's border profiles whose white base outside must be clipped for its outline to be measured.
MIN_CLIPPED_SHARE = 0.5
# Across the border: from 0.6 cells outside the outline to 1.6 cells in (the white cell behind it), in steps
# of this many cells, at 3 places along each white cell.
_REACH_CELLS = (-0.6, 1.6)
_STEP_CELLS = 0.025
_ALONG = (0.3, 0.5, 0.7)


@lru_cache(maxsize=512)
def code_cells(dictionary: str, aruco_id: int) -> NDArray[np.bool_]:
    """(g, g) whether each cell of the tag is white, its black border included (g = the code's size + 2): row 0 is
    the side from corner 0 to corner 1 (OpenCV's order), as the tag is printed."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    g = int(d.markerSize) + 2
    cells = cv2.aruco.generateImageMarker(d, int(aruco_id), g) > 127
    cells.setflags(write=False)
    return cells


@lru_cache(maxsize=512)
def _profiles(white_bytes: bytes, g: int) -> NDArray[np.float64]:
    """Canonical sample points (P, S, 2) (x, y in cells, the tag spanning 0..g) across the border at the white cells of
    the (g, g) pattern ``white_bytes`` (:func:`code_cells`' bytes)."""
    white = np.frombuffer(white_bytes, dtype=np.bool_).reshape(g, g)
    t = np.arange(_REACH_CELLS[0], _REACH_CELLS[1] + _STEP_CELLS / 2, _STEP_CELLS)
    out = []
    for c in range(1, g - 1):
        for f in _ALONG:
            u = c + f
            if white[1, c]:  # top side, inward is +y
                out.append(np.stack([np.full_like(t, u), t], axis=1))
            if white[c, g - 2]:  # right side, inward is -x
                out.append(np.stack([g - t, np.full_like(t, u)], axis=1))
            if white[g - 2, c]:  # bottom side, inward is -y
                out.append(np.stack([np.full_like(t, u), g - t], axis=1))
            if white[c, 1]:  # left side, inward is +x
                out.append(np.stack([t, np.full_like(t, u)], axis=1))
    pts = np.asarray(out, dtype=np.float64).reshape(-1, len(t), 2)
    pts.setflags(write=False)
    return pts


def border_shift_px(gray: NDArray[np.float32], corners_px: NDArray[np.float64], white: NDArray[np.bool_]) -> tuple[float, int]:
    """How far (px) the tag's true outline lies inward of the one ``corners_px`` (4, 2) put (negative: outward, the
    case of a clipped base), and the number of profiles it rests on (0: not measured).

    gray : (H, W) float32 frame. white : (g, g) :func:`code_cells`.
    """
    corners = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    g = white.shape[0]
    canon = np.array([[0, 0], [g, 0], [g, g], [0, g]], dtype=np.float32)
    homography = cv2.getPerspectiveTransform(canon, corners.astype(np.float32))
    side_px = float(np.mean(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)))
    if side_px / g < MIN_CELL_PX:
        return 0.0, 0
    canon_pts = _profiles(white.tobytes(), g)
    if len(canon_pts) < MIN_BORDER_PROFILES:
        return 0.0, 0
    p, s = canon_pts.shape[:2]
    img = cv2.perspectiveTransform(canon_pts.reshape(1, -1, 2), homography).reshape(p, s, 2)
    h, w = gray.shape
    inside = ((img[..., 0] >= 0) & (img[..., 0] <= w - 1) & (img[..., 1] >= 0) & (img[..., 1] <= h - 1)).all(axis=1)
    if inside.sum() < MIN_BORDER_PROFILES:
        return 0.0, 0
    img = img[inside]
    t = np.arange(_REACH_CELLS[0], _REACH_CELLS[1] + _STEP_CELLS / 2, _STEP_CELLS)
    # Only a tag whose white base is clipped around most of it (an over-exposed frame, not a glare spot) is measured,
    # and only across the border where the white cell behind it is clipped too: there both steps move alike. A glare
    # spot clips the cells under it and lifts the border there, so its inner steps move and its outer ones do not (a
    # glared tag of the twin, seed 5114, measured 0.40 px outwards where the truth is 0). The base is looked at
    # first: a well-exposed tag costs only that.
    outside = t <= -0.25
    base = cv2.remap(gray, img[:, outside, 0].astype(np.float32), img[:, outside, 1].astype(np.float32), cv2.INTER_LINEAR)
    clipped_out = base.max(axis=1) >= CLIPPED_LEVEL
    if clipped_out.mean() < MIN_CLIPPED_SHARE:
        return 0.0, 0
    values = cv2.remap(gray, img[..., 0].astype(np.float32), img[..., 1].astype(np.float32), cv2.INTER_LINEAR)
    half = t < 0.5
    a, ok_a = step_positions(values[:, half], t[half])      # outer step, cells
    b, ok_b = step_positions(values[:, ~half], t[~half])    # inner step, cells
    clipped_in = values[:, t >= 1.25].max(axis=1) >= CLIPPED_LEVEL
    ok = ok_a & ok_b & clipped_out & clipped_in
    if ok.sum() < MIN_BORDER_PROFILES:
        return 0.0, 0

    # Each profile is a straight segment in the image (a homography keeps lines), but its canonical parameter is not
    # linear in px: depths are mapped through the homography and measured along the segment.
    first, last = canon_pts[inside, 0], canon_pts[inside, -1]
    start, along = img[:, 0], img[:, -1] - img[:, 0]
    along /= np.linalg.norm(along, axis=1, keepdims=True)

    def at(u: NDArray[np.float64]) -> NDArray[np.float64]:
        """px along each profile from its first sample to canonical depth ``u`` (per profile)."""
        q = first + (last - first) * ((np.asarray(u, dtype=np.float64) - t[0]) / (t[-1] - t[0]))[:, None]
        qi = cv2.perspectiveTransform(q.reshape(1, -1, 2), homography).reshape(-1, 2)
        return np.sum((qi - start) * along, axis=1)

    a_px, b_px = at(a), at(b)
    e0, e1 = at(np.zeros(len(a))), at(np.ones(len(a)))
    beta = ((e1 - e0) - (b_px - a_px)) / 2.0
    shift = (a_px - beta - e0)[ok]
    median = float(np.median(shift))
    if abs(median) > MAX_SHIFT_CELLS * side_px / g:
        return 0.0, 0
    return median, int(ok.sum())


def moved_outline(corners_px: NDArray[np.float64], inward_px: float) -> NDArray[np.float64]:
    """Corners (4, 2) of the quadrilateral whose every side lies ``inward_px`` further inside (negative: outside)
    than ``corners_px``'s, each corner the crossing of its two moved sides."""
    q = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    centre = q.mean(axis=0)
    nxt = np.roll(q, -1, axis=0)
    d = (nxt - q) / np.linalg.norm(nxt - q, axis=1, keepdims=True)          # side k: corner k -> k + 1
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    n *= np.sign(np.sum((centre - (q + nxt) / 2) * n, axis=1))[:, None]    # inward normals
    corners, _ = edge_corners((q + inward_px * n)[None], d[None])           # corner k: sides k - 1 and k, moved
    return corners[0]
