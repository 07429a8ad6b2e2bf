"""Conformance of a drill axis within a bone corridor: distance to the cortex along it, and breach flags.

As in the reference: the acceptance volume is the bone interior (or a
corridor label); along the axis, between where it enters and leaves that
volume about the planned entry and target, equally spaced points get their
distance to the volume's surface. The distance is the clearance across the
axis: the nearest surface point in the plane through the sample at right
angles to the axis (the nearest point in 3D would be the cortex the wire
crosses at entry and exit, which it must cross). A clearance below the
K-wire radius (1.5 mm) is a breach; points outside the volume count as
negative clearance.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from .errors import DegenerateInput
from .line import Line3D
from .transforms import apply
from .volume import Volume

__all__ = ["SurfaceDistance", "Conformance", "conformance_along", "radial_clearance", "perturbed_axes", "K_WIRE_RADIUS_MM", "BONE_THRESHOLD_HU"]

K_WIRE_RADIUS_MM = 1.5
BONE_THRESHOLD_HU = 200.0
OUTSIDE_MM = -1e3  # the signed distance reported beyond the grid


@dataclass(frozen=True, kw_only=True, eq=False)
class SurfaceDistance:
    """Signed distance (mm) to the acceptance volume's surface: positive inside, negative outside; on a voxel grid."""

    distance_mm: NDArray[np.float32]  # (slices, rows, columns)
    patient_from_voxel: NDArray[np.float64]

    @classmethod
    def from_mask(cls, inside: NDArray[np.bool_], patient_from_voxel: NDArray[np.float64], *,
                  around_mm: ArrayLike | None = None, margin_mm: float = 40.0) -> "SurfaceDistance":
        """Signed distance to the surface of ``inside`` (slices, rows, columns); optionally cropped to the box
        about points ``around_mm`` (N, 3) plus ``margin_mm`` (much faster than the whole volume)."""
        inside, a = _crop(np.asarray(inside), patient_from_voxel, around_mm, margin_mm)
        if not inside.any():
            raise DegenerateInput("the acceptance volume is empty" + (" about the trajectories" if around_mm is not None else ""))
        spacing = np.linalg.norm(np.asarray(a)[:3, :3], axis=0)[::-1]  # (k, j, i) order
        d_in = ndimage.distance_transform_edt(inside, sampling=spacing)
        d_out = ndimage.distance_transform_edt(~inside, sampling=spacing)
        # Voxel centres lie half a voxel from the surface between them.
        half = 0.5 * float(np.min(spacing))
        signed = np.where(inside, d_in - half, -(d_out - half)).astype(np.float32)
        return cls(distance_mm=signed, patient_from_voxel=np.asarray(a, dtype=np.float64))

    @classmethod
    def bone(cls, ct: Volume, *, threshold_hu: float = BONE_THRESHOLD_HU, around_mm: ArrayLike | None = None, margin_mm: float = 40.0) -> "SurfaceDistance":
        """Bone = HU above ``threshold_hu`` with enclosed cavities filled; optionally cropped as in :meth:`from_mask`."""
        data, a = _crop(np.asarray(ct.data), ct.patient_from_voxel, around_mm, margin_mm)
        inside = ndimage.binary_fill_holes(data >= threshold_hu)
        return cls.from_mask(inside, a)

    @cached_property
    def voxel_from_patient(self) -> NDArray[np.float64]:
        return np.linalg.inv(self.patient_from_voxel)

    def at(self, points_mm: ArrayLike) -> NDArray[np.float64]:
        """Signed distance at patient points (N, 3), trilinear; far outside (``OUTSIDE_MM``) beyond the grid."""
        from .distance_kernels import sample_trilinear  # numba loads on first use, not on import

        return sample_trilinear(self.distance_mm, self.voxel_from_patient, np.asarray(points_mm, dtype=np.float64), outside=OUTSIDE_MM)


def _crop(data: NDArray, patient_from_voxel: NDArray[np.float64], around_mm: ArrayLike | None, margin_mm: float) -> tuple[NDArray, NDArray[np.float64]]:
    """``data`` (slices, rows, columns) cut to the box about ``around_mm`` + margin, with its shifted affine."""
    a = np.asarray(patient_from_voxel, dtype=np.float64)
    if around_mm is None:
        return data, a
    ijk = apply(np.linalg.inv(a), np.atleast_2d(around_mm))
    pad = margin_mm / np.linalg.norm(a[:3, :3], axis=0)
    lo = np.maximum(np.floor(ijk.min(axis=0) - pad).astype(int), 0)
    hi = np.minimum(np.ceil(ijk.max(axis=0) + pad).astype(int) + 1, np.asarray(data.shape[::-1]))
    if np.any(hi - lo < 2):
        raise DegenerateInput("the trajectories lie outside the volume")
    shift = np.eye(4)
    shift[:3, 3] = lo
    return data[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]], a @ shift


@dataclass(frozen=True, kw_only=True)
class Conformance:
    """Distances along the axis from its entry into the acceptance volume; ``breach`` if any is under the K-wire radius."""

    along_mm: NDArray[np.float64]      # (N,) from the entry point, along the axis
    distance_mm: NDArray[np.float64]   # (N,) signed distance to the surface
    entry_mm: NDArray[np.float64] | None   # (3,) where the axis enters the volume (None: it never does)
    exit_mm: NDArray[np.float64] | None
    kwire_radius_mm: float
    entry_zone_mm: float = 0.0

    @property
    def judged(self) -> NDArray[np.bool_]:
        return self.along_mm >= self.entry_zone_mm

    @property
    def breach(self) -> bool:
        return self.entry_mm is None or bool(np.any(self.distance_mm[self.judged] < self.kwire_radius_mm))

    @property
    def min_distance_mm(self) -> float:
        """Smallest judged clearance (-inf when the axis never enters the volume)."""
        d = self.distance_mm[self.judged]
        return float(np.min(d)) if d.size else float("-inf")

    @property
    def breach_along_mm(self) -> NDArray[np.float64]:
        """Judged positions (mm from entry) where the clearance is under the K-wire radius."""
        return self.along_mm[self.judged & (self.distance_mm < self.kwire_radius_mm)]


def conformance_along(
    axis_ct: Line3D,
    surface: SurfaceDistance,
    *,
    planned_entry_mm: ArrayLike,
    planned_target_mm: ArrayLike,
    kwire_radius_mm: float = K_WIRE_RADIUS_MM,
    step_mm: float = 0.5,
    before_mm: float = 20.0,
    entry_zone_mm: float = 3.0,
) -> Conformance:
    """Sample ``axis_ct`` (CT frame, direction into the patient) over the planned stretch.

    The stretch runs from ``before_mm`` ahead of the planned entry to the
    planned target, both projected onto the axis; within it the axis enters
    the volume where the distance first turns positive and leaves where it
    last is; that part is reported. The first ``entry_zone_mm`` after the
    entry, where the wire passes through the entry cortex (at a glancing
    angle the clearance there is small by geometry, not by misplacement),
    is reported but not judged.
    """
    e = axis_ct.closest_point(np.asarray(planned_entry_mm, dtype=np.float64))
    t = axis_ct.closest_point(np.asarray(planned_target_mm, dtype=np.float64))
    s0 = float((e - axis_ct.point_mm) @ axis_ct.direction) - before_mm
    s1 = float((t - axis_ct.point_mm) @ axis_ct.direction)
    if s1 <= s0:
        raise DegenerateInput("the planned target lies before the entry along this axis")
    s = np.arange(s0, s1 + 1e-9, step_mm)
    points = axis_ct.at(s)
    d = surface.at(points)
    inside = np.flatnonzero(d > 0)
    if inside.size == 0:
        return Conformance(along_mm=np.zeros(0), distance_mm=np.zeros(0), entry_mm=None, exit_mm=None, kwire_radius_mm=kwire_radius_mm)
    first, last = int(inside[0]), int(inside[-1])
    seg = slice(first, last + 1)
    clearance = radial_clearance(axis_ct, s[seg], surface, on_axis_mm=d[seg])
    return Conformance(along_mm=s[seg] - s[first], distance_mm=clearance, entry_mm=points[first], exit_mm=points[last],
                       kwire_radius_mm=kwire_radius_mm, entry_zone_mm=entry_zone_mm)


def radial_clearance(axis: Line3D, s_mm: NDArray[np.float64], surface: SurfaceDistance, *, on_axis_mm: NDArray[np.float64],
                     n_directions: int = 24, reach_mm: float = 20.0, step_mm: float = 0.25) -> NDArray[np.float64]:
    """(N,) distance from axis points at ``s_mm`` to the surface within the plane across the axis.

    Rays leave each point in ``n_directions`` directions of that plane; the
    first crossing to outside (linearly interpolated) is the clearance along
    that ray, the smallest over rays the clearance; ``reach_mm`` caps it.
    Points outside the volume keep their (negative) 3-D signed distance.
    """
    d = axis.direction
    u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(d, u)
    ang = np.linspace(0, 2 * np.pi, n_directions, endpoint=False)
    dirs = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w  # (R, 3)
    from .distance_kernels import first_crossings  # numba loads on first use, not on import

    clearance = first_crossings(surface.distance_mm, surface.voxel_from_patient, axis.at(s_mm), dirs, reach_mm=reach_mm, step_mm=step_mm, outside=OUTSIDE_MM)
    return np.where(on_axis_mm > 0, clearance, on_axis_mm)


def perturbed_axes(rng: np.random.Generator, entry_mm: ArrayLike, target_mm: ArrayLike, *, position_mm: float, angle_deg: float, n: int) -> list[Line3D]:
    """The reference's cone: ``n`` trajectories about entry->target, entry moved uniformly within ``position_mm``
    (in the plane across the trajectory) and the direction tilted uniformly within ``angle_deg``."""
    e = np.asarray(entry_mm, dtype=np.float64)
    d0 = np.asarray(target_mm, dtype=np.float64) - e
    d0 /= np.linalg.norm(d0)
    u = np.cross(d0, [1.0, 0.0, 0.0] if abs(d0[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(d0, u)
    out = []
    for _ in range(n):
        r, phi = position_mm * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        tilt, psi = np.radians(angle_deg) * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        d = np.cos(tilt) * d0 + np.sin(tilt) * (np.cos(psi) * u + np.sin(psi) * w)
        out.append(Line3D(point_mm=e + r * (np.cos(phi) * u + np.sin(phi) * w), direction=d))
    return out
