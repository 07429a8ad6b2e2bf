"""markers.json: the marker set as the product is handed it (the design, in mm, marker frame)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np

from drillnav.registration.markers import BB, MarkerDesign, MarkerSet

__all__ = ["SCHEMA_ID", "MARKERS_SCHEMA", "marker_set_to_json", "marker_set_from_json", "write_marker_set", "read_marker_set"]

SCHEMA_ID = "drillnav.markers/1"
MARKERS_SCHEMA: dict[str, Any] = json.loads((Path(__file__).with_name("markers.schema.json")).read_text())


def _vec(v) -> list[float]:
    return [float(x) for x in np.asarray(v).reshape(-1)]


def marker_set_to_json(marker_set: MarkerSet) -> dict[str, Any]:
    return {
        "schema": SCHEMA_ID,
        "frame": "marker frame m: origin at the central BB, +z along the normal towards the tag side, mm",
        "markers": [
            {
                "id": m.marker_id,
                "aruco": {"dictionary": m.aruco_dictionary, "id": m.aruco_id},
                "tag": {"size_mm": m.tag_size_mm, "center_mm": _vec(m.tag_center_mm)},
                "bbs": [{"center_mm": _vec(b.center_mm), "diameter_mm": b.diameter_mm} for b in m.bbs],
                "ring": {
                    "center_mm": _vec(m.ring_center_mm),
                    "normal": _vec(m.ring_normal),
                    "radius_mm": m.ring_radius_mm,
                    "wire_diameter_mm": m.ring_wire_diameter_mm,
                },
            }
            for m in marker_set.markers
        ],
    }


def marker_set_from_json(doc: Any) -> MarkerSet:
    """Validate against markers.schema.json and build the set; ``ValueError`` naming the field otherwise."""
    try:
        jsonschema.validate(doc, MARKERS_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise ValueError(f"markers file is invalid at {where}: {exc.message}") from None
    markers = []
    for m in doc["markers"]:
        markers.append(
            MarkerDesign(
                marker_id=m["id"],
                aruco_id=m["aruco"]["id"],
                aruco_dictionary=m["aruco"]["dictionary"],
                tag_size_mm=m["tag"]["size_mm"],
                tag_center_mm=np.array(m["tag"]["center_mm"], float),
                bbs=tuple(BB(center_mm=b["center_mm"], diameter_mm=b["diameter_mm"]) for b in m["bbs"]),
                ring_center_mm=np.array(m["ring"]["center_mm"], float),
                ring_normal=np.array(m["ring"]["normal"], float),
                ring_radius_mm=m["ring"]["radius_mm"],
                ring_wire_diameter_mm=m["ring"]["wire_diameter_mm"],
            )
        )
    ids = [m.marker_id for m in markers]
    if len(set(ids)) != len(ids):
        raise ValueError("markers file is invalid: duplicate marker ids")
    return MarkerSet(markers=tuple(markers))


def write_marker_set(path: str | Path, marker_set: MarkerSet) -> None:
    Path(path).write_text(json.dumps(marker_set_to_json(marker_set), indent=1))


def read_marker_set(path: str | Path) -> MarkerSet:
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    return marker_set_from_json(doc)
