"""``drillnav sim scene``: write one digital-twin scene folder that the other commands take as it is."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
from pydicom.uid import generate_uid

from drillnav.drivers.sim import anatomy
from drillnav.drivers.sim.ct_phantom import make_pelvis_ct
from drillnav.drivers.sim.dicom_io import write_ct_series, write_xa
from drillnav.drivers.sim.scene import PAPER_CARM, Scene, make_scene
from drillnav.registration.markers import default_marker_set
from drillnav.schemas.calibration import write_camera_calibration, write_drill_calibration
from drillnav.schemas.markers import write_marker_set
from drillnav.schemas.projection import write_projection
from drillnav.schemas.scene_files import plan_to_json, truth_to_json

from .cli import CliError
from .cli_markers import parse_ids
from .outputs import check_output_dir

__all__ = ["register", "write_scene"]


def write_scene(scene: Scene, out: Path, *, ct_voxel_mm: float | None = None) -> dict[str, float]:
    """Write every file of the scene folder (``ct/``, the CT series, when ``ct_voxel_mm``); returns timings in s."""
    t0 = time.perf_counter()
    if ct_voxel_mm is not None:
        ct = make_pelvis_ct(seed=scene.seed, voxel_mm=(ct_voxel_mm, ct_voxel_mm, ct_voxel_mm))
        write_ct_series(out / "ct", ct)
    (out / "fluoro").mkdir(exist_ok=True)
    if not cv2.imwrite(str(out / "camera.png"), scene.camera_image):
        raise CliError(f"could not write {out / 'camera.png'}")
    study, series = generate_uid(), generate_uid()
    for n, (name, view) in enumerate(scene.views.items(), start=1):
        a, b = scene.view_angles[name]
        write_xa(out / "fluoro" / f"{name}.dcm", scene.fluoro_log[name], primary_deg=a, secondary_deg=b,
                 source_to_detector_mm=PAPER_CARM["source_to_detector_mm"], source_to_isocenter_mm=PAPER_CARM["source_to_isocenter_mm"],
                 pixel_spacing_mm=PAPER_CARM["pixel_spacing_mm"], study_uid=study, series_uid=series, instance_number=n)
        write_projection(out / "fluoro" / f"{name}.json", view)
    write_camera_calibration(out / "camera.json", scene.calibrated_camera, rms_px=0.21, per_view_errors_px=[], label=f"twin seed {scene.seed}")
    write_drill_calibration(out / "drill.json", scene.calibrated_axis_drill, method="twin (true axis with calibration error)", residual_mm=0.1, residual_deg=0.12, label=f"twin seed {scene.seed}")
    write_marker_set(out / "markers.json", scene.marker_set)
    (out / "plan.json").write_text(json.dumps(plan_to_json(anatomy.CORRIDORS), indent=1))
    truth = truth_to_json(carm_from_drill=scene.carm_from_drill, carm_from_ct=scene.carm_from_ct, drill_axis_carm=scene.drill_axis_carm,
                          corridor_entry_carm_mm=scene.corridor_entry_carm_mm, carm_from_marker=scene.carm_from_marker, corridor=scene.corridor.name, seed=scene.seed)
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return {"write_s": time.perf_counter() - t0}


def _scene(args: argparse.Namespace) -> int:
    out = check_output_dir(args.out)
    ids = parse_ids(args.ids, default_marker_set()) if args.ids else None
    t0 = time.perf_counter()
    scene = make_scene(seed=args.seed, n_markers=args.markers, marker_ids=ids, views=args.views, corridor=args.corridor)
    t1 = time.perf_counter()
    if args.ct_voxel_mm is not None and not 0.3 <= args.ct_voxel_mm <= 4.0:
        raise CliError(f"--ct-voxel-mm must be 0.3..4 mm, got {args.ct_voxel_mm}")
    voxel = args.ct_voxel_mm if args.ct_voxel_mm is not None else (1.0 if args.ct else None)
    timings = write_scene(scene, out, ct_voxel_mm=voxel)
    print(f"wrote scene seed {args.seed} ({len(scene.carm_from_marker)} markers, views {', '.join(scene.views)}) to {out} in {t1 - t0 + timings['write_s']:.1f} s")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("sim", help="the digital twin")
    sub = p.add_subparsers(dest="sim_command", metavar="ACTION", required=True)
    s = sub.add_parser("scene", help="write one scene folder (camera frame, fluoroscopy DICOM, calibrations, markers, plan, truth)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--markers", type=int, default=5, help="number of markers (1-7)")
    s.add_argument("--ids", help="explicit marker ids instead, e.g. 0-4")
    s.add_argument("--views", default="inlet,outlet", help="comma list of ap, lateral, inlet, outlet, lao30, rao30 or PRIMARY:SECONDARY degrees")
    s.add_argument("--corridor", default="AIIS-PSIS", help="target corridor: " + ", ".join(c.name for c in anatomy.CORRIDORS))
    s.add_argument("--ct", action="store_true", help="also write the preoperative CT as a DICOM series in ct/ (1 mm voxels unless --ct-voxel-mm)")
    s.add_argument("--ct-voxel-mm", type=float, help="CT voxel size in mm (implies --ct)")
    s.add_argument("--out", required=True)
    s.set_defaults(func=_scene)
