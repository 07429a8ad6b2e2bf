"""Where the drill-axis error comes from: each input of a registration replaced by the twin's truth (issue 17).

For every registration of the accuracy study (``accuracy.py``: the same seeds, view pairs, drill poses, every
degradation and the real CT, M = 5, the product's joint solve with its tag recovery) the error at the corridor
entry is split into

- the **calibration part**: the drill axis that drill.json states against the true one, both carried by the true
  drill pose (no registration can remove it);
- the **pose part**: the true axis carried by the registered drill pose against the true pose,

and the pose part is measured again with the registration's inputs replaced by the twin's truth, one kind at a
time and then together (a diagnostic re-scoring, not something the product can do):

``corners``   the tags the product used, at their true corners (the true camera's projection of the printed tag);
``unscaled``  the detected corners less the offset along each tag's radii that the frame's tags share (measured
              against the truth: an exposure step or an over-exposed, blurred base moves every edge of a frame in);
``bbs``       every identified BB at the true projection of the as-built BB (the same correspondences);
``camera``    the true camera intrinsics and distortion instead of camera.json's;
``inputs``    all three;
``as_built``  all three, and the marker set as manufactured (BBs where manufacturing put them, 0.05 mm per
              axis) instead of markers.json's design;
``all``       and the views told they come from a flat panel (no intensifier distortion estimated).

and two a site can come near: ``measured``, the product's own detections and camera.json, with markers.json holding
each marker's BBs as built in the frame that best fits the design (what ``drillnav markers measure`` gives from
shots of the markers from several angles: X-ray does not show the BBs' common rigid displacement against the paper
tag), taken as perfectly measured (that command measures them to about 0.01 mm from six shots,
``tests/test_marker_as_built.py``); and ``built_rigid``, the same with that rigid displacement too.

What is left in ``all`` is the solve itself. Medians and 90th percentiles per setting, and per number of
markers the registration used, beside the reference's two-view median (0.9 mm). Ends with one JSON line.
Run: OPENBLAS_NUM_THREADS=1 nice .venv/bin/python benchmarks/error_sources.py [--seeds 6 --first-seed 7100 --views 2]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402
from accuracy import CT, _register, load_patient, study_scenes  # noqa: E402
from tag_detection import _true_corners  # noqa: E402

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA
from drillnav.registration.errors import DrillnavError
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.markers import MarkerSet
from drillnav.registration.transforms import apply
from drillnav.registration.video_fluoro import register_video_to_fluoro

SETTINGS = ("product", "measured", "built_rigid", "corners", "unscaled", "bbs", "camera", "inputs", "as_built", "all")
REFERENCE_TWO_VIEW_MM = 0.9


def _bb_rows(design: np.ndarray, used: np.ndarray) -> list[int]:
    """The rows of ``design`` (n, 3) that the observation's design centres ``used`` (k, 3) are."""
    return [int(np.argmin(np.linalg.norm(design - u, axis=1))) for u in used]


def _with_truth(pose, scene, *, as_built: bool, flat: bool, detected: bool = False, design_frame: bool = False):
    """A marker pose whose BB observations are the true projections of the as-built BBs (``detected``: the detected
    centres kept), and, ``as_built``, whose model BBs are the as-built ones (``design_frame``: in the frame that best
    fits the design); ``flat``, whose views state no intensifier distortion."""
    design = scene.marker_set.by_id(pose.marker_id).bb_centers_mm
    built = (scene.measured_marker_set().by_id(pose.marker_id) if design_frame else scene.manufactured[pose.marker_id]).bb_centers_mm
    obs = []
    for view, model, centres in pose.observations:
        rows = _bb_rows(design, model)
        seen = centres if detected else view.project(apply(scene.carm_from_marker[pose.marker_id], built[rows]))
        obs.append((replace(view, distortion_sigma_px=0.0) if flat else view, built[rows] if as_built else model, seen))
    return replace(pose, observations=tuple(obs))


def scene_rows(scene, dets: dict, frames: list, views: list[str]) -> list[dict]:
    """Every registration of one view set over the drill poses: the calibration part and each setting's pose part."""
    marker_poses = tuple(register_markers([dets[n] for n in views], [scene.views[n] for n in views], scene.marker_set))
    true_bbs = tuple(_with_truth(p, scene, as_built=False, flat=False) for p in marker_poses)
    built_bbs = tuple(_with_truth(p, scene, as_built=True, flat=False) for p in marker_poses)
    built_flat = tuple(_with_truth(p, scene, as_built=True, flat=True) for p in marker_poses)
    built_rigid = tuple(_with_truth(p, scene, as_built=True, flat=False, detected=True) for p in marker_poses)
    measured = tuple(_with_truth(p, scene, as_built=True, flat=False, detected=True, design_frame=True) for p in marker_poses)
    built_set = MarkerSet(markers=tuple(scene.manufactured[m.marker_id] for m in scene.marker_set.markers))
    measured_set = scene.measured_marker_set()
    entry = scene.corridor_entry_carm_mm
    true_axis = TRUE_DRILL_AXIS_CAMERA
    rows = []
    for pose, seen, image in frames:
        try:
            video, reg = _register(scene, image, seen, marker_poses, joint=True)
        except DrillnavError:
            continue
        truth = _true_corners(scene, pose) | _true_corners(scene, pose, partly=True)
        true_video = replace(video, markers=tuple(replace(m, corners_px=truth[m.marker_id]) for m in video.markers if m.marker_id in truth))
        radial = {i: (c - c.mean(axis=0)) / np.linalg.norm(c - c.mean(axis=0), axis=1)[:, None] for i, c in truth.items()}
        seen_true = [m for m in video.markers if m.marker_id in truth]
        shared = float(np.mean([np.sum((m.corners_px - truth[m.marker_id]) * radial[m.marker_id], axis=1).mean() for m in seen_true])) if seen_true else 0.0
        unscaled = replace(video, markers=tuple(replace(m, corners_px=m.corners_px - shared * radial[m.marker_id]) if m.marker_id in truth else m
                                                for m in video.markers))
        at_entry = true_axis.transformed(pose).closest_point(entry)

        def pose_part(carm_from_drill) -> float:
            return float(np.linalg.norm(true_axis.transformed(carm_from_drill).closest_point(entry) - at_entry))

        row = {"used": len(reg.used_ids), "views": len(views), "product": pose_part(reg.carm_from_drill),
               "calibration": float(np.linalg.norm(scene.calibrated_axis_drill.transformed(pose).closest_point(entry) - at_entry)),
               "total": float(np.linalg.norm(scene.calibrated_axis_drill.transformed(reg.carm_from_drill).closest_point(entry) - at_entry))}
        for name, v, m, ms, cam in (("measured", video, measured, measured_set, scene.calibrated_camera),
                                    ("built_rigid", video, built_rigid, built_set, scene.calibrated_camera),
                                    ("unscaled", unscaled, marker_poses, scene.marker_set, scene.calibrated_camera),
                                    ("corners", true_video, marker_poses, scene.marker_set, scene.calibrated_camera),
                                    ("bbs", video, true_bbs, scene.marker_set, scene.calibrated_camera),
                                    ("camera", video, marker_poses, scene.marker_set, scene.true_camera),
                                    ("inputs", true_video, true_bbs, scene.marker_set, scene.true_camera),
                                    ("as_built", true_video, built_bbs, built_set, scene.true_camera),
                                    ("all", true_video, built_flat, built_set, scene.true_camera)):
            try:
                row[name] = pose_part(register_video_to_fluoro(v, m, ms, cam, joint=True).carm_from_drill)
            except DrillnavError:
                row[name] = float("nan")
        rows.append(row)
    return rows


def run(*, seeds: int, first_seed: int, poses: int, n_views: int) -> list[dict]:
    deg = Degradations.parse("all")
    patient = load_patient(CT)
    rows = []
    for seed, pair, scene, dets, frames in study_scenes(seeds=seeds, first_seed=first_seed, poses=poses, degradations=deg, patient=patient):
        names = list(scene.views)
        for vs in ([names] if n_views == 2 else [[n] for n in names]):
            rows += [{"seed": seed, "pair": pair, **r} for r in scene_rows(scene, dets, frames, vs)]
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--first-seed", type=int, default=7100, help="unseen by the tests")
    ap.add_argument("--poses", type=int, default=2)
    ap.add_argument("--views", type=int, choices=(1, 2), default=2, help="register with both views of each pair, or each view alone")
    args = ap.parse_args()
    rows = run(seeds=args.seeds, first_seed=args.first_seed, poses=args.poses, n_views=args.views)
    if not rows:
        raise SystemExit("no registration: nothing to split")
    groups = {"every": rows, "1-2 markers": [r for r in rows if r["used"] <= 2], "3-5 markers": [r for r in rows if r["used"] >= 3]}
    print(f"\n{args.views} view(s), seeds {args.first_seed}-{args.first_seed + args.seeds - 1}: the error at the entry (total), its calibration part, "
          "and its pose part with each setting's inputs; mm, median / p90")
    print(f"| setting | {' | '.join(f'{g} (n = {len(rs)})' for g, rs in groups.items())} |")
    print("|---|" + "---|" * len(groups))
    figures = []
    for name in ("total", "calibration", *SETTINGS):
        cells = []
        for g, rs in groups.items():
            v = np.array([r[name] for r in rs], dtype=float)
            v = v[np.isfinite(v)]
            cells.append(f"{np.median(v):.2f} / {np.percentile(v, 90):.2f}" if len(v) else "-")
            if len(v) and g == "every":
                figures.append(figure(f"{args.views}v {name} median", float(np.median(v)), "mm", REFERENCE_TWO_VIEW_MM if args.views == 2 else None))
        print(f"| {name} | {' | '.join(cells)} |")
    report("error_sources", figures, seeds=args.seeds, first_seed=args.first_seed, poses=args.poses, views=args.views, registrations=len(rows))


if __name__ == "__main__":
    main()
