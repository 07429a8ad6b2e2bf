"""How large is each measurement error, and how much of it is common to a tag's corners or a marker's BBs? (issue 17)

The joint solve's noise model is what its predicted error can know about. This measures, on the twin, the
detections against the truth and splits each group's error into a part common to the group and the rest:

camera
    every tag's 4 detected corners against the true camera's projection of the tag's true corners (true
    drill pose, true intrinsics): per tag a common shift (the mean of the 4 errors, per image axis), a common
    scale (the errors' component along each corner's radius from the tag centre, averaged) and the
    independent remainder (RMS per coordinate, with the 3 fitted degrees of freedom taken out of the 8); the
    tags' shifts and scales further split into the part common to every tag of the frame and each tag's own;
    and each tag's shape modes (a scale, a turn and two stretches about its centre, px at its half-diagonal:
    :func:`shape_modes`) averaged over the frame's tags, against the RMS of their edge-stated noise
    (``VideoMarker.edge_sigma_px``): what the joint solve's ``frame_corner_sigma_px`` states.
fluoroscopy
    every identified BB's centre against the true view's projection of the design BB at the marker's true pose,
    split into the manufacturing part (the as-built BB's projection minus the design's: the same 3D error in
    every view) and the detection part (detected minus the as-built BB's projection); the detection part per
    (marker, view) into a common shift, a common scale and the independent remainder as for the corners.

Per degradation setting given (``--settings``, each a Degradations.parse text), RMS over all groups.
``--camera-size WxH`` measures the drill camera's part at another frame size (the degradations keep their sizes in
pixels, as the study's ``--camera-size`` draws them).
Run: nice -n 10 .venv/bin/python benchmarks/noise_decomposition.py [--seeds 4 --first-seed 9100] [--camera-size 640x480]
Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import CT, load_patient  # noqa: E402  (the study's patient)

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import make_scene, render_fluoro
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.joint_solve import frame_shape_modes
from drillnav.registration.transforms import apply, invert
from drillnav.registration.video_markers import VideoMarkerLocator

# A detection farther than this from the truth is a mismatch (wrong BB, wrong marker), not noise: left out.
MISMATCH_PX = 4.0


def split(err: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """A group's errors (N, 2) at image points (N, 2): common shift (2,), common scale (px at the group's mean
    radius), the independent remainder (N, 2)."""
    shift = err.mean(axis=0)
    rel = pts - pts.mean(axis=0)
    radius = np.linalg.norm(rel, axis=1)
    e = err - shift
    # Least squares of e ~ s * rel (a common scale about the centre), reported at the mean radius.
    s = float(np.sum(e * rel) / max(np.sum(rel * rel), 1e-12))
    rest = e - s * rel
    return shift, s * float(radius.mean()), rest


def shape_modes(err: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """A tag's corner errors (4, 2) at its corners (4, 2) as a scale, a turn and two stretches about its centre (4,),
    px at its half-diagonal (RMS distance of its corners from their centre), after a common shift; least squares."""
    basis = frame_shape_modes([pts]).reshape(-1, 4)  # the joint solve's own
    coef, *_ = np.linalg.lstsq(basis, (err - err.mean(axis=0)).ravel(), rcond=None)
    return coef


def camera_errors(scene, rng_seed, poses: int) -> dict[str, list]:
    locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)
    pose_rng, camera_rng = np.random.default_rng([rng_seed, 2]), np.random.default_rng([rng_seed, 3])
    out = {"shift": [], "scale": [], "rest": [], "dof": [], "frame_shift": [], "frame_scale": [], "tag_shift": [], "tag_scale": [],
           "frame_modes": [], "frame_edge_sigma": []}
    for _ in range(poses):
        carm_from_drill = scene.drill_pose_towards(pose_rng, offset_mm=5.0, tilt_deg=5.0)
        seen = locator.locate(scene.render_camera(camera_rng, carm_from_drill=carm_from_drill))
        drill_from_carm = invert(carm_from_drill)
        shifts, scales, modes, edges = [], [], [], []
        for v in seen.markers:
            design = scene.marker_set.by_id(v.marker_id)
            truth = scene.true_camera.project(apply(drill_from_carm @ scene.carm_from_marker[v.marker_id], design.tag_corners_mm()))
            err = np.asarray(v.corners_px) - truth
            if np.max(np.linalg.norm(err, axis=1)) > MISMATCH_PX:
                continue
            shift, scale, rest = split(err, truth)
            out["shift"].append(shift)
            out["scale"].append(scale)
            out["rest"].append(rest.ravel())
            out["dof"].append(8 - 3)
            shifts.append(shift)
            scales.append(scale)
            modes.append(shape_modes(err, truth))
            if v.edge_sigma_px > 0:
                edges.append(v.edge_sigma_px)
        if len(modes) >= 2 and edges:
            out["frame_modes"].append(np.mean(modes, axis=0))
            out["frame_edge_sigma"].append(float(np.sqrt(np.mean(np.square(edges)))))
        if len(shifts) >= 2:
            # The part common to every tag of the frame (one exposure, one blur kernel) and each tag's own.
            out["frame_shift"].append(np.mean(shifts, axis=0))
            out["frame_scale"].append(float(np.mean(scales)))
            out["tag_shift"] += list(np.asarray(shifts) - np.mean(shifts, axis=0))
            out["tag_scale"] += list(np.asarray(scales) - np.mean(scales))
    return out


def fluoro_errors(scene, rng_seed) -> dict[str, list]:
    image_rng = np.random.default_rng([rng_seed, 1])
    out = {"shift": [], "scale": [], "rest": [], "dof": [], "manufacturing": [], "mfg_shift": []}
    for name, view in scene.views.items():
        dets = detect_in_view(render_fluoro(scene, name, image_rng), scene.views[name], scene.marker_set)
        for m in dets.markers:
            if m.marker_id not in scene.carm_from_marker:
                continue
            keep = np.asarray(m.bb_index) >= 0
            if keep.sum() < 4:
                continue
            idx = np.asarray(m.bb_index)[keep]
            px = np.array([b.center_px for b in m.bbs])[keep]
            pose = scene.carm_from_marker[m.marker_id]
            design = view.project(apply(pose, scene.marker_set.by_id(m.marker_id).bb_centers_mm[idx]))
            built = view.project(apply(pose, scene.manufactured[m.marker_id].bb_centers_mm[idx]))
            err = px - built
            ok = np.linalg.norm(px - design, axis=1) <= MISMATCH_PX
            if ok.sum() < 4:
                continue
            shift, scale, rest = split(err[ok], built[ok])
            out["shift"].append(shift)
            out["scale"].append(scale)
            out["rest"].append(rest.ravel())
            out["dof"].append(2 * int(ok.sum()) - 3)
            mfg = (built - design)[ok]
            out["manufacturing"].append(mfg.ravel())
            out["mfg_shift"].append(mfg.mean(axis=0))
    return out


def summary(d: dict[str, list]) -> dict[str, float]:
    if not d["shift"]:
        return {"groups": 0}
    rest = np.concatenate(d["rest"])
    res = {
        "groups": len(d["shift"]),
        "common_shift_px_rms_per_axis": float(np.sqrt(np.mean(np.square(d["shift"])))),
        "common_scale_px_rms": float(np.sqrt(np.mean(np.square(d["scale"])))),
        # Each group's remainder has lost 3 of its 2N degrees of freedom to the fitted shift and scale.
        "independent_px_rms_per_coord": float(np.sqrt(np.sum(rest**2) / max(1, sum(d["dof"])))),
    }
    if d.get("frame_shift"):
        res["frame_shift_px_rms_per_axis"] = float(np.sqrt(np.mean(np.square(d["frame_shift"]))))
        res["frame_scale_px_rms"] = float(np.sqrt(np.mean(np.square(d["frame_scale"]))))
        res["tag_shift_within_frame_px_rms_per_axis"] = float(np.sqrt(np.mean(np.square(d["tag_shift"]))))
        res["tag_scale_within_frame_px_rms"] = float(np.sqrt(np.mean(np.square(d["tag_scale"]))))
    if d.get("frame_modes"):
        # Scale, turn, stretch, stretch (px at each tag's half-diagonal), the frame's mean over its tags; and the RMS of
        # the frame's tags' edge-stated noise, to which the joint solve ties them (FRAME_CORNER_PER_EDGE_SIGMA).
        res["frame_shape_modes_px_rms"] = np.sqrt(np.mean(np.square(d["frame_modes"]), axis=0)).round(4).tolist()
        res["frame_edge_sigma_px_rms"] = float(np.sqrt(np.mean(np.square(d["frame_edge_sigma"]))))
    if "manufacturing" in d and d["manufacturing"]:
        res["manufacturing_px_rms_per_coord"] = float(np.sqrt(np.mean(np.concatenate(d["manufacturing"]) ** 2)))
        res["manufacturing_shift_px_rms_per_axis"] = float(np.sqrt(np.mean(np.square(d["mfg_shift"]))))
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=9100, help="unseen by the tests and the accuracy study")
    ap.add_argument("--poses", type=int, default=3, help="camera frames per scene")
    ap.add_argument("--settings", default="none;motion_blur;defocus;mjpeg;tag_glare;glove;blood;colour;auto_exposure;"
                    "motion_blur,defocus,tag_glare,glove,blood,mjpeg,colour,auto_exposure;low_dose;ii_distortion;hardware;"
                    "low_dose,hardware,collimator,ii_distortion",
                    help="';'-separated degradation settings (each as --degradations of the study)")
    ap.add_argument("--views", default="inlet,outlet")
    ap.add_argument("--ct", type=Path, default=CT)
    ap.add_argument("--camera-size", default="1280x720", help="the drill camera's frame, WIDTHxHEIGHT px (as the study's --camera-size)")
    args = ap.parse_args()
    try:
        camera_size = tuple(int(v) for v in args.camera_size.lower().split("x"))
    except ValueError:
        camera_size = ()
    if len(camera_size) != 2 or min(camera_size) < 160:
        ap.error(f"--camera-size must be WIDTHxHEIGHT px, each at least 160, got {args.camera_size!r}")
    t0 = time.time()
    patient = None
    results = {}
    for text in args.settings.split(";"):
        deg = Degradations.parse(text)
        if deg.ct_anatomy and patient is None:
            patient = load_patient(args.ct)
        cam: dict[str, list] = {"shift": [], "scale": [], "rest": [], "dof": [], "frame_shift": [], "frame_scale": [], "tag_shift": [], "tag_scale": [],
                                "frame_modes": [], "frame_edge_sigma": []}
        flu: dict[str, list] = {"shift": [], "scale": [], "rest": [], "dof": [], "manufacturing": [], "mfg_shift": []}
        xray = any(getattr(deg, n) for n in ("low_dose", "ct_anatomy", "hardware", "collimator", "ii_distortion"))
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            scene = make_scene(seed=seed, views=args.views, render=False, degradations=deg, voxel_anatomy=patient if deg.ct_anatomy else None,
                               image_size=camera_size)
            if deg.camera or not xray:
                for k, v in camera_errors(scene, seed, args.poses).items():
                    cam[k] += v
            if xray or not deg.camera:
                for k, v in fluoro_errors(scene, seed).items():
                    flu[k] += v
        results[deg.label()] = {"camera": summary(cam), "fluoro": summary(flu)}
        c, f = results[deg.label()]["camera"], results[deg.label()]["fluoro"]
        fmt = lambda s: ("-" if not s.get("groups") else  # noqa: E731
                         f"{s['groups']:4d} groups: shift {s['common_shift_px_rms_per_axis']:.3f}, scale {s['common_scale_px_rms']:.3f}, "
                         f"independent {s['independent_px_rms_per_coord']:.3f}"
                         + (f", manufacturing {s['manufacturing_px_rms_per_coord']:.3f}" if "manufacturing_px_rms_per_coord" in s else "")
                         + (f"; of which common to the frame: shift {s['frame_shift_px_rms_per_axis']:.3f}, scale {s['frame_scale_px_rms']:.3f}"
                            if "frame_shift_px_rms_per_axis" in s else "")
                         + (f"; the frame's shape modes (scale, turn, stretches) {' / '.join(f'{v:.3f}' for v in s['frame_shape_modes_px_rms'])} "
                            f"against its tags' edge-stated {s['frame_edge_sigma_px_rms']:.3f}" if "frame_shape_modes_px_rms" in s else ""))
        print(f"{deg.label():60s} camera  {fmt(c)}\n{'':60s} fluoro  {fmt(f)}", flush=True)
    print(f"seeds {args.first_seed}-{args.first_seed + args.seeds - 1}, {args.poses} camera frames per scene, views {args.views}, "
          f"camera {camera_size[0]}x{camera_size[1]}; {time.time() - t0:.0f} s")
    print(json.dumps({"first_seed": args.first_seed, "seeds": args.seeds, "camera_size": list(camera_size), "results": results}))


if __name__ == "__main__":
    main()
