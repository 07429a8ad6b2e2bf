"""An analytic pelvis in the CT frame V (LPS, mm): soft-tissue body, bones as cortical shells over cancellous bone.

Analytic shapes let the twin image the anatomy exactly (no voxel sampling) and
give planned corridors that lie inside bone by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from drillnav.registration.transforms import apply

from .xray import MU_PER_MM

__all__ = ["Ellipsoid", "Corridor", "PELVIS", "BODY", "CORRIDORS", "pelvis_ellipsoids_carm", "skin_point"]


@dataclass(frozen=True, kw_only=True)
class Ellipsoid:
    name: str
    centre_mm: tuple[float, float, float]
    semi_axes_mm: tuple[float, float, float]
    euler_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tissue: str = "cortical"
    shell_mm: float = 2.5  # cortical thickness; 0 = solid

    def rotation(self) -> NDArray[np.float64]:
        return Rotation.from_euler("xyz", self.euler_deg, degrees=True).as_matrix()


@dataclass(frozen=True, kw_only=True)
class Corridor:
    """A planned trajectory: entry and target in V (mm) and the acceptance radius about it."""

    name: str
    entry_mm: tuple[float, float, float]
    target_mm: tuple[float, float, float]
    radius_mm: float = 4.0


def _bone_along(name: str, start_mm, end_mm, *, radius_mm: float, overhang_mm: float = 8.0) -> Ellipsoid:
    """A bone ellipsoid whose long axis runs from ``start_mm`` to ``end_mm`` (plus ``overhang_mm`` at each end)."""
    a, b = np.asarray(start_mm, dtype=np.float64), np.asarray(end_mm, dtype=np.float64)
    d = b - a
    length = float(np.linalg.norm(d))
    rot, _ = Rotation.align_vectors([d / length], [[1.0, 0.0, 0.0]])
    return Ellipsoid(name=name, centre_mm=tuple((a + b) / 2), semi_axes_mm=(length / 2 + overhang_mm, radius_mm, radius_mm),
                     euler_deg=tuple(rot.as_euler("xyz", degrees=True)))


def _mirror(p, side: float) -> tuple[float, float, float]:
    return (side * -p[0], p[1], p[2])  # the corridors are planned on the patient's right (x < 0)


# Bone axes of the superior pubic ramus and the posterior column (right side), which the corridors follow.
_RAMUS = ((-84.0, -26.0, -37.0), (-12.0, -58.0, -52.0))
_COLUMN = ((-90.0, 8.0, -5.0), (-72.0, 28.0, -100.0))

BODY = Ellipsoid(name="body", centre_mm=(0.0, 0.0, 0.0), semi_axes_mm=(170.0, 115.0, 220.0), tissue="soft", shell_mm=0.0)

PELVIS: tuple[Ellipsoid, ...] = tuple(
    e
    for side in (-1.0, 1.0)  # -1: the patient's right (x < 0), +1: left
    for e in (
        Ellipsoid(name=f"ilium{side:+.0f}", centre_mm=(side * 95.0, 25.0, 55.0), semi_axes_mm=(22.0, 62.0, 72.0), euler_deg=(0.0, 0.0, side * 28.0)),
        Ellipsoid(name=f"acetabulum{side:+.0f}", centre_mm=(side * 92.0, -5.0, -25.0), semi_axes_mm=(30.0, 30.0, 30.0)),
        _bone_along(f"superior-ramus{side:+.0f}", _mirror(_RAMUS[0], side), _mirror(_RAMUS[1], side), radius_mm=5.0),
        _bone_along(f"posterior-column{side:+.0f}", _mirror(_COLUMN[0], side), _mirror(_COLUMN[1], side), radius_mm=13.0, overhang_mm=0.0),
        Ellipsoid(name=f"ischium{side:+.0f}", centre_mm=(side * 72.0, 25.0, -85.0), semi_axes_mm=(16.0, 26.0, 38.0)),
        Ellipsoid(name=f"femoral-head{side:+.0f}", centre_mm=(side * 100.0, -8.0, -30.0), semi_axes_mm=(22.0, 22.0, 22.0), shell_mm=1.5),
    )
) + (Ellipsoid(name="sacrum", centre_mm=(0.0, 70.0, 40.0), semi_axes_mm=(42.0, 24.0, 70.0), euler_deg=(-20.0, 0.0, 0.0)),)

CORRIDORS: tuple[Corridor, ...] = (
    # Target 84 mm along the original plan direction: inside the ilium, short of the posterior cortex.
    Corridor(name="AIIS-PSIS", entry_mm=(-95.0, -15.0, 15.0), target_mm=(-92.26006, 62.631629, 46.965965)),
    Corridor(name="superior-ramus", entry_mm=(-80.0, -28.0, -38.0), target_mm=(-22.0, -53.8, -50.0), radius_mm=3.5),
    Corridor(name="posterior-column", entry_mm=(-88.0, 10.0, -10.0), target_mm=(-74.0, 25.5, -88.0), radius_mm=3.5),
)


def pelvis_ellipsoids_carm(carm_from_ct: NDArray[np.float64]) -> list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float]]:
    """Body and bones as ``(centre, semi_axes, carm_from_local rotation, mu)`` for ``add_ellipsoids``.

    A cortical shell is an outer ellipsoid of cortical bone minus an inner one
    whose attenuation difference leaves cancellous bone inside.
    """
    out = []
    for e in (BODY, *PELVIS):
        c = apply(carm_from_ct, np.asarray(e.centre_mm))
        r = carm_from_ct[:3, :3] @ e.rotation()
        axes = np.asarray(e.semi_axes_mm)
        mu_outer = MU_PER_MM[e.tissue] - (MU_PER_MM["soft"] if e.tissue != "soft" else 0.0)
        out.append((c, axes, r, mu_outer))
        if e.shell_mm > 0:
            out.append((c, axes - e.shell_mm, r, MU_PER_MM["cancellous"] - MU_PER_MM[e.tissue]))
    return out


def skin_point(x_mm: float, z_mm: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Point (3,) on the anterior skin at (x, z) in V, and the outward unit normal (3,)."""
    a, b, c = BODY.semi_axes_mm
    q = 1.0 - (x_mm / a) ** 2 - (z_mm / c) ** 2
    if q <= 0:
        raise ValueError(f"({x_mm}, {z_mm}) mm lies outside the body outline")
    p = np.array([x_mm, -b * np.sqrt(q), z_mm])
    n = p / np.array([a, b, c]) ** 2
    return p, n / np.linalg.norm(n)


def skin_entry(corridor: Corridor) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where the trajectory, extended back from its entry, leaves the anterior skin: point and normal (V)."""
    e = np.asarray(corridor.entry_mm, dtype=np.float64)
    d = corridor_direction(corridor)
    a, b, c = BODY.semi_axes_mm
    # Solve |(e - s d) / axes| = 1 for the s > 0 that exits the body.
    u, v = e / np.array([a, b, c]), d / np.array([a, b, c])
    qa, qb, qc = v @ v, -2 * (u @ v), u @ u - 1.0
    s = (-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
    p = e - s * d
    n = p / np.array([a, b, c]) ** 2
    return p, n / np.linalg.norm(n)


def corridor_direction(corridor: Corridor) -> NDArray[np.float64]:
    d = np.asarray(corridor.target_mm) - np.asarray(corridor.entry_mm)
    return d / np.linalg.norm(d)


