"""``drillnav calibrate camera|drill-axis``: calibrations from image files, written as camera.json / drill.json."""

from __future__ import annotations

import argparse

from .outputs import check_output_path

# OpenCV, scipy and the calibration math are imported by the commands that use them: ``--help`` stays instant.

__all__ = ["register"]


def _camera(args: argparse.Namespace) -> int:
    from drillnav.drivers.image_files import read_image
    from drillnav.registration.camera_calibration import calibrate_camera, parse_board
    from drillnav.schemas.calibration import write_camera_calibration

    out = check_output_path(args.out, suffixes=(".json",))
    spec = parse_board(args.board)
    images = [read_image(p) for p in args.images]
    cal = calibrate_camera(images, spec)
    write_camera_calibration(out, cal.camera, rms_px=cal.rms_px, per_view_errors_px=list(cal.per_view_errors_px), label=args.label)
    fx, fy = cal.camera.focal_px
    print(f"calibrated from {len(cal.used_views)} views (rejected {list(cal.rejected_views)}, board not found in {list(cal.not_found_views)}): "
          f"fx {fx:.1f} fy {fy:.1f} px, RMS {cal.rms_px:.3f} px -> {out}")
    return 0


def _drill_axis(args: argparse.Namespace) -> int:
    import numpy as np

    from drillnav.drivers.image_files import read_image
    from drillnav.registration.drill_axis import find_jig_poses, fit_axis_cylinder, fit_axis_screw, jig_size_mm
    from drillnav.schemas.calibration import read_camera_calibration, write_drill_calibration

    out = check_output_path(args.out, suffixes=(".json",))
    camera = read_camera_calibration(args.camera)
    poses = find_jig_poses([(p, read_image(p)) for p in args.frames], camera)
    screw = fit_axis_screw(poses)
    s = jig_size_mm()
    corners = np.array([[0, 0, 0], [s, 0, 0], [s, s, 0], [0, s, 0], [s / 2, s / 2, 0]], dtype=float)
    cyl = fit_axis_cylinder(poses, corners)
    write_drill_calibration(out, screw.axis, method="screw (common rotation axis, refined)", residual_mm=screw.residual_mm, residual_deg=screw.residual_deg, label=args.label)
    print(f"drill axis from {len(poses)} jig poses over {screw.rotation_range_deg:.0f} deg: screw residual {screw.residual_mm:.3f} mm / {screw.residual_deg:.3f} deg; "
          f"cylinder (MLESAC) residual {cyl.residual_mm:.3f} mm, {screw.axis.angle_deg(cyl.axis):.2f} deg from the screw axis -> {out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("calibrate", help="camera and drill-axis calibration")
    sub = p.add_subparsers(dest="calibrate_command", metavar="WHAT", required=True)
    c = sub.add_parser("camera", help="intrinsics from checkerboard or ChArUco views")
    c.add_argument("images", nargs="+")
    c.add_argument("--board", required=True, help="checkerboard:9x6:25mm or charuco:5x7:40mm:30mm[:DICT]")
    c.add_argument("--out", required=True)
    c.add_argument("--label", default="drill camera")
    c.set_defaults(func=_camera)
    d = sub.add_parser("drill-axis", help="the drill axis from frames of the rotating jig")
    d.add_argument("frames", nargs="+")
    d.add_argument("--camera", required=True, help="camera.json")
    d.add_argument("--out", required=True)
    d.add_argument("--label", default="drill")
    d.set_defaults(func=_drill_axis)
