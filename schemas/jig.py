"""jig.json: the drill-axis jig's geometry (ArUco grid board), as ``drillnav markers jig`` prints it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from drillnav.registration.drill_axis import (
    JIG_DICTIONARY, JIG_MARKER_MM, JIG_MARKERS, JIG_SEPARATION_MM, MIN_JIG_TAGS, jig_size_mm, jig_tag_corners_mm,
)

__all__ = ["JIG_SCHEMA", "jig_geometry_json"]

JIG_SCHEMA = json.loads(Path(__file__).with_name("jig.schema.json").read_text())


def jig_geometry_json() -> dict[str, Any]:
    """The jig as designed (:mod:`drillnav.registration.drill_axis`): layout, and each tag's corners in the board frame."""
    return {
        "schema": "drillnav.jig/1",
        "dictionary": JIG_DICTIONARY,
        "markers": list(JIG_MARKERS),
        "marker_mm": JIG_MARKER_MM,
        "separation_mm": JIG_SEPARATION_MM,
        "board_mm": [jig_size_mm(), jig_size_mm()],
        "min_tags_per_frame": MIN_JIG_TAGS,
        "frame": "board frame: origin at the outer top-left corner of the top-left tag as printed, x to the right, y down the page, "
                 "z into the board (OpenCV GridBoard); mm",
        "tags": [{"id": i, "corners_mm": [[float(v) for v in c] for c in corners]} for i, corners in sorted(jig_tag_corners_mm().items())],
    }
