"""Lines in 3D (the drill axis) and their images.

An axis is a point (mm) and a unit direction; for the drill axis the direction
points from the drill into the patient.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .transforms import apply, apply_vectors

__all__ = ["Line3D", "line_through_points_2d"]


@dataclass(frozen=True, kw_only=True)
class Line3D:
    """A 3D line ``point_mm + s * direction`` (s in mm).

    point_mm : (3,) a point on the line, mm.
    direction : (3,) unit direction (normalised on construction).
    """

    point_mm: NDArray[np.float64]
    direction: NDArray[np.float64]

    def __post_init__(self) -> None:
        p = np.asarray(self.point_mm, dtype=np.float64).reshape(3)
        d = np.asarray(self.direction, dtype=np.float64).reshape(3)
        n = np.linalg.norm(d)
        if not np.all(np.isfinite(p)) or not np.isfinite(n) or n < 1e-12:
            raise ValueError(f"a line needs a finite point and a non-zero direction, got {p.tolist()}, {d.tolist()}")
        object.__setattr__(self, "point_mm", p)
        object.__setattr__(self, "direction", d / n)

    @classmethod
    def through(cls, start_mm: ArrayLike, end_mm: ArrayLike) -> "Line3D":
        """Line from ``start_mm`` towards ``end_mm``."""
        a, b = np.asarray(start_mm, float), np.asarray(end_mm, float)
        return cls(point_mm=a, direction=b - a)

    def transformed(self, target_from_source: ArrayLike) -> "Line3D":
        """The same line expressed in the target frame."""
        return Line3D(point_mm=apply(target_from_source, self.point_mm), direction=apply_vectors(target_from_source, self.direction))

    def at(self, s_mm: ArrayLike) -> NDArray[np.float64]:
        """Points (N, 3) at signed distances ``s_mm`` (N,) along the line."""
        s = np.atleast_1d(np.asarray(s_mm, dtype=np.float64))
        return self.point_mm + s[:, None] * self.direction

    def closest_point(self, x_mm: ArrayLike) -> NDArray[np.float64]:
        """Point (3,) on the line nearest ``x_mm`` (3,)."""
        x = np.asarray(x_mm, dtype=np.float64)
        return self.point_mm + np.dot(x - self.point_mm, self.direction) * self.direction

    def distance_to_point(self, x_mm: ArrayLike) -> NDArray[np.float64] | float:
        """Perpendicular distance (mm) from point(s) (3,) or (N, 3) to the line."""
        x = np.asarray(x_mm, dtype=np.float64)
        v = x - self.point_mm
        perp = v - (v @ self.direction)[..., None] * self.direction
        d = np.linalg.norm(perp, axis=-1)
        return float(d) if d.ndim == 0 else d

    def angle_deg(self, other: "Line3D", *, oriented: bool = True) -> float:
        """Angle between the directions in degrees; unoriented lines give at most 90."""
        c = float(np.clip(np.dot(self.direction, other.direction), -1.0, 1.0))
        if not oriented:
            c = abs(c)
        return float(np.degrees(np.arccos(c)))

    def distance_to_line(self, other: "Line3D") -> float:
        """Shortest distance (mm) between the two lines (infinite extent)."""
        n = np.cross(self.direction, other.direction)
        nn = np.linalg.norm(n)
        w = other.point_mm - self.point_mm
        if nn < 1e-12:
            return float(self.distance_to_point(other.point_mm))
        return float(abs(np.dot(w, n)) / nn)

    def intersect_plane(self, plane_point_mm: ArrayLike, plane_normal: ArrayLike) -> NDArray[np.float64]:
        """Intersection (3,) with a plane; raises ``ValueError`` if parallel."""
        n = np.asarray(plane_normal, dtype=np.float64)
        denom = float(np.dot(n, self.direction))
        if abs(denom) < 1e-12:
            raise ValueError("line is parallel to the plane")
        s = np.dot(n, np.asarray(plane_point_mm, float) - self.point_mm) / denom
        return self.point_mm + s * self.direction

    def first_crossing(
        self,
        signed_distance: Callable[[NDArray[np.float64]], NDArray[np.float64]],
        *,
        start_mm: float = 0.0,
        stop_mm: float = 300.0,
        step_mm: float = 0.5,
    ) -> NDArray[np.float64] | None:
        """First point (3,) along the line where ``signed_distance`` (N, 3) -> (N,) changes sign.

        Samples from ``start_mm`` to ``stop_mm`` and refines by bisection; ``None`` if no crossing.
        A surface given as a mesh or a labelled volume passes its own signed-distance function.
        """
        s = np.arange(start_mm, stop_mm + step_mm, step_mm)
        f = np.asarray(signed_distance(self.at(s)), dtype=np.float64)
        change = np.nonzero(np.signbit(f[:-1]) != np.signbit(f[1:]))[0]
        if change.size == 0:
            return None
        lo, hi = s[change[0]], s[change[0] + 1]
        flo = f[change[0]]
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            fm = float(signed_distance(self.at(mid))[0])
            if np.signbit(fm) == np.signbit(flo):
                lo, flo = mid, fm
            else:
                hi = mid
        return self.at(0.5 * (lo + hi))[0]

    def project(self, projection_matrix: ArrayLike) -> NDArray[np.float64]:
        """Image of the line under a 3x4 projection: homogeneous 2D line (a, b, c), a^2 + b^2 = 1.

        Pixels (u, v) on the image line satisfy ``a u + b v + c = 0``.
        """
        p = np.asarray(projection_matrix, dtype=np.float64)
        x0 = p @ np.append(self.point_mm, 1.0)
        x1 = p @ np.append(self.point_mm + 100.0 * self.direction, 1.0)
        return line_through_points_2d(x0, x1)


def line_through_points_2d(x0_h: ArrayLike, x1_h: ArrayLike) -> NDArray[np.float64]:
    """Homogeneous 2D line (3,) through two homogeneous image points, normalised so a^2 + b^2 = 1."""
    line = np.cross(np.asarray(x0_h, float), np.asarray(x1_h, float))
    n = np.hypot(line[0], line[1])
    if n < 1e-12:
        raise ValueError("the line projects to a point (it runs along the ray)")
    return line / n
