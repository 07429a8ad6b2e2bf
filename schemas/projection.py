"""Projection-matrix JSON: a calibrated 3x4 matrix per fluoroscopy image (overrides positioner attributes)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from drillnav.registration.carm import CArmView

__all__ = ["view_to_json", "view_from_json", "write_projection", "read_projection"]


def view_to_json(view: CArmView) -> dict[str, Any]:
    return {
        "projection_matrix": [[float(v) for v in row] for row in view.projection_matrix],
        "rows": view.rows,
        "columns": view.columns,
        "pixel_spacing_mm": list(view.pixel_spacing_mm),
    }


def view_from_json(doc: Any, *, source: str = "projection") -> CArmView:
    if not isinstance(doc, dict):
        raise ValueError(f"{source}: expected a JSON object")
    for key in ("projection_matrix", "rows", "columns", "pixel_spacing_mm"):
        if key not in doc:
            raise ValueError(f"{source}: missing field '{key}'")
    try:
        return CArmView(projection_matrix=doc["projection_matrix"], rows=int(doc["rows"]), columns=int(doc["columns"]), pixel_spacing_mm=tuple(doc["pixel_spacing_mm"]))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: {exc}") from None


def write_projection(path: str | Path, view: CArmView) -> None:
    Path(path).write_text(json.dumps(view_to_json(view), indent=1))


def read_projection(path: str | Path) -> CArmView:
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not valid JSON ({exc})") from None
    return view_from_json(doc, source=str(p))
