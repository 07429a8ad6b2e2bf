"""Does the predicted 90 % bound cover 85-95 % of the errors, per configuration? (issue 17, "an honest predicted error").

The accuracy study's scenes and detections (``benchmarks/accuracy.py``: its view pairs, the real CT for
``ct_anatomy``), at seeds the product's tests and the study do not use, M = 5 markers, the joint solve, each
view pair with both views and with each view alone. Per configuration: the coverage of the 90 % bounds
(position at the corridor entry, angle), the distribution of actual / predicted (90 % bound), the share
flagged unreliable, errors over 10 deg that were not flagged, and which term makes the bound: the joint
solve's covariance (measurement noise and the camera prior) against the drill axis's calibration, with the
actual error split the same way (the twin knows the truth: the calibrated axis carried by the true pose,
against the true axis carried by the registered pose).

Each part of the error is also scored against its own term of the bound. The scene draws one drill-axis
calibration error per seed, shared by all its registrations; ``--calibration-redraws K`` also scores each
registration against K fresh draws of it (the twin's own draw, independent of the images), which takes that
term's sampling noise out of the coverage.

Detections are cached (``--cache``), so the predictor can be re-scored after a change without re-rendering.
Run: nice -n 10 .venv/bin/python benchmarks/bound_coverage.py [--seeds 6 --first-seed 8100 --poses 2] [--degradations all] [--calibration-redraws 10]
Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import CT, _pairs, camera_frames, load_patient  # noqa: E402  (the study's view pairs and patient)

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, _perturbed_axis, make_scene, render_fluoro
from drillnav.registration.errors import DrillnavError
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro

FIELDS = ("pos_mm", "ang_deg", "b90_pos_mm", "b90_ang_deg", "reliable", "cov_pos_mm", "cov_ang_deg", "cal_pos_mm", "cal_ang_deg",
          "err_pose_pos_mm", "err_pose_ang_deg", "err_cal_pos_mm", "err_cal_ang_deg", "mirror", "redrawn_cover_pos", "redrawn_cover_ang")


def _shots(seed: int, k: int, pair: str, views: str, poses: int, deg: Degradations, patient, cache: Path | None):
    """(scene, {view: FluoroDetections}, [(true carm_from_drill, VideoDetections)]) as the accuracy study makes them."""
    scene = make_scene(seed=seed, views=views, render=False, degradations=deg, voxel_anatomy=patient if deg.ct_anatomy else None)
    path = None if cache is None else cache / f"{deg.label()}-{seed}-{pair}-{poses}.pkl"
    if path is not None and path.exists():
        dets, frames = pickle.loads(path.read_bytes())
        return scene, dets, frames
    image_rng = np.random.default_rng([seed, k, 1])
    dets = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in scene.views}
    frames = camera_frames(scene, seed=seed, k=k, poses=poses)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps((dets, frames)))
    return scene, dets, frames


def _line_errors(axis, true_axis, entry) -> tuple[float, float]:
    return float(np.linalg.norm(axis.closest_point(entry) - true_axis.closest_point(entry))), float(axis.angle_deg(true_axis))


def _redrawn_coverage(scene, video, poses, reg, carm_from_drill, redraws: int) -> tuple[float, float]:
    """Share of ``redraws`` fresh drill-axis calibration errors (the twin's own draw) whose axis, registered by
    ``reg``, lies within its 90 % bounds (position, angle); NaN without redraws.

    The scene draws one calibration error per seed, shared by all its registrations, so a few dozen seeds are a
    few dozen draws of the bound's largest two-view term. The calibration error is independent of every image,
    so averaging over fresh draws for the same registration estimates the coverage with that term's sampling
    noise taken out.
    """
    if redraws <= 0:
        return float("nan"), float("nan")
    entry = scene.corridor_entry_carm_mm
    true_axis = TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
    rng = np.random.default_rng([scene.seed, 17])
    hits = np.zeros(2)
    for k in range(redraws):
        cal = _perturbed_axis(rng, TRUE_DRILL_AXIS_CAMERA)
        pe = predicted_axis_error(video, poses, reg, cal, working_point_carm_mm=entry, seed=k)
        pos, ang = _line_errors(cal.transformed(reg.carm_from_drill), true_axis, entry)
        hits += (pos <= pe.position90_mm, ang <= pe.angle90_deg)
    return float(hits[0] / redraws), float(hits[1] / redraws)


def score(scene, video, poses, reg, carm_from_drill, *, redraws: int = 0) -> tuple:
    """One registration's row (see FIELDS)."""
    entry = scene.corridor_entry_carm_mm
    cal = scene.calibrated_axis_drill
    axis, true_axis = cal.transformed(reg.carm_from_drill), TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
    pe = predicted_axis_error(video, poses, reg, cal, working_point_carm_mm=entry)
    # The bound's terms alone: the covariance without the axis calibration, the axis calibration without it.
    cov = predicted_axis_error(video, poses, dataclasses.replace(reg, mirror_carm_from_drill=None), cal, working_point_carm_mm=entry,
                               axis_sigma_mm=0.0, axis_sigma_deg=0.0)
    still = dataclasses.replace(reg, covariance_drill=np.zeros((6, 6)), mirror_carm_from_drill=None)
    calb = predicted_axis_error(video, poses, still, cal, working_point_carm_mm=entry)
    # The actual error's parts: the pose's (true axis carried by both poses), the calibration's (both axes by the true pose).
    e_pose = _line_errors(TRUE_DRILL_AXIS_CAMERA.transformed(reg.carm_from_drill), true_axis, entry)
    e_cal = _line_errors(cal.transformed(carm_from_drill), true_axis, entry)
    return (*_line_errors(axis, true_axis, entry), pe.position90_mm, pe.angle90_deg, float(pe.reliable), cov.position90_mm, cov.angle90_deg,
            calb.position90_mm, calb.angle90_deg, *e_pose, *e_cal, float(reg.mirror_carm_from_drill is not None),
            *_redrawn_coverage(scene, video, poses, reg, carm_from_drill, redraws))


def run(seeds: int, first_seed: int, poses: int, deg: Degradations, *, patient=None, m: int = 5, cache: Path | None = None,
        redraws: int = 0) -> dict:
    """rows[(pair, n_views)] = list of FIELDS tuples; refused[(pair, n_views)] = count; tried likewise."""
    rows: dict[tuple, list] = {}
    refused: dict[tuple, int] = {}
    tried: dict[tuple, int] = {}
    for seed in range(first_seed, first_seed + seeds):
        rng = np.random.default_rng(seed)
        for k, (pair, views) in enumerate(_pairs(rng).items()):
            scene, dets, frames = _shots(seed, k, pair, views, poses, deg, patient, cache)
            names = list(scene.views)
            subset = sorted(scene.carm_from_marker)[:m]
            for vs in [names] + [[n] for n in names]:
                marker_poses = tuple(p for p in register_markers([dets[n] for n in vs], [scene.views[n] for n in vs], scene.marker_set)
                                     if p.marker_id in subset)
                for carm_from_drill, seen in frames:
                    video = dataclasses.replace(seen, markers=tuple(v for v in seen.markers if v.marker_id in subset))
                    # One view: named by the view (a random pair's angles differ per seed: pooled as "random:one").
                    key = (pair if len(vs) == 2 else f"{pair}:{'one' if pair == 'random' else vs[0]}", len(vs))
                    tried[key] = tried.get(key, 0) + 1
                    try:
                        reg = register_video_to_fluoro(video, marker_poses, scene.marker_set, scene.calibrated_camera)
                    except DrillnavError:
                        refused[key] = refused.get(key, 0) + 1
                        continue
                    rows.setdefault(key, []).append(score(scene, video, marker_poses, reg, carm_from_drill, redraws=redraws))
        print(f"[{deg.label()}] seed {seed} done", file=sys.stderr, flush=True)
    return {"rows": rows, "refused": refused, "tried": tried}


def summarise(rows: list) -> dict:
    a = np.array(rows, dtype=float).reshape(-1, len(FIELDS))
    f = {name: a[:, i] for i, name in enumerate(FIELDS)}
    rp, ra = f["pos_mm"] / f["b90_pos_mm"], f["ang_deg"] / f["b90_ang_deg"]
    cov_share_p = f["cov_pos_mm"] ** 2 / (f["cov_pos_mm"] ** 2 + f["cal_pos_mm"] ** 2)
    cov_share_a = f["cov_ang_deg"] ** 2 / (f["cov_ang_deg"] ** 2 + f["cal_ang_deg"] ** 2)
    return {
        "n": len(a), "cover_pos_pct": 100 * float(np.mean(rp <= 1)), "cover_ang_pct": 100 * float(np.mean(ra <= 1)),
        "ratio_pos_q": np.percentile(rp, [10, 50, 90]).tolist(), "ratio_ang_q": np.percentile(ra, [10, 50, 90]).tolist(),
        "pos_median_mm": float(np.median(f["pos_mm"])), "ang_median_deg": float(np.median(f["ang_deg"])),
        "b90_pos_median_mm": float(np.median(f["b90_pos_mm"])), "b90_ang_median_deg": float(np.median(f["b90_ang_deg"])),
        "cov_share_pos": float(np.median(cov_share_p)), "cov_share_ang": float(np.median(cov_share_a)),
        "err_pose_pos_rms": float(np.sqrt(np.mean(f["err_pose_pos_mm"] ** 2))), "err_cal_pos_rms": float(np.sqrt(np.mean(f["err_cal_pos_mm"] ** 2))),
        "err_pose_ang_rms": float(np.sqrt(np.mean(f["err_pose_ang_deg"] ** 2))), "err_cal_ang_rms": float(np.sqrt(np.mean(f["err_cal_ang_deg"] ** 2))),
        "flagged_pct": 100 * float(np.mean(f["reliable"] < 0.5)), "unflagged_over_10deg": int(np.sum((f["ang_deg"] > 10) & (f["reliable"] > 0.5))),
        "mirror_pct": 100 * float(np.mean(f["mirror"] > 0.5)),
        # Each part of the error against its own term of the bound: which one under-covers.
        "cover_pose_part_pos_pct": 100 * float(np.mean(f["err_pose_pos_mm"] <= f["cov_pos_mm"])),
        "cover_pose_part_ang_pct": 100 * float(np.mean(f["err_pose_ang_deg"] <= f["cov_ang_deg"])),
        "cover_cal_part_pos_pct": 100 * float(np.mean(f["err_cal_pos_mm"] <= f["cal_pos_mm"])),
        "cover_cal_part_ang_pct": 100 * float(np.mean(f["err_cal_ang_deg"] <= f["cal_ang_deg"])),
        # With --calibration-redraws: coverage averaged over fresh calibration errors (NaN without).
        "cover_redrawn_pos_pct": _pct(f["redrawn_cover_pos"]), "cover_redrawn_ang_pct": _pct(f["redrawn_cover_ang"]),
    }


def _pct(shares) -> float | None:
    """Mean share in %, None where it was not measured (NaN)."""
    return None if np.all(np.isnan(shares)) else 100 * float(np.nanmean(shares))


def table(result: dict) -> list[str]:
    """Markdown rows: per configuration, then pooled per number of views."""
    lines = ["| configuration | views | n | refused | coverage pos / ang | actual/bound pos p10-p50-p90 | actual/bound ang p10-p50-p90 | "
             "median err mm / deg | median bound mm / deg | covariance share of bound pos / ang | RMS err pose / calib mm | RMS err pose / calib deg | "
             "part coverage pose / calib, pos | part coverage pose / calib, ang | coverage over redrawn calibrations pos / ang | flagged | >10 deg unflagged |",
             "|" + "---|" * 17]
    groups = [(k, result["rows"].get(k, [])) for k in sorted(result["tried"], key=lambda k: (-k[1], k[0]))]
    groups += [(("all pairs", nv), [r for k, v in result["rows"].items() if k[1] == nv for r in v]) for nv in (2, 1)]
    for (name, nv), rows in groups:
        tried = result["tried"].get((name, nv)) or sum(t for k, t in result["tried"].items() if k[1] == nv)
        refused = result["refused"].get((name, nv), 0) if (name, nv) in result["tried"] else sum(r for k, r in result["refused"].items() if k[1] == nv)
        if not rows:
            lines.append(f"| {name} | {nv} | 0 | {refused}/{tried} |" + " - |" * 13)
            continue
        s = summarise(rows)
        q = lambda v: "-".join(f"{x:.2f}" for x in v)  # noqa: E731
        redrawn = "-" if s["cover_redrawn_pos_pct"] is None else f"{s['cover_redrawn_pos_pct']:.1f} / {s['cover_redrawn_ang_pct']:.1f} %"
        lines.append(f"| {name} | {nv} | {s['n']} | {refused}/{tried} | {s['cover_pos_pct']:.0f} / {s['cover_ang_pct']:.0f} % | {q(s['ratio_pos_q'])} | "
                     f"{q(s['ratio_ang_q'])} | {s['pos_median_mm']:.2f} / {s['ang_median_deg']:.2f} | {s['b90_pos_median_mm']:.2f} / {s['b90_ang_median_deg']:.2f} | "
                     f"{s['cov_share_pos']:.2f} / {s['cov_share_ang']:.2f} | {s['err_pose_pos_rms']:.2f} / {s['err_cal_pos_rms']:.2f} | "
                     f"{s['err_pose_ang_rms']:.3f} / {s['err_cal_ang_rms']:.3f} | {s['cover_pose_part_pos_pct']:.0f} / {s['cover_cal_part_pos_pct']:.0f} % | "
                     f"{s['cover_pose_part_ang_pct']:.0f} / {s['cover_cal_part_ang_pct']:.0f} % | {redrawn} | {s['flagged_pct']:.0f} % | {s['unflagged_over_10deg']} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--first-seed", type=int, default=8100, help="unseen by the tests and the accuracy study (3000-)")
    ap.add_argument("--poses", type=int, default=2)
    ap.add_argument("--markers", type=int, default=5, help="M: the first M of the 5 placed markers")
    ap.add_argument("--degradations", default="none", help="all | none | comma-separated names from drivers/sim/degradations.py")
    ap.add_argument("--ct", type=Path, default=CT)
    ap.add_argument("--cache", type=Path, default=None, help="keep the detections here (re-score without re-rendering)")
    ap.add_argument("--calibration-redraws", type=int, default=0, help="also the coverage averaged over this many fresh drill-axis "
                    "calibration errors per registration (the scene's one draw per seed is shared by all its registrations)")
    args = ap.parse_args()
    deg = Degradations.parse(args.degradations)
    patient = load_patient(args.ct) if deg.ct_anatomy else None
    t0 = time.time()
    result = run(args.seeds, args.first_seed, args.poses, deg, patient=patient, m=args.markers, cache=args.cache, redraws=args.calibration_redraws)
    print(f"degradations: {deg.label()}; seeds {args.first_seed}-{args.first_seed + args.seeds - 1}, {args.poses} poses, M = {args.markers}; "
          f"{time.time() - t0:.0f} s")
    print("\n".join(table(result)))
    pooled = {str(nv): summarise([r for k, v in result["rows"].items() if k[1] == nv for r in v]) for nv in (2, 1)
              if any(k[1] == nv for k in result["rows"])}
    print(json.dumps({"degradations": deg.label(), "first_seed": args.first_seed, "seeds": args.seeds, "M": args.markers, "pooled": pooled}))


if __name__ == "__main__":
    main()
