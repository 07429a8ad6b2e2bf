"""Horn's closed-form absolute orientation with unit quaternions, weighted.

B. K. P. Horn, "Closed-form solution of absolute orientation using unit
quaternions", J. Opt. Soc. Am. A 4(4), 1987.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .errors import DegenerateInput
from .transforms import apply, check_points, make_transform

__all__ = ["RigidFit", "absolute_orientation", "absolute_orientation_batch"]


@dataclass(frozen=True, kw_only=True)
class RigidFit:
    """Result of a point-based rigid registration.

    target_from_source : (4, 4) transform.
    residuals_mm : (N,) distance of each transformed source point from its target (the per-point FRE).
    fre_mm : weighted RMS of the residuals.
    """

    target_from_source: NDArray[np.float64]
    residuals_mm: NDArray[np.float64]
    fre_mm: float


def absolute_orientation(
    source_points: ArrayLike, target_points: ArrayLike, weights: ArrayLike | None = None
) -> RigidFit:
    """Rigid transform minimising ``sum w_i |R s_i + t - d_i|^2``.

    Parameters
    ----------
    source_points, target_points : array, shape (N, 3)
        Corresponding points, N >= 3 and not collinear.
    weights : array, shape (N,), optional
        Non-negative weights (e.g. inverse variances); default all ones.
    """
    s = check_points(source_points)
    d = check_points(target_points)
    if s.shape != d.shape:
        raise DegenerateInput(f"point sets differ in shape: {s.shape} vs {d.shape}")
    n = s.shape[0]
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (n,) or np.any(w < 0) or w.sum() <= 0:
        raise DegenerateInput("weights must be N non-negative numbers with a positive sum")
    if np.count_nonzero(w) < 3:
        raise DegenerateInput(f"absolute orientation needs at least 3 weighted points, got {np.count_nonzero(w)}")
    wn = w / w.sum()
    cs, cd = wn @ s, wn @ d
    s0, d0 = s - cs, d - cd
    if np.linalg.matrix_rank(s0[w > 0], tol=1e-6 * max(1.0, np.abs(s0).max())) < 2:
        raise DegenerateInput("source points are collinear: the rotation about their line is undetermined")
    m = (s0 * wn[:, None]).T @ d0  # M[a, b] = sum w s_a d_b
    rot = _rotations(m[None])[0]
    t = make_transform(rot, cd - rot @ cs)
    res = np.linalg.norm(apply(t, s) - d, axis=1)
    return RigidFit(target_from_source=t, residuals_mm=res, fre_mm=float(np.sqrt(wn @ res**2)))


def absolute_orientation_batch(source_points: ArrayLike, target_points: ArrayLike) -> NDArray[np.float64]:
    """Unweighted Horn for B independent point sets at once (e.g. Monte-Carlo draws).

    Parameters
    ----------
    source_points, target_points : array, shape (B, N, 3)
        B sets of N >= 3 corresponding, non-collinear points.

    Returns
    -------
    target_from_source : (B, 4, 4)
        Each set's rigid transform, the same as :func:`absolute_orientation` gives it.
    """
    s = np.asarray(source_points, dtype=np.float64)
    d = np.asarray(target_points, dtype=np.float64)
    if s.ndim != 3 or s.shape[2] != 3 or s.shape != d.shape or s.shape[1] < 3:
        raise DegenerateInput(f"expected two (B, N>=3, 3) point arrays of one shape, got {s.shape} and {d.shape}")
    cs, cd = s.mean(axis=1), d.mean(axis=1)
    rot = _rotations(np.einsum("bna,bnc->bac", s - cs[:, None], d - cd[:, None]) / s.shape[1])
    out = np.zeros((s.shape[0], 4, 4))
    out[:, :3, :3] = rot
    out[:, :3, 3] = cd - np.einsum("bij,bj->bi", rot, cs)
    out[:, 3, 3] = 1.0
    return out


def _rotations(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """(B, 3, 3) rotations maximising ``trace(R M)`` for cross-covariances ``M[a, b] = sum w s_a d_b`` (B, 3, 3):
    the unit quaternion of the largest eigenvalue of Horn's symmetric 4x4 matrix."""
    (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = m[:, 0].T, m[:, 1].T, m[:, 2].T
    n_mat = np.stack([
        np.stack([sxx + syy + szz, syz - szy, szx - sxz, sxy - syx], axis=-1),
        np.stack([syz - szy, sxx - syy - szz, sxy + syx, szx + sxz], axis=-1),
        np.stack([szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy], axis=-1),
        np.stack([sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz], axis=-1),
    ], axis=-2)
    _, vecs = np.linalg.eigh(n_mat)
    w, x, y, z = vecs[:, :, -1].T  # eigh sorts ascending: the last vector has the largest eigenvalue
    return Rotation.from_quat(np.stack([x, y, z, w], axis=-1)).as_matrix()  # scipy wants the scalar last
