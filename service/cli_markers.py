"""``drillnav markers export|sheet|jig``: the marker set as JSON, and printable sheets for making markers (``detect`` and
``measure`` are in ``cli_detect`` and ``cli_measure``)."""

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


SHEET_CELL_MM = 60.0  # one marker and its label per cell
PAGE_MARGIN_MM = 12.0
SCALE_BAR_BAND_MM = 22.0  # room at the foot of a page for the scale bar and its caption


def _sheet(args: argparse.Namespace) -> int:
    import cv2
    from matplotlib.patches import Circle, Rectangle

    from drillnav.registration.markers import default_marker_set

    from .print_pages import PAPER_MM, draw_scale_bar, line_width_pt, new_page, save_pages

    ms = default_marker_set()
    ids = parse_ids(args.ids, ms)
    out = check_output_path(args.out, suffixes=(".pdf", ".svg"))
    w, h = PAPER_MM[args.paper]
    cell = SHEET_CELL_MM
    per_row = int((w - 2 * PAGE_MARGIN_MM) // cell)
    rows = int((h - 2 * PAGE_MARGIN_MM - SCALE_BAR_BAND_MM) // cell)
    per_page = per_row * rows
    x0 = (w - per_row * cell) / 2
    top = h - PAGE_MARGIN_MM
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    pages = []
    for first in range(0, len(ids), per_page):
        fig, ax = new_page(args.paper)
        chunk = ids[first : first + per_page]
        for n, i in enumerate(chunk):
            m = ms.by_id(i)
            cx, cy = x0 + (n % per_row + 0.5) * cell, top - (n // per_row + 0.5) * cell
            half = m.tag_size_mm / 2
            tag = cv2.aruco.generateImageMarker(dictionary, m.aruco_id, 240)
            ax.imshow(tag, cmap="gray", vmin=0, vmax=255, extent=(cx - half, cx + half, cy - half, cy + half), interpolation="none", zorder=2)
            # The wire ring drawn as wide as the wire (0.8 mm): a guide to lay the wire on.
            ax.add_patch(Circle((cx, cy), m.ring_radius_mm, fill=False, lw=line_width_pt(m.ring_wire_diameter_mm), color="tab:blue", zorder=1))
            for b in m.bbs:
                ax.add_patch(Circle((cx + b.center_mm[0], cy + b.center_mm[1]), b.diameter_mm / 2, fill=False, color="tab:red",
                                    lw=line_width_pt(0.2), zorder=3))
            ax.add_patch(Rectangle((cx - half, cy - half), 2 * half, 2 * half, fill=False, lw=line_width_pt(0.1), color="k", zorder=3))
            ax.text(cx, cy - m.ring_radius_mm - 2, f"marker {i}  tag {m.tag_size_mm:g} mm  BBs red ({', '.join(f'{d:g}' for d in sorted(set(m.bb_diameters_mm)))} mm)"
                    f"  ring {2 * m.ring_radius_mm:g} mm of {m.ring_wire_diameter_mm:g} mm wire", ha="center", va="top", fontsize=4)
        draw_scale_bar(ax, (w - 100.0) / 2, PAGE_MARGIN_MM + 8.0)
        pages.append(fig)
    save_pages(pages, out)
    print(f"wrote markers {ids} at 1:1 on {len(pages)} {args.paper} page(s) to {out}: check the 100 mm scale bar after printing")
    return 0


JIG_QUIET_ZONE_MM = 8.0  # white border about the board: the detector needs it to find the outer tags' edges


def _jig(args: argparse.Namespace) -> int:
    import json

    from matplotlib.patches import Rectangle

    from drillnav.registration.drill_axis import JIG_DICTIONARY, JIG_MARKER_MM, JIG_MARKERS, JIG_SEPARATION_MM, jig_board, jig_ids, jig_size_mm
    from drillnav.schemas.jig import jig_geometry_json

    from .print_pages import PAPER_MM, draw_scale_bar, line_width_pt, new_page, save_pages

    out = check_output_path(args.out, suffixes=(".pdf", ".svg"))
    geometry = check_output_path(args.geometry or out.with_suffix(".json"), suffixes=(".json",))
    w, h = PAPER_MM[args.paper]
    s = jig_size_mm()
    px_per_mm = 20  # the tags' cells fall on whole pixels: 12 mm tags of 8 cells, 30 px a cell
    image = jig_board().generateImage((round(s * px_per_mm), round(s * px_per_mm)), marginSize=0)
    fig, ax = new_page(args.paper)
    x0, y0 = (w - s) / 2, (h - s) / 2 + 20.0  # board's bottom-left corner on the page (mm)
    q = JIG_QUIET_ZONE_MM
    ax.add_patch(Rectangle((x0 - q, y0 - q), s + 2 * q, s + 2 * q, fill=False, lw=line_width_pt(0.2), ls=(0, (4, 4)), color="0.4"))
    ax.imshow(image, cmap="gray", vmin=0, vmax=255, extent=(x0, x0 + s, y0, y0 + s), interpolation="none")
    ax.text(w / 2, y0 + s + q + 6, "drillnav drill-axis jig", ha="center", va="bottom", fontsize=11)
    lines = [
        f"ArUco {JIG_DICTIONARY} grid board, {JIG_MARKERS[0]}x{JIG_MARKERS[1]} tags, ids {jig_ids()[0]}-{jig_ids()[-1]}, tags {JIG_MARKER_MM:g} mm, "
        f"gaps {JIG_SEPARATION_MM:g} mm, board {s:g} mm square.",
        "Cut along the dashed line (keep the white border). Glue flat on a rigid plate fixed to the drill or its sleeve,",
        "facing the drill camera, so the board turns with the drill about the drill axis. Record frames (or a live job)",
        "while turning the drill at least 20 deg (better 90 deg or more), the whole board in view.",
        f"Geometry (board frame, tag corners in mm): {geometry.name}.",
    ]
    for k, line in enumerate(lines):
        ax.text(w / 2, y0 - q - 6 - 4.5 * k, line, ha="center", va="top", fontsize=6.5)
    draw_scale_bar(ax, (w - 100.0) / 2, PAGE_MARGIN_MM + 8.0)
    save_pages([fig], out)
    geometry.write_text(json.dumps(jig_geometry_json(), indent=1))
    print(f"wrote the drill-axis jig at 1:1 on {args.paper} to {out} and its geometry to {geometry}: check the 100 mm scale bar after printing")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("markers", help="the multimodal marker set")
    sub = p.add_subparsers(dest="markers_command", metavar="ACTION", required=True)
    e = sub.add_parser("export", help="write the marker set (markers.json)")
    e.add_argument("--out", required=True)
    e.add_argument("--ids", help="ids to export, e.g. 0-4,7 (default: all 48)")
    e.set_defaults(func=_export)
    s = sub.add_parser("sheet", help="print tags at 1:1 scale with the BB layout and the wire ring (PDF or SVG), with a 100 mm scale bar")
    s.add_argument("--ids", required=True)
    s.add_argument("--out", required=True, help="sheet.pdf (one page per 12 markers on A4, 9 on Letter) or sheet.svg (one page)")
    s.add_argument("--paper", choices=("A4", "Letter"), default="A4")
    s.set_defaults(func=_sheet)
    j = sub.add_parser("jig", help="print the drill-axis calibration jig at 1:1 (PDF or SVG) and write its geometry (JSON)")
    j.add_argument("--out", required=True, help="jig.pdf or jig.svg")
    j.add_argument("--geometry", help="where the geometry JSON goes (default: beside --out, as .json)")
    j.add_argument("--paper", choices=("A4", "Letter"), default="A4")
    j.set_defaults(func=_jig)
    from .cli_detect import add_detect
    from .cli_measure import add_measure

    add_detect(sub)
    add_measure(sub)
