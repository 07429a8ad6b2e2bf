"""truth.json and plan.json of a twin scene folder."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np

from drillnav.registration.line import Line3D

from .geometry_json import axis_from_json, axis_to_json, transform_from_json, transform_to_json

__all__ = ["truth_to_json", "read_truth", "plan_to_json", "read_plan", "Truth", "TRUTH_SCHEMA", "PLAN_SCHEMA"]

TRUTH_SCHEMA = json.loads(Path(__file__).with_name("truth.schema.json").read_text())
PLAN_SCHEMA = json.loads(Path(__file__).with_name("plan.schema.json").read_text())


def _validated(path: str | Path, schema: dict) -> dict[str, Any]:
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
        jsonschema.validate(doc, schema)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not valid JSON ({exc})") from None
    except jsonschema.ValidationError as exc:
        where = "/".join(str(x) for x in exc.absolute_path) or "(top level)"
        raise ValueError(f"{p}: invalid at {where}: {exc.message}") from None
    return doc


def truth_to_json(*, carm_from_drill, carm_from_ct, drill_axis_carm: Line3D, corridor_entry_carm_mm, carm_from_marker: dict[int, Any], corridor: str, seed: int) -> dict[str, Any]:
    return {
        "schema": "drillnav.truth/1",
        "seed": seed,
        "corridor": corridor,
        "carm_from_drill": transform_to_json(carm_from_drill),
        "carm_from_ct": transform_to_json(carm_from_ct),
        "drill_axis_carm": axis_to_json(drill_axis_carm),
        "corridor_entry_carm_mm": [float(v) for v in corridor_entry_carm_mm],
        "markers": [{"id": int(i), "carm_from_marker": transform_to_json(t)} for i, t in sorted(carm_from_marker.items())],
    }


class Truth:
    """A parsed truth.json."""

    def __init__(self, doc: dict[str, Any]) -> None:
        self.carm_from_drill = transform_from_json(doc["carm_from_drill"], name="carm_from_drill")
        self.carm_from_ct = transform_from_json(doc["carm_from_ct"], name="carm_from_ct")
        self.drill_axis_carm = axis_from_json(doc["drill_axis_carm"], name="drill_axis_carm")
        self.corridor_entry_carm_mm = np.asarray(doc["corridor_entry_carm_mm"], dtype=np.float64)
        self.carm_from_marker = {m["id"]: transform_from_json(m["carm_from_marker"], name=f"marker {m['id']}") for m in doc["markers"]}


def read_truth(path: str | Path) -> Truth:
    return Truth(_validated(path, TRUTH_SCHEMA))


def read_plan(path: str | Path) -> dict[str, Any]:
    """plan.json, validated against plan.schema.json."""
    return _validated(path, PLAN_SCHEMA)


def plan_to_json(corridors) -> dict[str, Any]:
    return {
        "schema": "drillnav.plan/1",
        "frame": "CT patient coordinates (LPS), mm",
        "trajectories": [
            {"name": c.name, "entry_mm": list(map(float, c.entry_mm)), "target_mm": list(map(float, c.target_mm)), "corridor": {"type": "cylinder", "radius_mm": c.radius_mm}}
            for c in corridors
        ],
    }
