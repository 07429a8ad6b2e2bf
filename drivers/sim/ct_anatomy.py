"""A real CT as the twin's anatomy (``drillnav sim scene --anatomy``).

The rule is the same as for the analytic pelvis: the twin images a finer
truth than the product is given. Fluoroscopy integrates the CT as read, at
its full resolution with a fine ray step; the product is handed a copy
resampled onto a coarser in-plane grid, blurred and with added scanner noise.

Everything here is in the CT's own patient frame V (LPS, mm). The skin is
where the HU falls below ``SKIN_HU`` marching outwards from the body. A real
CT has no built-in plan: the trajectory comes from a plan file or entry and
target points, as a surgeon's planning would give it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from drillnav.registration.carm import CArmView
from drillnav.registration.drr import DrrVolume, render_drr
from drillnav.registration.errors import DegenerateInput
from drillnav.registration.volume import Volume

from .anatomy import Corridor

__all__ = ["VoxelAnatomy", "handed_copy", "render_line_integrals", "render_stride", "SKIN_HU"]

SKIN_HU = -400.0  # body / air boundary
RENDER_STEP_MM = 0.35
RENDER_STRIDE = 2  # a ray through every 2nd pixel where the CT's voxels are that coarse (render_stride)
DRR_CACHE_SIZE = 24  # ~7.6 MB each at 976x976


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.linalg.norm(v)


@dataclass(frozen=True, kw_only=True, eq=False)
class VoxelAnatomy:
    """A CT volume standing in for the patient: the truth the twin's fluoroscopy images."""

    volume: Volume
    corridor: Corridor
    truth_mu: DrrVolume
    _drr_cache: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_volume(cls, volume: Volume, *, corridor: Corridor) -> "VoxelAnatomy":
        """``corridor``: the planned trajectory the drill aims along (a real CT has no built-in plan)."""
        c = corridor
        for label, p in (("entry", c.entry_mm), ("target", c.target_mm)):
            if not volume.contains(np.asarray(p, dtype=np.float64))[0]:
                raise DegenerateInput(f"the corridor's {label} {tuple(round(v, 1) for v in p)} mm lies outside the CT ({volume.description})")
        return cls(volume=volume, corridor=c, truth_mu=DrrVolume.from_ct(volume))

    def line_integrals(self, view: CArmView, carm_from_ct: NDArray[np.float64]) -> NDArray[np.float64]:
        """Attenuation line integrals (rows, columns) through the full-resolution CT, fine ray step (:func:`render_line_integrals`).

        The last few are kept: a study shoots the same patient and view under
        several degradations, and one DRR of the CT takes a second or more.
        """
        key = (view.projection_matrix.tobytes(), view.rows, view.columns, np.asarray(carm_from_ct, dtype=np.float64).tobytes())
        cache = self._drr_cache
        if key not in cache:
            if len(cache) >= DRR_CACHE_SIZE:
                cache.pop(next(iter(cache)))
            cache[key] = render_line_integrals(self.truth_mu, view, carm_from_ct)
        return cache[key].copy()

    def skin_along(self, inside_mm: NDArray[np.float64], outward: NDArray[np.float64], *, max_mm: float = 400.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """March from ``inside_mm`` along ``outward`` to the skin: the skin point (3,) and outward normal (3,)."""
        s = np.arange(0.0, max_mm, 0.5)
        pts = np.asarray(inside_mm, dtype=np.float64) + s[:, None] * _unit(np.asarray(outward, dtype=np.float64))
        hu = self.volume.sample(pts)
        inside = hu > SKIN_HU
        if not inside[0]:
            raise DegenerateInput(f"{np.round(inside_mm, 1).tolist()} mm is not inside the body of the CT")
        out = np.flatnonzero(~inside)
        if out.size == 0:
            raise DegenerateInput(f"no skin within {max_mm:.0f} mm of {np.round(inside_mm, 1).tolist()} mm along {np.round(outward, 2).tolist()}")
        skin = pts[out[0]]
        # Normal: minus the HU gradient, by central differences over 2 mm.
        h = 2.0
        grad = np.array([(self.volume.sample(skin + h * e)[0] - self.volume.sample(skin - h * e)[0]) / (2 * h) for e in np.eye(3)])
        normal = -grad if np.linalg.norm(grad) > 1e-6 else -np.asarray(outward, dtype=np.float64)
        normal = _unit(normal)
        if normal @ outward < 0.2:  # a noisy gradient: fall back to the marching direction
            normal = _unit(np.asarray(outward, dtype=np.float64))
        return skin, normal

    def skin_entry(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Where the trajectory, extended back from its entry, leaves the skin: point and normal."""
        d = _unit(np.asarray(self.corridor.target_mm, dtype=np.float64) - np.asarray(self.corridor.entry_mm, dtype=np.float64))
        return self.skin_along(np.asarray(self.corridor.entry_mm, dtype=np.float64), -d)

    def posterior_extent_mm(self, carm_from_ct: NDArray[np.float64]) -> float:
        """The largest y in C of the body (where the table goes)."""
        body = np.argwhere(np.asarray(self.volume.data[:, ::4, ::4]) > SKIN_HU)
        if body.size == 0:
            raise DegenerateInput("the CT holds no body (nothing above -400 HU)")
        ijk = np.stack([body[:, 2] * 4, body[:, 1] * 4, body[:, 0]], axis=1).astype(np.float64)
        pts = ijk @ self.volume.patient_from_voxel[:3, :3].T + self.volume.patient_from_voxel[:3, 3]
        return float(np.max(pts @ carm_from_ct[1, :3] + carm_from_ct[1, 3]))


def render_stride(truth_mu: DrrVolume, view: CArmView, carm_from_ct: NDArray[np.float64]) -> int:
    """Every how many pixels a ray is cast: ``RENDER_STRIDE`` where that many pixels at the CT's centre span no
    more than its finest voxel, else 1 (a CT finer than the detector's pixels at the patient gets every ray)."""
    centre_ct = truth_mu.patient_from_voxel[:3, :3] @ ((np.asarray(truth_mu.mu.shape[::-1]) - 1) / 2.0) + truth_mu.patient_from_voxel[:3, 3]
    centre_carm = np.asarray(carm_from_ct, dtype=np.float64)[:3, :3] @ centre_ct + np.asarray(carm_from_ct, dtype=np.float64)[:3, 3]
    pixel_at_patient_mm = min(view.pixel_spacing_mm) / float(view.magnification(centre_carm[None, :])[0])
    return RENDER_STRIDE if RENDER_STRIDE * pixel_at_patient_mm <= float(np.min(truth_mu.spacing_mm)) else 1


def render_line_integrals(truth_mu: DrrVolume, view: CArmView, carm_from_ct: NDArray[np.float64]) -> NDArray[np.float64]:
    """Line integrals (rows, columns) of the twin's CT anatomy: rays through every :func:`render_stride`-th pixel,
    bilinear in between.

    With the real chest CT (0.7 mm voxels) a ray every 2nd pixel differs from a ray through every pixel by 0.001
    RMS (p99 0.003) in log units, against 0.04-0.05 of photon noise at the twin's full dose, and takes about a
    quarter of the time (``benchmarks/sim_scene.py``: 1.5 s against 5.7 s a view on 2 cores);
    ``tests/test_scene.py::test_voxel_anatomy_scene`` bounds the difference.
    """
    stride = render_stride(truth_mu, view, carm_from_ct)
    coarse = render_drr(truth_mu, view, carm_from_ct, stride=stride, step_mm=RENDER_STEP_MM)
    if stride == 1:
        return coarse.astype(np.float64)
    # Coarse sample (r, c) lies on pixel (stride r, stride c).
    map_x, map_y = np.meshgrid(np.arange(view.columns, dtype=np.float32) / stride, np.arange(view.rows, dtype=np.float32) / stride)
    return cv2.remap(coarse, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)


def handed_copy(volume: Volume, *, seed: int, voxel_scale: float = 1.25, noise_hu: float = 15.0, blur_mm: float = 0.6) -> Volume:
    """The CT the product is given: blurred, resampled in-plane by ``voxel_scale``, with scanner noise (int16 HU)."""
    if voxel_scale < 1.0:
        raise DegenerateInput(f"the handed CT must not be finer than the truth: voxel scale {voxel_scale} < 1")
    spacing = volume.spacing_mm  # (i, j, k) = (column, row, slice)
    data = np.asarray(volume.data, dtype=np.float32)
    if blur_mm > 0:
        data = ndimage.gaussian_filter(data, sigma=[blur_mm / spacing[2], blur_mm / spacing[1], blur_mm / spacing[0]])
    nk, nj, ni = data.shape
    nj2, ni2 = int(nj / voxel_scale), int(ni / voxel_scale)
    # New voxel centres in old voxel coordinates: c_new * scale + (scale - 1) / 2 keeps the field centred.
    jj = np.arange(nj2) * voxel_scale + (voxel_scale - 1) / 2
    ii = np.arange(ni2) * voxel_scale + (voxel_scale - 1) / 2
    out = np.empty((nk, nj2, ni2), np.float32)
    grid_j, grid_i = np.meshgrid(jj, ii, indexing="ij")
    for k in range(nk):
        out[k] = ndimage.map_coordinates(data[k], [grid_j, grid_i], order=1, mode="nearest")
    rng = np.random.default_rng([seed, 11])
    body = out > -900
    out[body] += rng.normal(scale=noise_hu, size=int(body.sum())).astype(np.float32)
    scale = np.diag([voxel_scale, voxel_scale, 1.0, 1.0])
    shift = np.eye(4)
    shift[:2, 3] = (voxel_scale - 1) / 2
    a = volume.patient_from_voxel @ shift @ scale
    return Volume(data=np.clip(np.rint(out), -1024, 8191).astype(np.int16), patient_from_voxel=a,
                  description=f"{volume.description} (twin copy: {voxel_scale:g}x in-plane voxels, {noise_hu:g} HU noise)")
