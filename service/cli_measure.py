"""``drillnav markers measure``: each marker's BBs as built, from fluoroscopy shots of the markers from several angles.

The markers lie still (on the table, or on the patient before the case) while the C-arm shoots them from several
angles (AP, lateral, inlet, outlet, obliques: the wider the spread, the better each BB is placed). Every marker
identified in at least two shots has its BBs measured (:mod:`drillnav.registration.marker_as_built`) and written
into a copy of markers.json; the rest of each marker (tag, ring) and every other marker are copied as they are.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

from .cli import CliError
from .outputs import check_output_path

__all__ = ["add_measure"]

# A marker whose BBs fit their views worse than this (RMS px) moved between the shots, or a BB was matched wrongly:
# it is not measured, and keeps its design in the markers.json written.
MAX_RESIDUAL_PX = 1.5


def _measure(args: argparse.Namespace) -> int:
    import numpy as np

    from drillnav.drivers.fluoro_dicom import read_fluoro
    from drillnav.registration.errors import DegenerateInput
    from drillnav.registration.marker_as_built import measure_as_built
    from drillnav.registration.marker_pose import register_markers
    from drillnav.registration.markers import BB, MarkerSet
    from drillnav.schemas.markers import read_marker_set, write_marker_set

    from .fluoro_polarity import settle_polarity

    out = check_output_path(args.out, suffixes=(".json",))
    if not args.tolerance_mm > 0:
        raise CliError(f"--tolerance-mm must be > 0, got {args.tolerance_mm}")
    marker_set = read_marker_set(args.markers)
    images = [img for f in args.fluoro for img in read_fluoro(f)]
    if len(images) < 2:
        raise CliError(f"{len(images)} fluoroscopy image(s): measuring the markers needs at least 2 shots from different angles")
    # An image whose file does not say which way its values run is taken in the reading that shows the markers.
    detections = [settle_polarity(img, marker_set).detections for img in images]
    poses = register_markers(detections, [img.view for img in images], marker_set)
    measured = {}
    for pose in poses:
        design = marker_set.by_id(pose.marker_id)
        try:
            got = measure_as_built(pose, design, tolerance_mm=args.tolerance_mm)
        except DegenerateInput as exc:
            print(f"marker {pose.marker_id}: not measured: {exc}")
            continue
        if got.residual_px > MAX_RESIDUAL_PX:
            print(f"marker {pose.marker_id}: not measured: its BBs fit their {got.n_views} views at {got.residual_px:.2f} px RMS "
                  f"(over {MAX_RESIDUAL_PX} px: the marker moved between the shots, or a BB was matched wrongly)")
            continue
        measured[pose.marker_id] = got
        print(f"marker {pose.marker_id}: {got.n_views} views, BBs moved {np.round(got.moved_mm, 3).tolist()} mm from the design "
              f"(1 sigma {np.round(got.sigma_mm, 3).tolist()} mm), fit {got.residual_px:.2f} px RMS")
    if not measured:
        raise CliError("no marker was identified in 2 or more shots with a consistent fit: nothing measured, nothing written")
    markers = []
    for m in marker_set.markers:
        got = measured.get(m.marker_id)
        if got is not None:
            m = replace(m, bbs=tuple(BB(center_mm=c, diameter_mm=b.diameter_mm) for c, b in zip(got.bb_centers_mm, m.bbs)))
        markers.append(m)
    write_marker_set(out, MarkerSet(markers=tuple(markers)))
    print(f"wrote {out}: {len(measured)} of {len(marker_set.markers)} markers measured ({sorted(measured)})")
    return 0


def add_measure(markers_subparsers) -> None:
    m = markers_subparsers.add_parser("measure", help="measure each marker's BBs as built from fluoroscopy shots of the markers from several angles")
    m.add_argument("--markers", required=True, help="markers.json (the design)")
    m.add_argument("--fluoro", required=True, nargs="+", help="fluoroscopy DICOM files of the markers lying still, from 2 or more angles")
    m.add_argument("--out", required=True, help="markers.json with the measured BBs")
    m.add_argument("--tolerance-mm", type=float, default=0.1, help="the BBs' manufacturing tolerance, 1 sigma per axis (default %(default)s mm)")
    m.set_defaults(func=_measure)
