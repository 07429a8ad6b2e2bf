"""``drillnav markers export|sheet``: the marker set as JSON, and printable sheets for making markers."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from .cli import CliError
from .outputs import check_output_path

if TYPE_CHECKING:
    from drillnav.registration.markers import MarkerSet

# numpy, OpenCV and matplotlib are imported by the commands that use them: ``drillnav markers --help`` stays instant.

__all__ = ["register", "parse_ids"]


def parse_ids(text: str, marker_set: MarkerSet) -> list[int]:
    """'0-4,7' -> [0, 1, 2, 3, 4, 7]; refuses malformed ranges and unknown ids."""
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        try:
            if "-" in part:
                lo, hi = (int(v) for v in part.split("-", 1))
                if hi < lo:
                    raise CliError(f"marker id range '{part}' runs backwards")
                ids.extend(range(lo, hi + 1))
            else:
                ids.append(int(part))
        except ValueError:
            raise CliError(f"malformed marker ids '{text}': use e.g. 0-4,7") from None
    for i in ids:
        marker_set.by_id(i)
    return ids


def _export(args: argparse.Namespace) -> int:
    from drillnav.registration.markers import default_marker_set
    from drillnav.schemas.markers import write_marker_set

    ms = default_marker_set()
    if args.ids:
        ms = ms.subset(parse_ids(args.ids, ms))
    out = check_output_path(args.out, suffixes=(".json",))
    write_marker_set(out, ms)
    print(f"wrote {len(ms.markers)} markers to {out}")
    return 0


def _sheet(args: argparse.Namespace) -> int:
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    from drillnav.registration.markers import default_marker_set

    ms = default_marker_set()
    ids = parse_ids(args.ids, ms)
    out = check_output_path(args.out, suffixes=(".pdf", ".svg"))
    mm = 1 / 25.4
    per_row = 3
    cell = 60.0
    rows = (len(ids) + per_row - 1) // per_row
    fig = plt.figure(figsize=(per_row * cell * mm, rows * cell * mm))
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_xlim(0, per_row * cell)
    ax.set_ylim(-rows * cell, 0)
    ax.set_aspect("equal")
    ax.axis("off")
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    for n, i in enumerate(ids):
        m = ms.by_id(i)
        cx, cy = (n % per_row + 0.5) * cell, -(n // per_row + 0.5) * cell
        h = m.tag_size_mm / 2
        tag = cv2.aruco.generateImageMarker(dictionary, m.aruco_id, 240)
        ax.imshow(tag, cmap="gray", extent=(cx - h, cx + h, cy - h, cy + h), interpolation="nearest", zorder=2)
        ax.add_patch(Circle((cx, cy), m.ring_radius_mm, fill=False, lw=m.ring_wire_diameter_mm / mm * 72 / 72, color="tab:blue", zorder=1))
        for b in m.bbs:
            ax.add_patch(Circle((cx + b.center_mm[0], cy + b.center_mm[1]), b.diameter_mm / 2, fill=False, color="tab:red", lw=0.6, zorder=3))
        ax.add_patch(Rectangle((cx - h, cy - h), 2 * h, 2 * h, fill=False, lw=0.3, color="k", zorder=3))
        ax.text(cx, cy - m.ring_radius_mm - 3, f"marker {i}  tag 30 mm  BB red (2.0/3.5 mm)  ring 48 mm", ha="center", va="top", fontsize=4)
    fig.savefig(out)
    plt.close(fig)
    print(f"wrote a 1:1 sheet of markers {ids} to {out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("markers", help="the multimodal marker set")
    sub = p.add_subparsers(dest="markers_command", metavar="ACTION", required=True)
    e = sub.add_parser("export", help="write the marker set (markers.json)")
    e.add_argument("--out", required=True)
    e.add_argument("--ids", help="ids to export, e.g. 0-4,7 (default: all 48)")
    e.set_defaults(func=_export)
    s = sub.add_parser("sheet", help="print tags at 1:1 scale with the BB layout (PDF or SVG)")
    s.add_argument("--ids", required=True)
    s.add_argument("--out", required=True)
    s.set_defaults(func=_sheet)
    from .cli_detect import add_detect

    add_detect(sub)
