"""Coarse translation of the CT before CMA-ES: where does the fluoroscopy's anatomy sit in a wide DRR?

The initial pose (positioner angles, the CT point assumed at the isocentre)
can be off by many centimetres along the table. At the coarsest level the
DRR is rendered over a detector widened by ``search_mm`` on every side;
the fluoroscopy's gradient-magnitude image is matched in it (normalised
correlation, markers and tools masked), and each view's pixel shift is one
2-D constraint on the 3-D translation at the isocentre; all views are
solved jointly by least squares (one view leaves depth unchanged).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .carm import CArmView
from .drr import DrrVolume, render_drr
from .transforms import make_transform

__all__ = ["Prealignment", "prealign_translation"]


@dataclass(frozen=True, kw_only=True)
class Prealignment:
    carm_from_ct: NDArray[np.float64]
    translation_mm: NDArray[np.float64]   # (3,) applied in the C-arm frame
    scores: tuple[float, ...]              # per view, normalised correlation at the best shift


def _grad_mag(img: NDArray[np.float32]) -> NDArray[np.float32]:
    s = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.8)
    return cv2.magnitude(cv2.Sobel(s, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(s, cv2.CV_32F, 0, 1, ksize=3))


def _widened(view: CArmView, pad: int) -> CArmView:
    shift = np.array([[1.0, 0.0, pad], [0.0, 1.0, pad], [0.0, 0.0, 1.0]])
    return CArmView(projection_matrix=shift @ view.projection_matrix, rows=view.rows + 2 * pad, columns=view.columns + 2 * pad, pixel_spacing_mm=view.pixel_spacing_mm)


def prealign_translation(
    volume: DrrVolume,
    views: list[CArmView],
    images_binned: list[NDArray[np.float32]],
    valid: list[NDArray[np.bool_]],
    carm_from_ct: NDArray[np.float64],
    *,
    search_mm: float = 100.0,
) -> Prealignment:
    """Translate ``carm_from_ct`` so each binned view's anatomy lines up; ``views`` match ``images_binned`` (rows, cols)."""
    rows_a, rhs, scores = [], [], []
    for view, img, ok in zip(views, images_binned, valid):
        k, source_from_carm = view.decompose()
        sid = float(np.linalg.norm(source_from_carm[:3, 3]))  # source to isocentre
        mm_per_px_iso = view.pixel_spacing_mm[1] * sid / view.source_to_detector_mm
        pad = int(np.ceil(search_mm / mm_per_px_iso))
        wide = _widened(view, pad)
        drr = render_drr(volume, wide, carm_from_ct)
        template = _grad_mag(img)
        mask = ok.astype(np.float32)
        template = template * mask
        result = cv2.matchTemplate(_grad_mag(drr), template, cv2.TM_CCORR_NORMED, mask=mask)
        result = np.nan_to_num(result, nan=-1.0, posinf=-1.0, neginf=-1.0)
        _, best, _, (bx, by) = cv2.minMaxLoc(result)
        scores.append(float(best))
        # Anatomy found at offset (bx - pad, by - pad) in the DRR must move by the opposite in the image.
        du, dv = -(bx - pad), -(by - pad)
        r = source_from_carm[:3, :3]
        rows_a.append(r[0] / mm_per_px_iso)
        rows_a.append(r[1] / mm_per_px_iso)
        rhs.extend([du * k[0, 0] / abs(k[0, 0]), dv * k[1, 1] / abs(k[1, 1])])
    a, b = np.asarray(rows_a), np.asarray(rhs, dtype=np.float64)
    t, *_ = np.linalg.lstsq(a, b, rcond=None)
    return Prealignment(carm_from_ct=make_transform(np.eye(3), t) @ carm_from_ct, translation_mm=t, scores=tuple(scores))
