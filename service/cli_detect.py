"""``drillnav markers detect``: the video detector on any image, so a user can check what the camera sees."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from .outputs import check_output_path

if TYPE_CHECKING:
    from drillnav.registration.camera import PinholeCamera

__all__ = ["add_detect"]


def read_any_camera(path: str) -> PinholeCamera:
    """camera.json, or an OpenCV YAML with camera_matrix and distortion_coefficients."""
    import cv2

    from drillnav.registration.camera import PinholeCamera
    from drillnav.schemas.calibration import read_camera_calibration

    p = Path(path)
    if p.suffix.lower() in (".yml", ".yaml"):
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        k, d = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
        w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
        fs.release()
        if k is None or d is None:
            raise ValueError(f"{p}: needs camera_matrix and distortion_coefficients")
        return PinholeCamera(width=w, height=h, camera_matrix=k, distortion=d.ravel())
    return read_camera_calibration(p)


def _detect(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from drillnav.drivers.image_files import read_image
    from drillnav.registration.transforms import make_transform
    from drillnav.registration.video_markers import detect_tags, tag_object_points
    from drillnav.schemas.geometry_json import transform_to_json

    out = check_output_path(args.out, suffixes=(".json",))
    image = read_image(args.image)
    tags = detect_tags(image, dictionary=args.dictionary)
    camera = read_any_camera(args.camera) if args.camera else None
    markers = []
    for marker_id, corners in tags:
        entry = {"id": marker_id, "corners_px": corners.tolist()}
        if camera is not None:
            obj = tag_object_points(args.tag_size_mm)
            n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, corners, camera.camera_matrix, camera.distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            best = int(np.argmin(np.asarray(errs).ravel()))
            entry["camera_from_tag"] = transform_to_json(make_transform(cv2.Rodrigues(rvecs[best])[0], tvecs[best].ravel()))
        markers.append(entry)
    out.write_text(json.dumps({"image": str(args.image), "dictionary": args.dictionary, "markers": markers}, indent=1))
    print(f"{len(markers)} tag(s) found: ids {sorted(m['id'] for m in markers)} -> {out}")
    return 0


def add_detect(markers_subparsers) -> None:
    d = markers_subparsers.add_parser("detect", help="detect ArUco tags in an image (and their poses, given a camera)")
    d.add_argument("image")
    d.add_argument("--dictionary", default="DICT_6X6_250")
    d.add_argument("--camera", help="camera.json or OpenCV YAML")
    d.add_argument("--tag-size-mm", type=float, default=30.0)
    d.add_argument("--out", required=True)
    d.set_defaults(func=_detect)
