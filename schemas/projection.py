"""Projection-matrix JSON: a calibrated 3x4 matrix per fluoroscopy image (overrides positioner attributes)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema

from drillnav.registration.carm import CArmView

PROJECTION_SCHEMA = json.loads(Path(__file__).with_name("projection.schema.json").read_text())

__all__ = ["view_to_json", "view_from_json", "write_projection", "read_projection"]


def view_to_json(view: CArmView) -> dict[str, Any]:
    return {
        "projection_matrix": [[float(v) for v in row] for row in view.projection_matrix],
        "rows": view.rows,
        "columns": view.columns,
        "pixel_spacing_mm": list(view.pixel_spacing_mm),
        **({"distortion_sigma_px": float(view.distortion_sigma_px)} if view.distortion_sigma_px > 0 else {}),
    }


def view_from_json(doc: Any, *, source: str = "projection") -> CArmView:
    try:
        jsonschema.validate(doc, PROJECTION_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise ValueError(f"{source}: invalid at {where}: {exc.message}") from None
    try:
        return CArmView(projection_matrix=doc["projection_matrix"], rows=int(doc["rows"]), columns=int(doc["columns"]), pixel_spacing_mm=tuple(doc["pixel_spacing_mm"]),
                        distortion_sigma_px=float(doc.get("distortion_sigma_px", 0.0)))
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
