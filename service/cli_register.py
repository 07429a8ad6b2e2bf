"""``drillnav register``: the drill axis on the fluoroscopy views from one camera frame and 1+ shots.

The parser alone: the work (and its numpy, OpenCV and registration imports) is in ``registration_run``, imported
when the command runs, so ``drillnav register --help`` answers at once.
"""

from __future__ import annotations

import argparse

__all__ = ["register"]


def _handler(args: argparse.Namespace) -> int:
    from .registration_run import handle

    return handle(args)


def register(subparsers) -> None:
    p = subparsers.add_parser("register", help="register the drill axis to fluoroscopy from a camera frame and 1+ shots")
    p.add_argument("--markers", required=True, help="markers.json")
    p.add_argument("--camera", required=True, help="camera.json")
    p.add_argument("--drill", required=True, help="drill.json")
    p.add_argument("--video", required=True, help="camera frame (PNG/JPEG)")
    p.add_argument("--fluoro", required=True, nargs="+", help="fluoroscopy DICOM file(s); <file>.json beside one overrides its geometry")
    p.add_argument("--out", required=True, help="result.json")
    p.add_argument("--overlays", help="folder for overlay PNGs")
    p.add_argument("--mask-markers", action="store_true", help="mask the markers out of the overlays")
    p.add_argument("--ct", help="preoperative CT: a folder with one DICOM series or a .nii/.nii.gz file (video-CT mode)")
    p.add_argument("--plan", help="plan.json: planned trajectories in CT coordinates, judged for conformance")
    p.add_argument("--ct-views", help="folder for the CT slice images (axial, coronal, sagittal, oblique + mosaic)")
    p.add_argument("--ct-at", help="X,Y,Z: the CT point the C-arm is centred on (default: the plan's first entry, else the CT centre)")
    p.add_argument("--refine-gi", action="store_true", help="refine each marker pose by the reference's DRR + gradient information + CMA-ES (about 1.5 s per marker)")
    p.set_defaults(func=_handler)
