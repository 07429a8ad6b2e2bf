"""``drillnav sim scene``: write one digital-twin scene folder that the other commands take as it is."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

from .cli import CliError
from .outputs import check_output_dir

if TYPE_CHECKING:
    from drillnav.drivers.sim import anatomy
    from drillnav.drivers.sim.scene import Scene

# The twin's libraries (scipy, pydicom, the renderers) are imported by the functions that use them, not on import:
# ``drillnav sim --help`` stays instant.

__all__ = ["register", "write_scene"]


def write_scene(scene: Scene, out: Path, *, ct_voxel_mm: float | None = None, plan_doc: dict | None = None) -> dict[str, float]:
    """Write every file of the scene folder; returns timings in s.

    ``ct/`` holds the CT the product is handed: for the analytic pelvis when
    ``ct_voxel_mm`` is given (voxel size), for a real-CT anatomy always (its
    in-plane voxels scaled by ``ct_voxel_mm`` / the truth's, at least 1.25x).
    ``plan_doc`` replaces the plan.json made from the scene's corridors.
    """
    import cv2
    import numpy as np
    from pydicom.uid import generate_uid

    from drillnav.drivers.sim import anatomy
    from drillnav.drivers.sim.ct_anatomy import handed_copy
    from drillnav.drivers.sim.ct_phantom import make_pelvis_ct
    from drillnav.drivers.sim.dicom_io import write_ct_series, write_xa
    from drillnav.drivers.sim.scene import AXIS_CALIBRATION_UNCERTAINTY, PAPER_CARM
    from drillnav.schemas.calibration import write_camera_calibration, write_drill_calibration
    from drillnav.schemas.markers import write_marker_set
    from drillnav.schemas.projection import write_projection
    from drillnav.schemas.scene_files import plan_to_json, truth_to_json

    t0 = time.perf_counter()
    patient = scene.voxel_anatomy
    if patient is not None:
        truth_mm = float(np.min(patient.volume.spacing_mm[:2]))
        scale = max(1.25, (ct_voxel_mm or 0.0) / truth_mm)
        write_ct_series(out / "ct", handed_copy(patient.volume, seed=scene.seed, voxel_scale=scale), patient_id="TWIN-CT", series_description="twin copy of a real CT")
    elif ct_voxel_mm is not None:
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
                 pixel_spacing_mm=PAPER_CARM["pixel_spacing_mm"], study_uid=study, series_uid=series, instance_number=n,
                 image_intensifier=scene.degradations.ii_distortion)
        write_projection(out / "fluoro" / f"{name}.json", view)
    write_camera_calibration(out / "camera.json", scene.calibrated_camera, rms_px=0.21, per_view_errors_px=[], label=f"twin seed {scene.seed}")
    write_drill_calibration(out / "drill.json", scene.calibrated_axis_drill, method="twin (true axis with calibration error)", residual_mm=AXIS_CALIBRATION_UNCERTAINTY.sigma_mm,
                            residual_deg=AXIS_CALIBRATION_UNCERTAINTY.rms_tilt_deg, label=f"twin seed {scene.seed}")
    write_marker_set(out / "markers.json", scene.marker_set)
    if plan_doc is None:
        plan_doc = plan_to_json((patient.corridor,) if patient is not None else anatomy.CORRIDORS)
    (out / "plan.json").write_text(json.dumps(plan_doc, indent=1))
    truth = truth_to_json(carm_from_drill=scene.carm_from_drill, carm_from_ct=scene.carm_from_ct, drill_axis_carm=scene.drill_axis_carm,
                          corridor_entry_carm_mm=scene.corridor_entry_carm_mm, carm_from_marker=scene.carm_from_marker, corridor=scene.corridor.name, seed=scene.seed)
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return {"write_s": time.perf_counter() - t0}


def _point(text: str, option: str) -> tuple[float, float, float]:
    import numpy as np

    try:
        p = tuple(float(v) for v in text.split(","))
    except ValueError:
        p = ()
    if len(p) != 3 or not all(np.isfinite(p)):
        raise CliError(f"{option} must be X,Y,Z in mm (CT patient coordinates), got '{text}'")
    return p  # type: ignore[return-value]


def _trajectory(args: argparse.Namespace) -> tuple[anatomy.Corridor, dict | None]:
    """The real-CT anatomy's trajectory: --entry/--target, or one from --plan (by --corridor name, else the first),
    with the plan to write (that trajectory, its acceptance volume's path made absolute)."""
    from drillnav.drivers.sim import anatomy
    from drillnav.schemas.scene_files import plan_to_json

    from .ct_mode import load_plan

    if (args.entry is None) != (args.target is None):
        raise CliError("--entry and --target go together")
    if args.entry is not None:
        if args.plan:
            raise CliError("give either --plan or --entry/--target, not both")
        return anatomy.Corridor(name="planned", entry_mm=_point(args.entry, "--entry"), target_mm=_point(args.target, "--target"), radius_mm=3.5), None
    if not args.plan:
        raise CliError("--anatomy needs the planned trajectory: --plan plan.json or --entry X,Y,Z --target X,Y,Z (CT patient mm)")
    plan = load_plan(args.plan)
    chosen = [p for p in plan if args.corridor in (None, p.trajectory.name)]
    if not chosen:
        raise CliError(f"{args.plan} has no trajectory '{args.corridor}': it has {', '.join(p.trajectory.name for p in plan)}")
    t = chosen[0].trajectory
    corridor = anatomy.Corridor(name=t.name, entry_mm=tuple(map(float, t.entry_mm)), target_mm=tuple(map(float, t.target_mm)), radius_mm=t.radius_mm)
    doc = plan_to_json([corridor])
    doc["trajectories"][0]["acceptance"] = chosen[0].acceptance  # load_plan made a label path absolute
    return corridor, doc


def _scene(args: argparse.Namespace) -> int:
    from drillnav.drivers.ct_volume import read_ct
    from drillnav.drivers.sim.ct_anatomy import VoxelAnatomy
    from drillnav.drivers.sim.scene import make_scene
    from drillnav.registration.markers import default_marker_set

    from .cli_markers import parse_ids

    out = check_output_dir(args.out)
    ids = parse_ids(args.ids, default_marker_set()) if args.ids else None
    if args.ct_voxel_mm is not None and not 0.3 <= args.ct_voxel_mm <= 4.0:
        raise CliError(f"--ct-voxel-mm must be 0.3..4 mm, got {args.ct_voxel_mm}")
    t0 = time.perf_counter()
    patient, plan_doc = None, None
    if args.anatomy:
        corridor_ct, plan_doc = _trajectory(args)
        patient = VoxelAnatomy.from_volume(read_ct(args.anatomy), corridor=corridor_ct)
    elif args.plan or args.entry or args.target:
        raise CliError("--plan, --entry and --target choose the trajectory in a real CT: they need --anatomy")
    corridor = args.corridor or "AIIS-PSIS"
    scene = make_scene(seed=args.seed, n_markers=args.markers, marker_ids=ids, views=args.views, corridor=corridor,
                       kwire=not args.no_kwire, voxel_anatomy=patient)
    t1 = time.perf_counter()
    voxel = args.ct_voxel_mm if args.ct_voxel_mm is not None else (1.0 if args.ct else None)
    timings = write_scene(scene, out, ct_voxel_mm=voxel, plan_doc=plan_doc)
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
    s.add_argument("--corridor", help="target corridor of the twin's pelvis, e.g. AIIS-PSIS (the default; an unknown name lists them); with --anatomy --plan, a trajectory's name in the plan")
    s.add_argument("--ct", action="store_true", help="also write the preoperative CT as a DICOM series in ct/ (1 mm voxels unless --ct-voxel-mm)")
    s.add_argument("--ct-voxel-mm", type=float, help="CT voxel size in mm (implies --ct)")
    s.add_argument("--anatomy", metavar="CT", help="a real CT (DICOM folder or .nii/.nii.gz) as the patient instead of the analytic pelvis; ct/ gets a resampled, noisier copy")
    s.add_argument("--plan", help="with --anatomy: plan.json whose trajectory the drill aims along")
    s.add_argument("--entry", metavar="X,Y,Z", help="with --anatomy: planned entry in CT patient coordinates (mm)")
    s.add_argument("--target", metavar="X,Y,Z", help="with --anatomy: planned target in CT patient coordinates (mm)")
    s.add_argument("--no-kwire", action="store_true", help="no K-wire in the drill (it shows in the fluoroscopy otherwise)")
    s.add_argument("--out", required=True)
    s.set_defaults(func=_scene)
