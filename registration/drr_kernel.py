"""The DRR ray-casting kernel, compiled by numba (see :mod:`drillnav.registration.drr`).

A module of its own so that importing :mod:`drillnav.registration.drr` does not
import numba (~0.4 s): numba loads, and the kernel compiles or loads from its
cache (``cache=True``: ``__pycache__`` beside this file, or ``NUMBA_CACHE_DIR``),
on the first rendered DRR.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["drr_kernel"]


@numba.njit(parallel=True, fastmath=True, cache=True, boundscheck=False, nogil=True)
def drr_kernel(mu, origin_vox, vox_from_pix, carm_from_pix, step_mm, row0, col0, stride, out):  # pragma: no cover - compiled
    nk, nj, ni = mu.shape
    rows, cols = out.shape
    hi_i, hi_j, hi_k = ni - 1.0, nj - 1.0, nk - 1.0
    for r in numba.prange(rows):
        v = row0 + r * stride
        for c in range(cols):
            u = col0 + c * stride
            # Ray direction in C-arm mm (for its length) and in voxel units per mm.
            wx = carm_from_pix[0, 0] * u + carm_from_pix[0, 1] * v + carm_from_pix[0, 2]
            wy = carm_from_pix[1, 0] * u + carm_from_pix[1, 1] * v + carm_from_pix[1, 2]
            wz = carm_from_pix[2, 0] * u + carm_from_pix[2, 1] * v + carm_from_pix[2, 2]
            inv_len = 1.0 / np.sqrt(wx * wx + wy * wy + wz * wz)
            di = (vox_from_pix[0, 0] * u + vox_from_pix[0, 1] * v + vox_from_pix[0, 2]) * inv_len
            dj = (vox_from_pix[1, 0] * u + vox_from_pix[1, 1] * v + vox_from_pix[1, 2]) * inv_len
            dk = (vox_from_pix[2, 0] * u + vox_from_pix[2, 1] * v + vox_from_pix[2, 2]) * inv_len
            # Slab clipping against [0, n-1] on each axis; t in mm along the ray.
            t0 = -1e30
            t1 = 1e30
            for o, d, hi in ((origin_vox[0], di, hi_i), (origin_vox[1], dj, hi_j), (origin_vox[2], dk, hi_k)):
                if abs(d) < 1e-12:
                    if o < 0.0 or o > hi:
                        t0 = 1e30
                else:
                    a = (0.0 - o) / d
                    b = (hi - o) / d
                    if a > b:
                        a, b = b, a
                    t0 = max(t0, a)
                    t1 = min(t1, b)
            total = 0.0
            if t1 > t0:
                n = int((t1 - t0) / step_mm)
                t = t0 + 0.5 * ((t1 - t0) - (n - 1) * step_mm) if n > 0 else t0
                for _ in range(n):
                    x = origin_vox[0] + t * di
                    y = origin_vox[1] + t * dj
                    z = origin_vox[2] + t * dk
                    i0 = min(max(int(x), 0), ni - 2)
                    j0 = min(max(int(y), 0), nj - 2)
                    k0 = min(max(int(z), 0), nk - 2)
                    fx = x - i0
                    fy = y - j0
                    fz = z - k0
                    c00 = mu[k0, j0, i0] + fx * (mu[k0, j0, i0 + 1] - mu[k0, j0, i0])
                    c01 = mu[k0, j0 + 1, i0] + fx * (mu[k0, j0 + 1, i0 + 1] - mu[k0, j0 + 1, i0])
                    c10 = mu[k0 + 1, j0, i0] + fx * (mu[k0 + 1, j0, i0 + 1] - mu[k0 + 1, j0, i0])
                    c11 = mu[k0 + 1, j0 + 1, i0] + fx * (mu[k0 + 1, j0 + 1, i0 + 1] - mu[k0 + 1, j0 + 1, i0])
                    c0 = c00 + fy * (c01 - c00)
                    c1 = c10 + fy * (c11 - c10)
                    total += c0 + fz * (c1 - c0)
                    t += step_mm
            out[r, c] = total * step_mm
