"""``drillnav calibration convert``: camera.json <-> OpenCV YAML <-> ROS camera_info YAML."""

from __future__ import annotations

import argparse
from pathlib import Path

from drillnav.schemas.camera_yaml import CalibrationFormat, convert

from .cli import CliError
from .outputs import check_output_path

__all__ = ["register"]


def _convert(args: argparse.Namespace) -> int:
    src = Path(args.input)
    if not src.is_file():
        raise CliError(f"{src}: no such file")
    out = check_output_path(args.output, suffixes=(".json", ".yaml", ".yml"))
    if args.to is None:
        if out.suffix.lower() != ".json":
            raise CliError(f"{out}: a YAML output needs --to opencv or --to ros (the two YAML formats differ)")
        to = CalibrationFormat.JSON
    else:
        to = CalibrationFormat(args.to)
    out.write_text(convert(src.read_text(), to, source=str(src), camera_name=args.camera_name))
    print(f"{src} -> {out} ({to.value})")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("calibration", help="calibration files in other tools' formats")
    sub = p.add_subparsers(dest="calibration_command", metavar="WHAT", required=True)
    c = sub.add_parser("convert", help="camera.json, OpenCV YAML or ROS camera_info YAML (read: any, detected) to one of them")
    c.add_argument("input")
    c.add_argument("output")
    c.add_argument("--to", choices=[f.value for f in CalibrationFormat], help="output format (default: json for a .json output)")
    c.add_argument("--camera-name", default="drill_camera", help="camera_name in a ROS file")
    c.set_defaults(func=_convert)
