"""Digitally reconstructed radiographs of a CT through the C-arm projection model.

Each detector pixel's ray from the source is clipped to the volume's box and
sampled at equal steps (one voxel by default) by trilinear interpolation of
the attenuation volume; the sum times the step is the line integral, the
same quantity the fluoroscopy intake yields (log attenuation).

The kernel is compiled by numba (``parallel=True``, one detector row per
task): a per-pixel loop in LLVM-compiled code reaches the speed targets on
two CPU cores, which numpy's whole-array gathers cannot (they materialise
every sample point), and it needs no compiler or GPU on the user's machine.
It releases the GIL (``nogil``), so the daemon's camera loop runs on while a
CT registration renders. The kernel lives in :mod:`.drr_kernel`, imported on
the first render, so importing this module does not load numba.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .carm import CArmView
from .transforms import invert
from .volume import MU_WATER_PER_MM, Volume, hu_to_mu

__all__ = ["DrrVolume", "render_drr", "drr_pyramid"]


@dataclass(frozen=True, kw_only=True, eq=False)
class DrrVolume:
    """An attenuation volume (1/mm, float32, C order) ready for the kernel, with its voxel grid."""

    mu: NDArray[np.float32]
    patient_from_voxel: NDArray[np.float64]

    @classmethod
    def from_ct(cls, volume: Volume, *, downsample: int = 1, threshold_hu: float | None = None) -> "DrrVolume":
        """Attenuation from HU; with ``threshold_hu``, only the attenuation in excess of it (e.g. 150: bone alone).

        ``downsample`` is the pyramid factor: every axis goes to about that many
        times the finest voxel size (:meth:`Volume.isotropic_factors`).
        """
        v = volume.downsampled(volume.isotropic_factors(downsample))
        hu = np.asarray(v.data, np.float32)
        if threshold_hu is not None:
            mu = np.maximum(hu - np.float32(threshold_hu), 0.0) * np.float32(MU_WATER_PER_MM / 1000.0)
        else:
            mu = hu_to_mu(hu)
        mu, patient_from_voxel = _crop_to_attenuation(np.ascontiguousarray(mu, dtype=np.float32), v.patient_from_voxel)
        return cls(mu=mu, patient_from_voxel=patient_from_voxel)

    @property
    def spacing_mm(self) -> NDArray[np.float64]:
        return np.linalg.norm(self.patient_from_voxel[:3, :3], axis=0)


def _crop_to_attenuation(mu: NDArray[np.float32], patient_from_voxel: NDArray[np.float64]) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """``mu`` (k, j, i) cut to the box of its non-zero voxels plus one zero voxel each side, with the shifted grid.

    Exact: trilinear samples inside the box are unchanged and those outside it
    were zero. Rays are clipped to the box, so air around the body (40 % of the
    twin's volume) costs nothing.
    """
    nz = [np.flatnonzero(np.any(mu > 0, axis=tuple(a for a in range(3) if a != ax))) for ax in range(3)]
    if any(n.size == 0 for n in nz):
        return mu, patient_from_voxel
    lo = [max(int(n[0]) - 1, 0) for n in nz]
    hi = [min(int(n[-1]) + 2, size) for n, size in zip(nz, mu.shape)]
    if any(h - l < 2 for l, h in zip(lo, hi)):
        return mu, patient_from_voxel
    shift = np.eye(4)
    shift[:3, 3] = lo[::-1]  # (i, j, k)
    cropped = np.ascontiguousarray(mu[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]])
    return cropped, np.asarray(patient_from_voxel, dtype=np.float64) @ shift


def render_drr(
    volume: DrrVolume,
    view: CArmView,
    carm_from_ct: NDArray[np.float64],
    *,
    roi: tuple[int, int, int, int] | None = None,
    stride: int = 1,
    step_mm: float | None = None,
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """Line integrals of attenuation (rows, columns) over ``view``'s pixels (or ``roi`` = col0, row0, col1, row1).

    ``stride`` samples every n-th pixel of the view (pixel centres kept on the
    view's grid); ``step_mm`` defaults to the smallest voxel size.
    """
    col0, row0, col1, row1 = roi if roi is not None else (0, 0, view.columns, view.rows)
    shape = ((row1 - row0 + stride - 1) // stride, (col1 - col0 + stride - 1) // stride)
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape:
        raise ValueError(f"out has shape {out.shape}, the DRR needs {shape}")
    voxel_from_carm = np.linalg.inv(volume.patient_from_voxel) @ invert(carm_from_ct)
    m = view.projection_matrix[:, :3]
    carm_from_pix = np.linalg.inv(m)  # direction (unnormalised) through pixel (u, v, 1)
    source = view.source_position_mm
    origin_vox = voxel_from_carm[:3, :3] @ source + voxel_from_carm[:3, 3]
    vox_from_pix = voxel_from_carm[:3, :3] @ carm_from_pix
    step = float(step_mm if step_mm is not None else np.min(volume.spacing_mm))
    from .drr_kernel import drr_kernel  # numba loads on the first DRR, not on import

    drr_kernel(volume.mu, origin_vox, vox_from_pix, carm_from_pix, step, float(row0), float(col0), float(stride), out)
    return out


def drr_pyramid(volume: Volume, factors: tuple[int, ...] = (1, 2, 4), *, threshold_hu: float | None = None) -> dict[int, DrrVolume]:
    """Attenuation volumes at each downsampling factor, for coarse-to-fine registration."""
    return {f: DrrVolume.from_ct(volume, downsample=f, threshold_hu=threshold_hu) for f in factors}
