"""Rings that overlap in projection: one piece of wire split into the ellipses it is made of.

Markers lie close together on the anterior skin, so in a lateral view (and at
steep random angles) their rings project across one another and their wires
form one connected piece, too large to be one ring. Such a piece is split by
RANSAC: ellipses through five of its pixels (drawn near one another, so that
they tend to lie on one ring) are scored by how much of their circumference
the piece's pixels follow; the best is refitted to the pixels along it and
taken when the wire follows most of its circumference (of its part inside the
field, for a ring the image's edge cuts); its pixels leave the piece, and the
next ring is looked for among the rest.

Pure math: numpy and OpenCV's ellipse fit.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["split_rings", "ellipse_distance", "sectors_in_field"]

# Of 36 sectors of an ellipse's circumference (10 deg each about its centre, in the circle's own angle), those the
# piece's pixels must reach for it to be a ring: a ring crossed by another ring, a K-wire or a clamp's jaw still
# shows most of its wire; a chance ellipse through parts of two rings follows them over much less.
MIN_SECTORS = 27
SECTORS = 36
# A ring cut by the field's edge is judged on the sectors whose arc lies in the field: the piece's pixels must reach
# MIN_SECTORS / SECTORS of those, and at least this many must lie in the field (half the ring: the detector keeps a
# lone ring cut by the edge only when its arc spans half a turn). Two rings crossing at the top of a lateral view,
# each cut by the edge (seed 11000's AP+lateral pair, markers 0 and 22, 65-68 deg to the beam, all their BBs in the
# field), follow 20 of their 23 sectors in the field and 26 of 24 (a wire's pixels at the edge reach one more): at 27
# of 36 neither was split out, and the piece identified no marker.
MIN_SECTORS_IN_FIELD = 18
# Draws per ring looked for; the five pixels of a draw are taken within a ring's largest extent of the first one.
DRAWS = 500
# The grid (px) the fits run on: a wire 4-6 px wide holds several of its pixels per step along it.
_GRID_PX = 2.0


def ellipse_distance(points_px: NDArray[np.float64], ellipse) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(distance (N,) px, angle (N,) rad): each point's distance from ``ellipse`` (as cv2.fitEllipse gives it) to
    first order (Sampson's: the conic's value over its gradient's length, the normal distance near the curve, where a
    ray from the centre would run obliquely along a flat ellipse's sides), and its angle about the centre in the
    circle's own parameter."""
    (cx, cy), (d1, d2), angle = ellipse
    a = np.radians(angle)
    dx, dy = points_px[:, 0] - cx, points_px[:, 1] - cy
    u = dx * np.cos(a) + dy * np.sin(a)
    v = -dx * np.sin(a) + dy * np.cos(a)
    ha, hb = max(d1 / 2.0, 1e-6), max(d2 / 2.0, 1e-6)
    ru, rv = u / ha, v / hb
    # F = ru^2 + rv^2 - 1 is the squared radius's excess: its value over |grad F| is the first-order distance. With
    # F = r^2 - 1 = (r - 1)(r + 1), the (r + 1) factor is taken as 2 r so that far points do not count double.
    r = np.hypot(ru, rv) + 1e-12
    grad = 2.0 * np.hypot(u / ha**2, v / hb**2) + 1e-12
    return np.abs(r - 1.0) * 2.0 * r / grad, np.arctan2(rv, ru)


def _sectors(theta: NDArray[np.float64]) -> int:
    return int(np.unique(((theta + np.pi) / (2 * np.pi) * SECTORS).astype(int) % SECTORS).size)


def split_rings(points_px: NDArray[np.float32], *, min_major_px: float, max_major_px: float, wire_px: float,
                min_minor_ratio: float = 0.2, max_rings: int = 4, seed: int = 0, shape: tuple[int, int] | None = None
                ) -> tuple[NDArray[np.float32], ...]:
    """The rings (each its pixels (K, 2) float32, column, row) that one piece of wire ``points_px`` (N, 2) is made of.

    A ring is an ellipse of major axis ``min_major_px``-``max_major_px`` whose minor axis is at least
    ``min_minor_ratio`` of its major (flatter is edge-on, which identifies nothing: the detector passes its
    ``EDGE_ON_MINOR_RATIO``), whose circumference the
    piece's pixels follow over MIN_SECTORS of SECTORS sectors within ``wire_px`` (the wire's width). Its pixels are
    those within ``wire_px`` of it; a pixel where two rings cross goes to both. Deterministic for one ``seed``.
    Empty when no ring is found, as for a piece that is no ring at all.

    ``shape``: the image's (rows, columns); a ring cut by its edge then needs MIN_SECTORS of SECTORS of the sectors
    whose arc lies in the field, and at least ``MIN_SECTORS_IN_FIELD`` of those (None: every sector counts).
    """
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 10:
        return ()
    grid = np.unique(np.round(pts / _GRID_PX).astype(np.int64), axis=0).astype(np.float64) * _GRID_PX
    tol = max(1.5, 0.5 * wire_px)  # a pixel this near a candidate counts for it
    rng = np.random.default_rng(seed)
    left = np.ones(len(grid), dtype=bool)
    rings = []
    for _ in range(max_rings):
        pool = grid[left]
        if len(pool) < SECTORS:
            break
        best = _best_draw(pool, rng, min_major_px=min_major_px, max_major_px=max_major_px, min_minor_ratio=min_minor_ratio, tol=tol, shape=shape)
        if best is None:
            break
        ellipse = best
        for _ in range(3):  # refit to the pixels along it
            d, _theta = ellipse_distance(pool, ellipse)
            near = d < tol
            if near.sum() < 5:
                break
            ellipse = cv2.fitEllipse(pool[near].astype(np.float32).reshape(-1, 1, 2))
        d, theta = ellipse_distance(pool, ellipse)
        if not _follows(_sectors(theta[d < tol]), ellipse, shape) or not _shape_ok(ellipse, min_major_px, max_major_px, min_minor_ratio):
            break
        rings.append(ellipse)
        # The wire's far side too: a thick wire would otherwise give the same ring again from its outer pixels.
        gone = np.flatnonzero(left)[d < wire_px]
        left[gone] = False
    out = []
    for ellipse in rings:
        d, _theta = ellipse_distance(pts, ellipse)
        out.append(np.asarray(points_px, dtype=np.float32).reshape(-1, 2)[d < wire_px])
    return tuple(out)


def sectors_in_field(ellipse, shape: tuple[int, int], *, margin_px: float = 2.0) -> int:
    """How many of the SECTORS sectors of ``ellipse`` (as cv2.fitEllipse gives it) have their arc's middle inside an
    image of ``shape`` (rows, columns), ``margin_px`` from its edge."""
    (cx, cy), (d1, d2), angle = ellipse
    a = np.radians(angle)
    t = -np.pi + (np.arange(SECTORS) + 0.5) * (2.0 * np.pi / SECTORS)
    u, v = d1 / 2.0 * np.cos(t), d2 / 2.0 * np.sin(t)
    x = cx + u * np.cos(a) - v * np.sin(a)
    y = cy + u * np.sin(a) + v * np.cos(a)
    rows, cols = shape
    return int(np.count_nonzero((x >= margin_px) & (x <= cols - 1 - margin_px) & (y >= margin_px) & (y <= rows - 1 - margin_px)))


def _follows(covered: int, ellipse, shape: tuple[int, int] | None) -> bool:
    """Whether the wire covering ``covered`` sectors of ``ellipse`` follows it as a ring's (:data:`MIN_SECTORS`), counting
    only the sectors in the field of an image of ``shape`` (None: all)."""
    if shape is None:
        return covered >= MIN_SECTORS
    visible = sectors_in_field(ellipse, shape)
    return visible >= MIN_SECTORS_IN_FIELD and covered * SECTORS >= MIN_SECTORS * visible


def _shape_ok(ellipse, min_major_px: float, max_major_px: float, min_minor_ratio: float) -> bool:
    (cx, cy), (d1, d2), _angle = ellipse
    if not np.all(np.isfinite([cx, cy, d1, d2])):
        return False
    major, minor = max(d1, d2), min(d1, d2)
    return min_major_px <= major <= max_major_px and minor >= min_minor_ratio * major


def _best_draw(pool: NDArray[np.float64], rng: np.random.Generator, *, min_major_px: float, max_major_px: float,
               min_minor_ratio: float, tol: float, shape: tuple[int, int] | None = None):
    """The drawn ellipse whose circumference ``pool``'s pixels follow over most sectors (most pixels on a tie), or None.
    With ``shape`` (rows, columns) the share of its sectors in the field that they follow counts, among ellipses with
    at least :data:`MIN_SECTORS_IN_FIELD` there: a ring cut by the edge is no worse a ring for it."""
    best, best_score = None, -1
    for _ in range(DRAWS):
        first = pool[rng.integers(len(pool))]
        near = np.flatnonzero(np.abs(pool - first).max(axis=1) < max_major_px)
        if len(near) < 5:
            continue
        five = pool[rng.choice(near, 5, replace=False)]
        try:
            ellipse = cv2.fitEllipse(five.astype(np.float32).reshape(-1, 1, 2))
        except cv2.error:
            continue
        if not _shape_ok(ellipse, min_major_px, max_major_px, min_minor_ratio):
            continue
        visible = SECTORS if shape is None else sectors_in_field(ellipse, shape)
        if visible < MIN_SECTORS_IN_FIELD:
            continue
        d, theta = ellipse_distance(pool, ellipse)
        on = d < tol
        score = _sectors(theta[on]) * SECTORS / visible * len(pool) + int(on.sum())
        if score > best_score:
            best, best_score = ellipse, score
    return best
