"""Rigid transforms as 4x4 homogeneous matrices.

Naming: ``target_from_source`` maps points expressed in ``source`` to ``target``:
``x_target = apply(target_from_source, x_source)``, and transforms chain as
``a_from_c = a_from_b @ b_from_c``. Translations are in mm.

Quaternions in this package are scalar-first unit quaternions ``(w, x, y, z)``
(Horn's convention); conversion to other orders happens in ``schemas`` only.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    "check_transform",
    "check_points",
    "make_transform",
    "invert",
    "apply",
    "apply_vectors",
    "from_rotvec",
    "to_rotvec",
    "from_quaternion",
    "to_quaternion",
    "rotation_angle_deg",
    "translation_mm",
    "euler_transform",
]


def check_transform(transform: ArrayLike, *, tolerance: float = 1e-6) -> NDArray[np.float64]:
    """Return ``transform`` as a float 4x4 rigid transform or raise ``ValueError``.

    Parameters
    ----------
    transform : array-like, shape (4, 4)
        Homogeneous rigid transform; the upper-left 3x3 must be a rotation.
    tolerance : float
        Allowed deviation of ``R^T R`` from identity and of ``det R`` from 1.
    """
    t = np.asarray(transform, dtype=np.float64)
    if t.shape != (4, 4):
        raise ValueError(f"expected a 4x4 transform, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("transform has non-finite entries")
    if not np.allclose(t[3], [0.0, 0.0, 0.0, 1.0], atol=tolerance):
        raise ValueError(f"last row of a rigid transform must be [0, 0, 0, 1], got {t[3].tolist()}")
    r = t[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=tolerance) or abs(np.linalg.det(r) - 1.0) > tolerance:
        raise ValueError("upper-left 3x3 of the transform is not a proper rotation")
    return t


def check_points(points: ArrayLike, *, dim: int = 3) -> NDArray[np.float64]:
    """Return ``points`` as float array of shape (N, dim) or raise ``ValueError``."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 1 and p.shape[0] == dim:
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != dim:
        raise ValueError(f"expected points of shape (N, {dim}), got {p.shape}")
    return p


def make_transform(rotation: ArrayLike, translation_mm: ArrayLike) -> NDArray[np.float64]:
    """Build a 4x4 transform from a 3x3 rotation and a translation (3,) in mm."""
    t = np.eye(4)
    t[:3, :3] = np.asarray(rotation, dtype=np.float64)
    t[:3, 3] = np.asarray(translation_mm, dtype=np.float64)
    return t


def invert(target_from_source: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a rigid transform, ``source_from_target``, without a general matrix inverse."""
    t = np.asarray(target_from_source, dtype=np.float64)
    r = t[:3, :3]
    out = np.eye(4)
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ t[:3, 3]
    return out


def apply(target_from_source: ArrayLike, points_source: ArrayLike) -> NDArray[np.float64]:
    """Map points (N, 3) or (3,) from the source frame to the target frame (same shape out)."""
    t = np.asarray(target_from_source, dtype=np.float64)
    p = np.asarray(points_source, dtype=np.float64)
    return p @ t[:3, :3].T + t[:3, 3]


def apply_vectors(target_from_source: ArrayLike, vectors_source: ArrayLike) -> NDArray[np.float64]:
    """Rotate direction vectors (N, 3) or (3,) into the target frame (no translation)."""
    t = np.asarray(target_from_source, dtype=np.float64)
    return np.asarray(vectors_source, dtype=np.float64) @ t[:3, :3].T


def from_rotvec(rotvec_rad: ArrayLike, translation_mm: ArrayLike = (0.0, 0.0, 0.0)) -> NDArray[np.float64]:
    """Transform from a rotation vector (3,) in rad (axis times angle) and a translation (3,) in mm."""
    return make_transform(Rotation.from_rotvec(np.asarray(rotvec_rad, float)).as_matrix(), translation_mm)


def to_rotvec(target_from_source: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Split a transform into (rotation vector (3,) rad, translation (3,) mm)."""
    t = np.asarray(target_from_source, dtype=np.float64)
    return Rotation.from_matrix(t[:3, :3]).as_rotvec(), t[:3, 3].copy()


def from_quaternion(quaternion_wxyz: ArrayLike, translation_mm: ArrayLike = (0.0, 0.0, 0.0)) -> NDArray[np.float64]:
    """Transform from a scalar-first quaternion (w, x, y, z) and a translation (3,) in mm."""
    q = np.asarray(quaternion_wxyz, dtype=np.float64)
    n = np.linalg.norm(q)
    if q.shape != (4,) or n < 1e-12:
        raise ValueError(f"expected a non-zero quaternion (w, x, y, z), got {q.tolist()}")
    w, x, y, z = q / n
    return make_transform(Rotation.from_quat([x, y, z, w]).as_matrix(), translation_mm)


def to_quaternion(target_from_source: ArrayLike) -> NDArray[np.float64]:
    """Scalar-first unit quaternion (w, x, y, z) of a transform's rotation, with w >= 0."""
    x, y, z, w = Rotation.from_matrix(np.asarray(target_from_source, float)[:3, :3]).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def rotation_angle_deg(transform: ArrayLike) -> float:
    """Rotation angle in degrees of a transform's rotation part (0 for identity)."""
    r = np.asarray(transform, dtype=np.float64)[:3, :3]
    c = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def translation_mm(transform: ArrayLike) -> NDArray[np.float64]:
    """Translation part (3,) in mm."""
    return np.asarray(transform, dtype=np.float64)[:3, 3].copy()


def euler_transform(angles_deg: ArrayLike, translation_mm: ArrayLike = (0.0, 0.0, 0.0), *, order: str = "xyz") -> NDArray[np.float64]:
    """Transform from extrinsic Euler angles in degrees (scipy ``order``) and a translation in mm."""
    return make_transform(Rotation.from_euler(order, np.asarray(angles_deg, float), degrees=True).as_matrix(), translation_mm)
