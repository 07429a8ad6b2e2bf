"""The twin's preoperative CT: the analytic pelvis voxelised in Hounsfield units.

The attenuation field is exactly the one the fluoroscopy renderer integrates
(body, cortical shells over cancellous bone, overlaps adding as they do there),
sampled on a CT grid with first-order partial-volume edges, the scanner's
blur and noise. So the product is handed a CT that is coarser and noisier
than the truth the fluoroscopy images, as a real preoperative CT is.
V, the CT frame, is the DICOM patient frame (LPS, mm) with the origin at the
pelvis centre.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from drillnav.registration.volume import MU_WATER_PER_MM, Volume

from .anatomy import pelvis_ellipsoids_carm

__all__ = ["make_pelvis_ct", "FIELD_MM"]

# Reconstructed field: x (patient left), y (posterior) and z (head) extents in V, mm.
FIELD_MM = ((-180.0, 180.0), (-180.0, 180.0), (-150.0, 150.0))


def _grid(voxel_mm: tuple[float, float, float]) -> tuple[tuple[int, int, int], NDArray[np.float64]]:
    """Shape (slices, rows, columns) and patient_from_voxel covering FIELD_MM."""
    dx, dy, dz = voxel_mm
    (x0, x1), (y0, y1), (z0, z1) = FIELD_MM
    ni, nj, nk = (int(round((hi - lo) / d)) for (lo, hi), d in zip(FIELD_MM, voxel_mm))
    a = np.diag([dx, dy, dz, 1.0])
    a[:3, 3] = [x0 + dx / 2, y0 + dy / 2, z0 + dz / 2]
    return (nk, nj, ni), a


def make_pelvis_ct(*, seed: int = 0, voxel_mm: tuple[float, float, float] = (1.0, 1.0, 1.0), noise_hu: float = 12.0, blur_mm: float = 0.5) -> Volume:
    """The pelvis phantom as an int16 HU volume with ``patient_from_voxel`` (air -1000 HU)."""
    shape, patient_from_voxel = _grid(voxel_mm)
    nk, nj, ni = shape
    mu = np.zeros(shape, np.float32)
    h = float(np.mean(voxel_mm))
    origin = patient_from_voxel[:3, 3]
    for centre, semi_axes, rotation, value in pelvis_ellipsoids_carm(np.eye(4)):
        extent = np.abs(rotation) @ semi_axes + 2 * h  # axis-aligned half-size of the rotated ellipsoid
        lo = np.floor((centre - extent - origin) / voxel_mm).astype(int)
        hi = np.ceil((centre + extent - origin) / voxel_mm).astype(int) + 1
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, [ni, nj, nk])
        if np.any(hi <= lo):
            continue
        xs = (origin[0] + voxel_mm[0] * np.arange(lo[0], hi[0]) - centre[0]).astype(np.float32)
        ys = (origin[1] + voxel_mm[1] * np.arange(lo[1], hi[1]) - centre[1]).astype(np.float32)
        inv = (rotation.T / semi_axes[:, None]).astype(np.float32)  # local scaled coordinates q = inv @ (p - c)
        for k in range(lo[2], hi[2]):
            z = np.float32(origin[2] + voxel_mm[2] * k - centre[2])
            q = [inv[r, 0] * xs[None, :] + inv[r, 1] * ys[:, None] + inv[r, 2] * z for r in range(3)]
            radius = np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2)
            # |grad r| = |q / a| / r: first-order distance to the surface in mm.
            grad = np.sqrt((q[0] / semi_axes[0]) ** 2 + (q[1] / semi_axes[1]) ** 2 + (q[2] / semi_axes[2]) ** 2) / np.maximum(radius, 1e-6)
            distance = (radius - 1.0) / np.maximum(grad, 1e-9)
            occupancy = np.clip(0.5 - distance / h, 0.0, 1.0)
            mu[k, lo[1] : hi[1], lo[0] : hi[0]] += np.float32(value) * occupancy
    if blur_mm > 0:
        mu = ndimage.gaussian_filter(mu, sigma=[blur_mm / v for v in voxel_mm[::-1]])
    hu = mu * np.float32(1000.0 / MU_WATER_PER_MM) - np.float32(1000.0)
    rng = np.random.default_rng([seed, 7])
    body = hu > -900
    hu[body] += rng.normal(scale=noise_hu, size=int(body.sum())).astype(np.float32)
    data = np.clip(np.rint(hu), -1024, 8191).astype(np.int16)
    return Volume(data=data, patient_from_voxel=patient_from_voxel, description=f"twin pelvis CT, {voxel_mm[0]:g}x{voxel_mm[1]:g}x{voxel_mm[2]:g} mm")
