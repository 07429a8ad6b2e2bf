"""Analytic X-ray line integrals for the twin: ellipsoids, spheres (BBs), the wire ring, the K-wire, the table.

All functions add ``mu * chord_length_mm`` (dimensionless line integrals) into a
detector image (rows, columns) for a :class:`CArmView`. Shapes are given in
frame C. Sampling is at pixel centres with ``supersample`` x ``supersample``
sub-pixels so that small BBs are imaged with their true partial-volume edges.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from drillnav.registration.carm import CArmView

__all__ = ["add_ellipsoids", "add_spheres", "add_ring", "add_cylinder", "add_slab", "add_box", "pixel_rays", "MU_PER_MM"]

# Linear attenuation at ~60 keV effective (1/mm).
MU_PER_MM = {"soft": 0.020, "cancellous": 0.030, "cortical": 0.055, "tungsten": 7.0, "steel": 0.95, "table": 0.008}


def pixel_rays(view: CArmView, *, supersample: int = 1) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Source (3,) and unit directions (rows*s, columns*s, 3) through sub-pixel centres."""
    s = supersample
    offs = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(view.columns)[:, None] + offs[None, :]).reshape(-1)
    v = (np.arange(view.rows)[:, None] + offs[None, :]).reshape(-1)
    uu, vv = np.meshgrid(u, v)
    m_inv = np.linalg.inv(view.projection_matrix[:, :3])
    d = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ m_inv.T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    src = view.source_position_mm
    centre = np.linalg.solve(view.projection_matrix[:, :3], [view.columns / 2, view.rows / 2, 1.0])
    if np.dot(centre, d[view.rows * s // 2, view.columns * s // 2]) < 0:
        d = -d
    return src, d


def _bin(image_ss: NDArray[np.float64], s: int) -> NDArray[np.float64]:
    """Sub-pixels (..., rows*s, columns*s) averaged to pixels (..., rows, columns)."""
    *lead, r, c = image_ss.shape
    return image_ss.reshape(*lead, r // s, s, c // s, s).mean(axis=(-3, -1))


def _window(view: CArmView, corners_mm: NDArray[np.float64]) -> tuple[slice, slice] | None:
    """Rows and columns (slices) of the detector that can see a body inside the convex hull of ``corners_mm`` (N, 3),
    two pixels to spare; None where it misses the detector. The whole detector where a corner is not in front of the
    source (the projection of the hull is then unbounded).

    A ray that misses the body adds exactly nothing, so the shapes below compute their chords in this window alone:
    the pelvis's ellipsoids, the K-wire and a retractor each cover a part of the field.
    """
    if np.any(view.depth_mm(corners_mm) <= 1.0):
        return slice(0, view.rows), slice(0, view.columns)
    px = view.project(corners_mm)
    c0, r0 = np.floor(px.min(axis=0)).astype(int) - 2
    c1, r1 = np.ceil(px.max(axis=0)).astype(int) + 3
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, view.columns), min(r1, view.rows)
    if c0 >= c1 or r0 >= r1:
        return None
    return slice(r0, r1), slice(c0, c1)


def _box_corners(centre: NDArray[np.float64], axes_scaled: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 8 corners (8, 3) of the box ``centre + axes_scaled @ (+-1, +-1, +-1)``; ``axes_scaled`` (3, 3) columns."""
    signs = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    return centre + signs @ axes_scaled.T


def add_ellipsoids(
    image: NDArray[np.float64],
    view: CArmView,
    ellipsoids: list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float]],
    *,
    rays: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> None:
    """Add solid ellipsoids ``(centre (3,), semi_axes_mm (3,), rotation (3,3) carm_from_local, mu)``.

    A negative ``mu`` subtracts (used for the cancellous cavity inside a cortical shell).
    """
    src, d = rays if rays is not None else pixel_rays(view)
    for centre, axes, rot, mu in ellipsoids:
        centre = np.asarray(centre, float)
        win = _window(view, _box_corners(centre, np.asarray(rot, float) * np.asarray(axes, float)[None, :]))
        if win is None:
            continue
        a = (rot / np.asarray(axes, float)[None, :]).T  # local scaled coords: A (x - c)
        u = a @ (src - centre)
        v = d[win] @ a.T
        vv = np.einsum("...i,...i->...", v, v)
        uv = v @ u
        disc = uv * uv - vv * (u @ u - 1.0)
        chord = np.where(disc > 0, 2.0 * np.sqrt(np.maximum(disc, 0.0)) / vv, 0.0)
        image[win] += mu * chord


def add_spheres(
    image: NDArray[np.float64],
    view: CArmView,
    centres_mm: NDArray[np.float64],
    radii_mm: NDArray[np.float64],
    mu: float | NDArray[np.float64],
    *,
    supersample: int = 3,
) -> None:
    """Add spheres by exact chord lengths in a window around each sphere's projection.

    Spheres whose windows lie inside the detector and have one size are computed together (a ring is a thousand
    of them), their chords added in the spheres' order; those the detector's edge cuts, one at a time. A pixel sums
    the same chords as one sphere at a time would, in another order only across those groups (equal to rounding).
    """
    centres = np.asarray(centres_mm, float).reshape(-1, 3)
    radii = np.broadcast_to(np.asarray(radii_mm, float), (centres.shape[0],))
    mus = np.broadcast_to(np.asarray(mu, float), (centres.shape[0],))
    src = view.source_position_mm
    px = view.project(centres)
    mag = view.magnification(centres)
    m_inv = np.linalg.inv(view.projection_matrix[:, :3])
    s = supersample
    offs = (np.arange(s) + 0.5) / s - 0.5
    halves = np.ceil(radii * mag / min(view.pixel_spacing_mm) + 2).astype(int)
    corner = np.rint(px).astype(int) - halves[:, None]  # (column, row) of each window's first pixel
    inside = (corner[:, 0] >= 0) & (corner[:, 1] >= 0) & (corner[:, 0] + 2 * halves + 1 <= view.columns) & (corner[:, 1] + 2 * halves + 1 <= view.rows)
    for i in np.flatnonzero(~inside):
        _add_sphere_clipped(image, corner[i], halves[i], centres[i] - src, radii[i], mus[i], m_inv, offs)
    for half in np.unique(halves[inside]):
        group = np.flatnonzero(inside & (halves == half))
        for chunk in np.array_split(group, -(-group.size // 256)):
            _add_spheres_inside(image, corner[chunk], int(half), centres[chunk] - src, radii[chunk], mus[chunk], m_inv, offs)


def _sphere_rays(u: NDArray[np.float64], v: NDArray[np.float64], m_inv: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit ray directions (..., rows*s, columns*s, 3) through sub-pixels ``u`` (..., columns*s) and ``v`` (..., rows*s),
    oriented towards the sphere at ``w`` (..., 3) from the source (the middle ray decides, one per window)."""
    uu = np.broadcast_to(u[..., None, :], (*u.shape[:-1], v.shape[-1], u.shape[-1]))
    vv = np.broadcast_to(v[..., :, None], uu.shape)
    d = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ m_inv.T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    middle = d[..., d.shape[-3] // 2, d.shape[-2] // 2, :]
    flip = np.einsum("...i,...i->...", w, middle) < 0
    return np.where(flip[..., None, None, None], -d, d)


def _chords(d: NDArray[np.float64], w: NDArray[np.float64], r: NDArray[np.float64]) -> NDArray[np.float64]:
    """Chord lengths (..., rows*s, columns*s) of rays ``d`` through spheres of radius ``r`` (...) at ``w`` (..., 3)."""
    t = np.einsum("...rci,...i->...rc", d, w)
    dist2 = np.einsum("...i,...i->...", w, w)[..., None, None] - t * t
    return 2.0 * np.sqrt(np.maximum(np.asarray(r)[..., None, None] ** 2 - dist2, 0.0))


def _add_spheres_inside(image: NDArray[np.float64], corner: NDArray[np.int64], half: int, w: NDArray[np.float64], r: NDArray[np.float64],
                        mu: NDArray[np.float64], m_inv: NDArray[np.float64], offs: NDArray[np.float64]) -> None:
    """K spheres whose (2 half + 1)-pixel windows at ``corner`` (K, 2: column, row) lie inside the detector: centres
    ``w`` (K, 3) from the source, radii ``r`` (K,), attenuations ``mu`` (K,); ``offs`` (s,) the sub-pixel offsets."""
    n, s = 2 * half + 1, offs.size
    steps = (np.arange(n)[:, None] + offs).reshape(-1)
    u = corner[:, 0:1] + steps
    v = corner[:, 1:2] + steps
    pixels = np.asarray(mu)[:, None, None] * _bin(_chords(_sphere_rays(u, v, m_inv, w), w, r), s)
    rows = corner[:, 1, None, None] + np.arange(n)[None, :, None]
    cols = corner[:, 0, None, None] + np.arange(n)[None, None, :]
    np.add.at(image, (np.broadcast_to(rows, pixels.shape), np.broadcast_to(cols, pixels.shape)), pixels)


def _add_sphere_clipped(image: NDArray[np.float64], corner: NDArray[np.int64], half: int, w: NDArray[np.float64], r: float, mu: float,
                        m_inv: NDArray[np.float64], offs: NDArray[np.float64]) -> None:
    """One sphere whose window (``corner`` (2,): column, row) the detector's edge cuts (arguments as
    :func:`_add_spheres_inside`, one sphere's)."""
    c0, r0 = int(corner[0]), int(corner[1])
    c1, r1 = c0 + 2 * half + 1, r0 + 2 * half + 1
    cc0, rr0, cc1, rr1 = max(c0, 0), max(r0, 0), min(c1, image.shape[1]), min(r1, image.shape[0])
    if cc0 >= cc1 or rr0 >= rr1:
        return
    u = (np.arange(cc0, cc1)[:, None] + offs).reshape(-1)
    v = (np.arange(rr0, rr1)[:, None] + offs).reshape(-1)
    image[rr0:rr1, cc0:cc1] += mu * _bin(_chords(_sphere_rays(u, v, m_inv, w), w, r), offs.size)


def add_ring(
    image: NDArray[np.float64],
    view: CArmView,
    carm_from_marker: NDArray[np.float64],
    *,
    radius_mm: float,
    wire_diameter_mm: float,
    mu: float,
) -> None:
    """Add the wire ring as a chain of overlapping spheres scaled to the tube's volume per length."""
    rho = wire_diameter_mm / 2.0
    spacing = rho / 2.0
    n = int(np.ceil(2 * np.pi * radius_mm / spacing))
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    local = np.stack([radius_mm * np.cos(t), radius_mm * np.sin(t), np.zeros(n), np.ones(n)], axis=1)
    centres = (local @ np.asarray(carm_from_marker).T)[:, :3]
    # Each sphere holds 4/3 pi rho^3; the tube holds pi rho^2 per mm.
    scale = np.pi * rho**2 * (2 * np.pi * radius_mm / n) / (4.0 / 3.0 * np.pi * rho**3)
    add_spheres(image, view, centres, np.full(n, rho), mu * scale, supersample=2)


def add_cylinder(
    image: NDArray[np.float64],
    view: CArmView,
    start_mm: NDArray[np.float64],
    end_mm: NDArray[np.float64],
    *,
    radius_mm: float,
    mu: float,
    rays: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> None:
    """Add a solid cylinder (a K-wire) from ``start_mm`` to ``end_mm`` (frame C) by exact chord lengths.

    Each ray's chord through the infinite cylinder is clipped to the slab
    between the two end planes, so the flat ends are imaged exactly.
    """
    src, d = rays if rays is not None else pixel_rays(view)
    p0, p1 = np.asarray(start_mm, float), np.asarray(end_mm, float)
    cube = _box_corners(np.zeros(3), radius_mm * np.eye(3))
    win = _window(view, np.concatenate([p0 + cube, p1 + cube]))
    if win is None:
        return
    image, d = image[win], d[win]
    length = float(np.linalg.norm(p1 - p0))
    a = (p1 - p0) / length
    w = src - p0
    da = d @ a
    d_perp = d - da[..., None] * a
    w_perp = w - (w @ a) * a
    qa = np.einsum("...i,...i->...", d_perp, d_perp)
    qb = 2.0 * (d_perp @ w_perp)
    qc = w_perp @ w_perp - radius_mm**2
    disc = qb * qb - 4.0 * qa * qc
    ok = (disc > 0) & (qa > 1e-12)
    root = np.sqrt(np.where(ok, disc, 0.0))
    qa_safe = np.where(ok, qa, 1.0)
    lo, hi = (-qb - root) / (2 * qa_safe), (-qb + root) / (2 * qa_safe)
    # Along the axis: s(t) = w.a + t d.a must lie in [0, length].
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (0.0 - w @ a) / da
        t1 = (length - w @ a) / da
    parallel = np.abs(da) < 1e-12
    lo = np.where(parallel, lo, np.maximum(lo, np.minimum(t0, t1)))
    hi = np.where(parallel, hi, np.minimum(hi, np.maximum(t0, t1)))
    image += mu * np.where(ok, np.clip(hi - lo, 0.0, None), 0.0)


def add_slab(image: NDArray[np.float64], view: CArmView, *, y_min_mm: float, y_max_mm: float, mu: float,
             rays: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None, half_width_mm: float = 250.0) -> None:
    """Add a slab between the planes y = y_min and y = y_max of frame C, |x| <= half_width (the table)."""
    src, d = rays if rays is not None else pixel_rays(view)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (y_min_mm - src[1]) / d[..., 1]
        t1 = (y_max_mm - src[1]) / d[..., 1]
    lo, hi = np.minimum(t0, t1), np.maximum(t0, t1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx0 = (-half_width_mm - src[0]) / d[..., 0]
        tx1 = (half_width_mm - src[0]) / d[..., 0]
    lo = np.maximum(lo, np.minimum(tx0, tx1))
    hi = np.minimum(hi, np.maximum(tx0, tx1))
    length = np.nan_to_num(np.clip(hi, 0, None) - np.clip(lo, 0, None), nan=0.0, posinf=0.0)
    image += mu * np.clip(length, 0.0, 200.0)


def add_box(
    image: NDArray[np.float64],
    view: CArmView,
    *,
    centre_mm: NDArray[np.float64],
    carm_from_box_rotation: NDArray[np.float64],
    half_size_mm: NDArray[np.float64],
    mu: float,
    rays: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> None:
    """Add a solid oriented box (a retractor blade) by exact chord lengths (slab method in the box's frame).

    ``carm_from_box_rotation`` (3, 3): the box's axes as columns in frame C; ``half_size_mm`` (3,) along them.
    """
    src, d = rays if rays is not None else pixel_rays(view)
    r = np.asarray(carm_from_box_rotation, dtype=np.float64)
    win = _window(view, _box_corners(np.asarray(centre_mm, dtype=np.float64), r * np.asarray(half_size_mm, dtype=np.float64)[None, :]))
    if win is None:
        return
    image, d = image[win], d[win]
    o = r.T @ (src - np.asarray(centre_mm, dtype=np.float64))
    db = d @ r
    lo = np.full(d.shape[:-1], -np.inf)
    hi = np.full(d.shape[:-1], np.inf)
    for k, h in enumerate(np.asarray(half_size_mm, dtype=np.float64)):
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (-h - o[k]) / db[..., k]
            t1 = (h - o[k]) / db[..., k]
        parallel = np.abs(db[..., k]) < 1e-12
        inside = abs(o[k]) <= h
        lo = np.where(parallel, np.where(inside, lo, np.inf), np.maximum(lo, np.minimum(t0, t1)))
        hi = np.where(parallel, np.where(inside, hi, -np.inf), np.minimum(hi, np.maximum(t0, t1)))
    image += mu * np.clip(np.nan_to_num(hi - lo, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
