"""JSON forms of transforms and axes shared by every drillnav file.

A transform is a 4x4 row-major nested list in mm (``target_from_source``); an
axis is ``{"point_mm": [x, y, z], "direction": [dx, dy, dz]}`` with a unit
direction that, for the drill axis, points from the drill into the patient.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drillnav.registration.line import Line3D
from drillnav.registration.transforms import check_transform

__all__ = [
    "TRANSFORM_SCHEMA",
    "AXIS_SCHEMA",
    "transform_to_json",
    "transform_from_json",
    "axis_to_json",
    "axis_from_json",
]

TRANSFORM_SCHEMA: dict[str, Any] = {
    "type": "array",
    "description": "4x4 rigid transform target_from_source, row-major, translation in mm",
    "minItems": 4,
    "maxItems": 4,
    "items": {"type": "array", "minItems": 4, "maxItems": 4, "items": {"type": "number"}},
}

AXIS_SCHEMA: dict[str, Any] = {
    "type": "object",
    "description": "a 3D line: a point in mm and a unit direction (drill into patient)",
    "required": ["point_mm", "direction"],
    "properties": {
        "point_mm": {"type": "array", "minItems": 3, "maxItems": 3, "items": {"type": "number"}},
        "direction": {"type": "array", "minItems": 3, "maxItems": 3, "items": {"type": "number"}},
    },
}


def transform_to_json(target_from_source: ArrayLike) -> list[list[float]]:
    """4x4 transform -> nested lists (row-major)."""
    return [[float(v) for v in row] for row in np.asarray(target_from_source, dtype=np.float64)]


def transform_from_json(value: Any, *, name: str = "transform") -> NDArray[np.float64]:
    """Nested lists -> checked 4x4 rigid transform; ``ValueError`` naming ``name`` otherwise."""
    try:
        return check_transform(np.asarray(value, dtype=np.float64), tolerance=1e-5)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: {exc}") from exc


def axis_to_json(axis: Line3D) -> dict[str, list[float]]:
    return {"point_mm": [float(v) for v in axis.point_mm], "direction": [float(v) for v in axis.direction]}


def axis_from_json(value: Any, *, name: str = "axis") -> Line3D:
    try:
        return Line3D(point_mm=value["point_mm"], direction=value["direction"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected {{'point_mm': [x, y, z], 'direction': [dx, dy, dz]}}: {exc}") from exc
