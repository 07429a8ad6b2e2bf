"""Compiled look-ups in a signed-distance volume, for conformance at camera rate.

scipy's ``map_coordinates`` costs about 0.6 us a point and holds the GIL;
the radial clearance of one axis needs ~400k points, 19 ms on the frame
path. These numba kernels give the same numbers (trilinear, a constant
``outside`` beyond the grid's outermost voxel centres), stop each ray at
its first crossing, and release the GIL.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["sample_trilinear", "first_crossings"]


@numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
def _trilinear(vol, a, x, y, z, outside):  # pragma: no cover - compiled
    """``vol`` (k, j, i) at patient point (x, y, z); ``a`` (3, 4) voxel_from_patient giving (i, j, k)."""
    fi = a[0, 0] * x + a[0, 1] * y + a[0, 2] * z + a[0, 3]
    fj = a[1, 0] * x + a[1, 1] * y + a[1, 2] * z + a[1, 3]
    fk = a[2, 0] * x + a[2, 1] * y + a[2, 2] * z + a[2, 3]
    nk, nj, ni = vol.shape
    if not (0.0 <= fi <= ni - 1.0 and 0.0 <= fj <= nj - 1.0 and 0.0 <= fk <= nk - 1.0):
        return outside
    i0, j0, k0 = min(int(fi), ni - 2), min(int(fj), nj - 2), min(int(fk), nk - 2)
    ti, tj, tk = fi - i0, fj - j0, fk - k0
    c00 = vol[k0, j0, i0] * (1 - ti) + vol[k0, j0, i0 + 1] * ti
    c01 = vol[k0, j0 + 1, i0] * (1 - ti) + vol[k0, j0 + 1, i0 + 1] * ti
    c10 = vol[k0 + 1, j0, i0] * (1 - ti) + vol[k0 + 1, j0, i0 + 1] * ti
    c11 = vol[k0 + 1, j0 + 1, i0] * (1 - ti) + vol[k0 + 1, j0 + 1, i0 + 1] * ti
    return (c00 * (1 - tj) + c01 * tj) * (1 - tk) + (c10 * (1 - tj) + c11 * tj) * tk


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _sample(vol, a, pts, outside, out):  # pragma: no cover - compiled
    for n in range(pts.shape[0]):
        out[n] = _trilinear(vol, a, pts[n, 0], pts[n, 1], pts[n, 2], outside)


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _crossings(vol, a, centres, dirs, n_steps, step, reach, outside, out):  # pragma: no cover - compiled
    for n in range(centres.shape[0]):
        best = reach
        for r in range(dirs.shape[0]):
            prev = 0.0
            for m in range(n_steps):
                rr = m * step
                v = _trilinear(vol, a, centres[n, 0] + dirs[r, 0] * rr, centres[n, 1] + dirs[r, 1] * rr, centres[n, 2] + dirs[r, 2] * rr, outside)
                if v <= 0.0:
                    if m == 0:
                        crossing = 0.0
                    else:
                        frac = prev / max(prev - v, 1e-9)
                        crossing = (m - 1) * step + min(max(frac, 0.0), 1.0) * step
                    if crossing < best:
                        best = crossing
                    break
                if rr >= best:  # this ray can no longer beat the nearest crossing found
                    break
                prev = v
        out[n] = best


def sample_trilinear(distance_mm: NDArray[np.float32], voxel_from_patient: NDArray[np.float64], points_mm: NDArray[np.float64],
                     *, outside: float) -> NDArray[np.float64]:
    """Values (N,) of ``distance_mm`` (slices, rows, columns) at patient points (N, 3); ``outside`` beyond the grid."""
    pts = np.ascontiguousarray(np.atleast_2d(points_mm), dtype=np.float64)
    out = np.empty(pts.shape[0])
    _sample(distance_mm, np.ascontiguousarray(voxel_from_patient[:3], dtype=np.float64), pts, float(outside), out)
    return out


def first_crossings(distance_mm: NDArray[np.float32], voxel_from_patient: NDArray[np.float64], centres_mm: NDArray[np.float64],
                    directions: NDArray[np.float64], *, reach_mm: float, step_mm: float, outside: float) -> NDArray[np.float64]:
    """(N,) smallest distance, over unit ``directions`` (R, 3), from each centre (N, 3) to where the value first
    turns non-positive, linearly interpolated between steps of ``step_mm``; ``reach_mm`` when no ray crosses within it."""
    n_steps = int(np.floor(reach_mm / step_mm + 1e-9)) + 1
    out = np.empty(len(centres_mm))
    _crossings(distance_mm, np.ascontiguousarray(voxel_from_patient[:3], dtype=np.float64), np.ascontiguousarray(centres_mm, dtype=np.float64),
               np.ascontiguousarray(directions, dtype=np.float64), n_steps, float(step_mm), float(reach_mm), float(outside), out)
    return out
