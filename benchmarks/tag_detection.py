"""Share of visible tags the drill camera's detector finds, per operating-room degradation (issue 17).

For each seed and drill pose the twin renders one frame per camera degradation
(each alone, then all, then none), and ``VideoMarkerLocator`` looks for the
scene's tags. A tag counts as visible when its four true corners project inside
the frame (a glove over a corner still counts: a tag the detector cannot decode
is a miss, not an excuse). Also measured: false ids (ids found that are not in
the scene, or not visible), the RMS corner error of found tags against the true
projection, and the locator's time per frame. Tag-free frames (the drape only,
every degradation) are checked for false ids too.

Tags the detector misses are then looked for where they are predicted (``VideoMarkerLocator.recover``, the
product's recovery, :mod:`drillnav.registration.tag_recovery`): here predicted from the true drill pose and the
marker's true pose through the CALIBRATED camera (its calibration error is in the prediction; the registration's
own error is not: ``benchmarks/accuracy.py --diagnose --per-degradation`` measures recovery from the product's
registration). Reported: tags recovered, false recoveries (a corner over 3 px from the truth) and the recovered
corners' RMS error. Every marker's tag is placed where the same pose puts it (``recover(placed_px=..., by_place=True)``,
as the product passes a settled registration's): a tag of the set placed away from a missed one is no rival to its
identity, and a tag found where predicted (or, in the 10-22 px column, within the reach) is named by its place when
no other placed marker can be there.

The missed tags are also searched for with no prediction (``VideoMarkerLocator.search``,
:mod:`drillnav.registration.tag_search`: what a frame that shares no marker with fluoroscopy gets): tags found,
false ones, their corners' RMS error and the search's time per frame; the search reads a tag cut by the frame's edge
on what of it is in the frame, so such a tag found by it is scored against its true corners, not counted false.
And tags cut by the frame's edge (at least 60 % of their area in it), which ArUco never finds, looked for where they
are predicted (on what of them is in the frame): tags recovered, false ones, and their corners' RMS error, the
corners outside the frame included. Markers placed as a surgeon places them (``--conditions surgeon_markers``)
spread wider than the camera's field. Last, the
missed tags predicted 10-22 px off (a random direction), as a registration on one or two markers predicts them, looked
for within its reach (``recover(reach_px=pipeline.WEAK_REACH_PX)``, every marker's tag placed as its own moved
prediction puts it): tags recovered, false ones, their corners' RMS error and the time per frame.

    .venv/bin/python benchmarks/tag_detection.py --seeds 3 --poses 4
    .venv/bin/python benchmarks/tag_detection.py --seeds 31 --poses 3 --first-seed 5000 --conditions surgeon_markers

Prints a table and one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from drillnav.drivers.sim.degradations import CAMERA, Degradations
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.pipeline import WEAK_REACH_PX
from drillnav.registration.tag_recovery import MIN_SHARE_IN_FRAME, predict_tag_corners, share_in_frame
from drillnav.registration.transforms import apply
from drillnav.registration.video_markers import VideoMarkerLocator


def _true_corners(scene, carm_from_drill, *, partly: bool = False) -> dict[int, np.ndarray]:
    """Marker id -> (4, 2) true tag corners (OpenCV order) for the tags fully inside the frame (``partly``: instead
    those cut by the frame's edge with at least ``MIN_SHARE_IN_FRAME`` of their area in it)."""
    cam = scene.true_camera
    out = {}
    for marker_id, pose in scene.camera_from_marker(carm_from_drill).items():
        pts = apply(pose, scene.manufactured[marker_id].tag_corners_mm())
        if np.any(pts[:, 2] <= 1.0):
            continue
        px = cam.project(pts)
        whole = np.all((px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height))
        if whole != partly and (not partly or share_in_frame(px, width=cam.width, height=cam.height) >= MIN_SHARE_IN_FRAME):
            out[marker_id] = px
    return out


def _score_recovered(video, truth: dict[int, np.ndarray], row: dict, name: str) -> None:
    """Count ``video``'s recovered markers into ``row[name]`` (within 3 px of the truth at every corner, their squared
    corner errors into ``row["sq_err_" + name]``) or ``row[name + "_false"]``."""
    for m in video.markers:
        if not m.recovered:
            continue
        err = np.linalg.norm(m.corners_px - truth[m.marker_id], axis=1) if m.marker_id in truth else np.array([np.inf])
        if err.max() > 3.0:
            row[f"{name}_false"] += 1
            continue
        row[name] += 1
        row[f"sq_err_{name}"] += float(np.sum(err**2))


def measure(*, seeds: int = 3, poses: int = 4, first_seed: int = 3000, conditions: list[str] | None = None) -> dict[str, dict]:
    """condition -> {visible, found, false_ids, corner_rms_px, ms_per_frame, recovered, recovered_false, recovered_corner_rms_px}
    summed over seeds x poses."""
    conditions = conditions if conditions is not None else ["none", *CAMERA, "all"]
    rows = {c: {"visible": 0, "found": 0, "false_ids": 0, "sq_err": 0.0, "n_corners": 0, "seconds": 0.0, "frames": 0,
                 "recovered": 0, "recovered_false": 0, "sq_err_recovered": 0.0,
                 "searched": 0, "searched_false": 0, "sq_err_searched": 0.0, "search_seconds": 0.0,
                 "partly_visible": 0, "partly": 0, "partly_false": 0, "sq_err_partly": 0.0,
                 "reached": 0, "reached_false": 0, "sq_err_reached": 0.0, "reach_seconds": 0.0} for c in conditions}
    for seed in range(first_seed, first_seed + seeds):
        for cond in conditions:
            # "all": every camera degradation (the fluoroscopy ones do not touch the camera frame).
            # "all": every camera degradation; "a+b": several settings at once (e.g. all+surgeon_markers).
            deg = Degradations.parse(",".join(n for part in cond.split("+") for n in (CAMERA if part == "all" else [part])))
            scene = make_scene(seed=seed, render=False, degradations=deg)
            locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)
            pose_rng, camera_rng = np.random.default_rng([seed, 2]), np.random.default_rng([seed, 3])
            for _ in range(poses):
                pose = scene.drill_pose_towards(pose_rng, offset_mm=5.0, tilt_deg=5.0)
                frame = scene.render_camera(camera_rng, carm_from_drill=pose)
                truth = _true_corners(scene, pose)
                t0 = time.perf_counter()
                det = locator.locate(frame)
                r = rows[cond]
                r["seconds"] += time.perf_counter() - t0
                r["frames"] += 1
                r["visible"] += len(truth)
                for m in det.markers:
                    if m.marker_id not in truth:
                        r["false_ids"] += 1
                        continue
                    r["found"] += 1
                    r["sq_err"] += float(np.sum((m.corners_px - truth[m.marker_id]) ** 2))
                    r["n_corners"] += 4
                r["false_ids"] += len(det.ignored_ids)
                missed = {i: c for i, c in truth.items() if i not in det.by_id()}
                expected = {i: predict_tag_corners(carm_from_drill=pose, carm_from_marker=scene.carm_from_marker[i],
                                                   tag_corners_marker_mm=scene.marker_set.by_id(i).tag_corners_mm(), camera=scene.calibrated_camera)
                            for i in missed}
                t0 = time.perf_counter()
                searched = locator.search(frame, det, scene.marker_set.ids)
                r["search_seconds"] += time.perf_counter() - t0
                # Tags cut by the frame's edge (ArUco never finds them): the search reads them on what is in the frame, and
                # the recovery looks for them where they are predicted.
                cut = _true_corners(scene, pose, partly=True)
                _score_recovered(searched, {**truth, **cut}, r, "searched")
                r["partly_visible"] += len(cut)
                predicted_cut = {i: predict_tag_corners(carm_from_drill=pose, carm_from_marker=scene.carm_from_marker[i],
                                                        tag_corners_marker_mm=scene.marker_set.by_id(i).tag_corners_mm(), camera=scene.calibrated_camera)
                                 for i in cut}
                # Where the registration puts every marker's tag (the product's placed_px): a tag placed away from a missed
                # one is no rival to its identity.
                places = {i: predict_tag_corners(carm_from_drill=pose, carm_from_marker=scene.carm_from_marker[i],
                                                 tag_corners_marker_mm=scene.marker_set.by_id(i).tag_corners_mm(), camera=scene.calibrated_camera)
                          for i in scene.carm_from_marker}
                placed = {i: np.zeros((0, 4, 2)) if c is None else c[None] for i, c in places.items()}
                _score_recovered(locator.recover(frame, det, {i: c for i, c in predicted_cut.items() if c is not None}, placed_px=placed, by_place=True),
                                 cut, r, "partly")
                _score_recovered(locator.recover(frame, det, {i: c for i, c in expected.items() if c is not None}, placed_px=placed, by_place=True),
                                 truth, r, "recovered")
                # The same tags predicted 10-22 px off, as a registration on one or two markers predicts them, looked for
                # within the weak registration's reach (pipeline.WEAK_REACH_PX).
                off_rng = np.random.default_rng([seed, r["frames"], 4])
                moved = {}
                for i, c in places.items():
                    if c is not None:
                        angle, length = off_rng.uniform(0, 2 * np.pi), off_rng.uniform(10.0, 22.0)
                        moved[i] = c + length * np.array([np.cos(angle), np.sin(angle)])
                shifted = {i: moved[i] for i, c in expected.items() if c is not None}
                placed_moved = {i: moved[i][None] if i in moved else np.zeros((0, 4, 2)) for i in places}
                t0 = time.perf_counter()
                _score_recovered(locator.recover(frame, det, shifted, reach_px=WEAK_REACH_PX, placed_px=placed_moved, by_place=True), truth, r, "reached")
                r["reach_seconds"] += time.perf_counter() - t0
    out = {}
    for c, r in rows.items():
        out[c] = {
            "visible": r["visible"], "found": r["found"], "found_share": r["found"] / max(r["visible"], 1),
            "false_ids": r["false_ids"], "corner_rms_px": float(np.sqrt(r["sq_err"] / max(r["n_corners"], 1))),
            "ms_per_frame": 1000.0 * r["seconds"] / max(r["frames"], 1),
            "recovered": r["recovered"], "recovered_false": r["recovered_false"],
            "recovered_corner_rms_px": float(np.sqrt(r["sq_err_recovered"] / max(4 * r["recovered"], 1))),
            "searched": r["searched"], "searched_false": r["searched_false"],
            "searched_corner_rms_px": float(np.sqrt(r["sq_err_searched"] / max(4 * r["searched"], 1))),
            "search_ms_per_frame": 1000.0 * r["search_seconds"] / max(r["frames"], 1),
            "partly_visible": r["partly_visible"], "partly_recovered": r["partly"], "partly_false": r["partly_false"],
            "partly_corner_rms_px": float(np.sqrt(r["sq_err_partly"] / max(4 * r["partly"], 1))),
            "reached": r["reached"], "reached_false": r["reached_false"],
            "reached_corner_rms_px": float(np.sqrt(r["sq_err_reached"] / max(4 * r["reached"], 1))),
            "reach_ms_per_frame": 1000.0 * r["reach_seconds"] / max(r["frames"], 1),
        }
    return out


def false_ids_without_tags(*, seeds: int = 3, first_seed: int = 3000) -> int:
    """Ids found on frames with no tag at all (the drape, every camera degradation on)."""
    count = 0
    for seed in range(first_seed, first_seed + seeds):
        scene = make_scene(seed=seed, render=False, degradations=Degradations.parse(",".join(CAMERA)))
        locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=range(250))
        rng = np.random.default_rng([seed, 4])
        pose = scene.drill_pose_towards(rng)
        away = pose.copy()
        away[:3, 3] += 5000.0 * pose[:3, 2]  # far past the markers: every tag behind the camera or out of frame
        frame = scene.render_camera(rng, carm_from_drill=away)
        det = locator.locate(frame)
        count += len(det.markers) + len(det.ignored_ids)
    return count


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--poses", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=3000)
    ap.add_argument("--conditions", default=None, help="comma-separated: none, all (every camera degradation) or degradation names, "
                    "'+' joining several (all+surgeon_markers); default: none, each camera degradation alone, all")
    args = ap.parse_args()
    res = measure(seeds=args.seeds, poses=args.poses, first_seed=args.first_seed, conditions=args.conditions.split(",") if args.conditions else None)
    print(f"{'condition':<14} {'visible':>7} {'found':>6} {'share':>6} {'false':>5} {'corner rms px':>13} {'ms/frame':>8} "
          f"{'recovered':>9} {'false':>5} {'rms px':>6} {'searched':>8} {'false':>5} {'rms px':>6} {'ms':>5} {'cut by edge':>11} {'recovered':>9} "
          f"{'false':>5} {'rms px':>6} {'10-22 px off':>12} {'false':>5} {'rms px':>6} {'ms':>5}")
    for c, r in res.items():
        print(f"{c:<14} {r['visible']:>7} {r['found']:>6} {r['found_share']:>6.1%} {r['false_ids']:>5} {r['corner_rms_px']:>13.3f} {r['ms_per_frame']:>8.1f} "
              f"{r['recovered']:>9} {r['recovered_false']:>5} {r['recovered_corner_rms_px']:>6.3f} "
              f"{r['searched']:>8} {r['searched_false']:>5} {r['searched_corner_rms_px']:>6.3f} {r['search_ms_per_frame']:>5.1f} "
              f"{r['partly_visible']:>11} {r['partly_recovered']:>9} {r['partly_false']:>5} {r['partly_corner_rms_px']:>6.3f} "
              f"{r['reached']:>12} {r['reached_false']:>5} {r['reached_corner_rms_px']:>6.3f} {r['reach_ms_per_frame']:>5.1f}")
    empty = false_ids_without_tags(seeds=args.seeds, first_seed=args.first_seed)
    print(f"false ids on {args.seeds} tag-free frames (every camera degradation): {empty}")
    print(json.dumps({"seeds": args.seeds, "poses": args.poses, "first_seed": args.first_seed, "false_ids_tag_free_frames": empty,
                      "per_condition": {c: {"found_share": round(r["found_share"], 4), "visible_tags": r["visible"], "found_tags": r["found"],
                                            "false_ids": r["false_ids"], "corner_rms_px": round(r["corner_rms_px"], 4),
                                            "locate_ms_per_frame": round(r["ms_per_frame"], 2), "recovered_tags": r["recovered"],
                                            "recovered_false": r["recovered_false"],
                                            "recovered_corner_rms_px": round(r["recovered_corner_rms_px"], 4),
                                            "searched_tags": r["searched"], "searched_false": r["searched_false"],
                                            "searched_corner_rms_px": round(r["searched_corner_rms_px"], 4),
                                            "search_ms_per_frame": round(r["search_ms_per_frame"], 2),
                                            "partly_in_frame_tags": r["partly_visible"], "partly_recovered": r["partly_recovered"],
                                            "partly_false": r["partly_false"],
                                            "partly_corner_rms_px": round(r["partly_corner_rms_px"], 4),
                                            "off_10_22px_recovered_within_reach": r["reached"], "off_10_22px_false": r["reached_false"],
                                            "off_10_22px_corner_rms_px": round(r["reached_corner_rms_px"], 4),
                                            "reach_ms_per_frame": round(r["reach_ms_per_frame"], 2)} for c, r in res.items()}}))


if __name__ == "__main__":
    main()
