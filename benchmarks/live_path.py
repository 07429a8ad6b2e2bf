"""The live frame path's accuracy and time on the hard twin: freehand sequences through ``track_frame``.

``benchmarks/accuracy.py`` registers each frame afresh (``drillnav register``); the registration node does
not. It runs the joint solve on a frame and tracks the frames after it on the markers that solve refined
(:class:`~drillnav.registration.pipeline.JointRefinement`), until the period runs out or a frame needs a solve
of its own (no tag found, too few tracked markers seen). This benchmark follows that path: per seed and view
pair (inlet+outlet, AP+lateral, two random positioner angles, both views, the five placed markers), the
fluoroscopy marker poses, then ``--frames`` freehand frames at 30 frames/s of capture time through
``track_frame`` with the joint solve inline every ``JOINT_PERIOD_NS`` (deterministic; the node runs the same
solve in a worker, ``benchmarks/frame_path.py``). The twin is as hard as an operating room (every degradation,
the real CT as the patient).

Per frame: the drill-axis error (position at the corridor entry, as the study scores it, and at the frame's
working point, where its 90 % bound is given; angle) against the truth, whether the bound covers it, whether the
frame was flagged, the wall time, and what the frame was: tracked, solved, solved on tags named among the
posed markers (``FrameAxis.named_ids``), or refused.

Reference (Vagdargi et al. 2021): median 0.9 mm / 2.0 deg with 2 views and 5 markers (Sec. 3.1); 96.2 ms per
frame for the whole video loop (Table 4).
``--worker`` runs the frames as the node does instead: ``JointSolveWorker.track``, the periodic solve in a worker
process, a frame that sees a weakly posed marker beside one tracked marker tracked and its solve asked of the worker.
Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/live_path.py [--seeds 3 --first-seed 3000 --frames 30] [--worker]
[--marker-tilt 0,10] (markers stuck flat on the skin).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402
from accuracy import CT, _pairs, load_patient, with_marker_tilt  # noqa: E402

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, make_scene, render_fluoro
from drillnav.registration.errors import DrillnavError
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.pipeline import JOINT_PERIOD_NS, LiveCalibration, track_frame
from drillnav.service.joint_worker import JointSolveWorker

FRAME_NS = 33_333_333  # 30 frames/s of capture time


def sequence(scene, *, seed: int, k: int, frames: int, worker: JointSolveWorker | None = None) -> list[dict]:
    """One freehand sequence of ``scene`` (seeded by seed and view pair k) through ``track_frame`` (or ``worker``'s
    ``track``, as the node runs it): a dict per frame."""
    image_rng = np.random.default_rng([seed, k, 1])
    dets = [detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in scene.views]
    poses = register_markers(dets, list(scene.views.values()), scene.marker_set)
    calibration = LiveCalibration.build(camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill, marker_set=scene.marker_set)
    pose_rng, camera_rng = np.random.default_rng([seed, k, 2]), np.random.default_rng([seed, k, 3])
    entry = scene.corridor_entry_carm_mm
    refinement, out = None, []
    for j in range(frames):
        carm_from_drill = scene.drill_pose_towards(pose_rng, offset_mm=5.0, tilt_deg=5.0)
        image = scene.render_camera(camera_rng, carm_from_drill=carm_from_drill)
        t0 = time.perf_counter_ns()
        try:
            if worker is not None:
                fa = worker.track(image, calibration=calibration, poses=poses, stamp_ns=j * FRAME_NS)
            else:
                fa = track_frame(image, calibration=calibration, poses=poses, marker_set=scene.marker_set, refinement=refinement,
                                 now_ns=j * FRAME_NS, joint_period_ns=JOINT_PERIOD_NS)
        except DrillnavError as exc:
            out.append({"kind": "refused", "ms": (time.perf_counter_ns() - t0) / 1e6, "reason": str(exc).split(" (")[0]})
            continue
        ms = (time.perf_counter_ns() - t0) / 1e6
        refinement = fa.refinement
        named = [m.marker_id for m in fa.video.markers if m.named_among_posed and m.marker_id in fa.registration.used_ids]
        truth = TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
        kind = "named" if named else ("solved" if fa.registration.method == "joint" else "tracked")
        pe, work = fa.predicted_error, fa.working_point_carm_mm
        out.append({"kind": kind, "ms": ms, "pos_mm": float(np.linalg.norm(fa.axis_full_carm.closest_point(entry) - truth.closest_point(entry))),
                    "work_mm": float(np.linalg.norm(work - truth.closest_point(work))),
                    "ang_deg": fa.axis_full_carm.angle_deg(truth), "b90_mm": pe.position90_mm, "b90_deg": pe.angle90_deg,
                    "reliable": pe.reliable, "used": len(fa.registration.used_ids), "wants_solve": bool(getattr(fa, "wants_solve", False))})
    return out


def _record(frames: list[dict], per_pair: dict[str, list[dict]], seq: list[dict], *, seed: int, pair: str) -> None:
    seq = [f | {"seed": seed, "pair": pair, "frame": j} for j, f in enumerate(seq)]
    frames += seq
    per_pair.setdefault(pair, []).extend(seq)
    done = [f for f in seq if "pos_mm" in f]
    worst = max((f["pos_mm"] for f in done), default=float("nan"))
    print(f"seed {seed} {pair:13s} frames {len(seq)} refused {len(seq) - len(done)} median "
          f"{np.median([f['pos_mm'] for f in done]) if done else float('nan'):.2f} mm, worst {worst:.2f} mm", file=sys.stderr, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=3000)
    ap.add_argument("--frames", type=int, default=30, help="frames per sequence (30 per second of capture time)")
    ap.add_argument("--degradations", default="all", help="as benchmarks/accuracy.py: all | none | a,b,...")
    ap.add_argument("--ct", type=Path, default=CT, help="the real CT, the patient of the ct_anatomy degradation")
    ap.add_argument("--worker", action="store_true", help="as the node runs: the periodic solve in JointSolveWorker (each adopting frame "
                    "waits for its solve, so the figures do not hang on this machine's load; its wall time then includes that wait)")
    ap.add_argument("--save", type=Path, help="write every frame's figures (seed, pair, frame index added) to this JSON file")
    ap.add_argument("--marker-tilt", default=None, help="as benchmarks/accuracy.py: the markers' tilt from the AP beam, LOW,HIGH deg (default "
                    "the twin's 10,40; 0,10 for markers stuck flat on the skin, edge-on in a lateral view)")
    args = ap.parse_args()
    deg = Degradations.parse(args.degradations)
    deg = with_marker_tilt(ap, deg, args.marker_tilt)
    patient = load_patient(args.ct) if deg.ct_anatomy else None
    frames: list[dict] = []
    per_pair: dict[str, list[dict]] = {}
    with contextlib.ExitStack() as stack:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            for k, (pair, views) in enumerate(_pairs(np.random.default_rng(seed)).items()):
                scene = make_scene(seed=seed, views=views, render=False, degradations=deg, voxel_anatomy=patient)
                worker = None
                if args.worker:
                    worker = stack.enter_context(JointSolveWorker(marker_set=scene.marker_set, wait_s=30.0))
                    worker.wait_ready()
                seq = sequence(scene, seed=seed, k=k, frames=args.frames, worker=worker)
                if worker is not None:
                    worker.close()
                _record(frames, per_pair, seq, seed=seed, pair=pair)
    if args.save:
        args.save.write_text(json.dumps(frames, default=float))
    done = [f for f in frames if "pos_mm" in f]
    pos, ang = np.array([f["pos_mm"] for f in done]), np.array([f["ang_deg"] for f in done])
    ms = np.array([f["ms"] for f in frames])
    by_kind = {kind: np.array([f["ms"] for f in frames if f["kind"] == kind]) for kind in ("tracked", "solved", "named", "refused")}
    pct = lambda a, q: float(np.percentile(a, q)) if len(a) else float("nan")  # noqa: E731
    figs = [
        figure("frames", float(len(frames)), "n"),
        figure("frames refused", 100.0 * (len(frames) - len(done)) / len(frames), "%"),
        figure("position error median", float(np.median(pos)), "mm", 0.9),
        figure("position error p95", pct(pos, 95), "mm"),
        figure("position error max", float(pos.max()), "mm"),
        figure("angle error median", float(np.median(ang)), "deg", 2.0),
        figure("angle error p95", pct(ang, 95), "deg"),
    ]
    for pair, seq in per_pair.items():
        p = np.array([f["pos_mm"] for f in seq if "pos_mm" in f])
        figs += [figure(f"{pair}: position error median", float(np.median(p)), "mm", 0.9), figure(f"{pair}: position error p95", pct(p, 95), "mm")]
    for kind in ("tracked", "solved", "named"):
        sel = [f for f in done if f["kind"] == kind]
        if sel:
            figs += [figure(f"{kind} frames: bound covers position", 100.0 * float(np.mean([f["work_mm"] <= f["b90_mm"] for f in sel])), "%"),
                     figure(f"{kind} frames: bound covers angle", 100.0 * float(np.mean([f["ang_deg"] <= f["b90_deg"] for f in sel])), "%")]
    work = np.array([f["work_mm"] for f in done])
    figs += [
        figure("position error at the working point median", float(np.median(work)), "mm", 0.9),
        figure("bound covers position (working point)", 100.0 * float(np.mean(work <= np.array([f["b90_mm"] for f in done]))), "%"),
        figure("bound covers angle", 100.0 * float(np.mean(ang <= np.array([f["b90_deg"] for f in done]))), "%"),
        figure("errors over 10 mm or 10 deg not flagged", float(sum((f["pos_mm"] > 10 or f["ang_deg"] > 10) and f["reliable"] for f in done)), "n"),
        figure("frames tracked that asked for a solve (worker)", float(sum(f.get("wants_solve", False) for f in frames)), "n"),
        figure("frame wall p50", pct(ms, 50), "ms", 96.2),
        figure("frame wall p99", pct(ms, 99), "ms", 96.2),
    ]
    for kind, a in by_kind.items():
        figs += [figure(f"{kind} frames", float(len(a)), "n")]
        if len(a):
            figs += [figure(f"{kind} frames: wall p50", pct(a, 50), "ms", 96.2), figure(f"{kind} frames: wall max", float(a.max()), "ms", 96.2)]
    report("live_path", figs, seeds=f"{args.first_seed}-{args.first_seed + args.seeds - 1}", frames_per_sequence=args.frames,
           degradations=deg.label(), marker_tilt_deg=list(deg.marker_tilt_deg), mode="worker" if args.worker else "inline", load_average_1min=round(os.getloadavg()[0], 1),
           note=("JointSolveWorker.track, the periodic solve in its worker process (adopting frames wait for it)" if args.worker else
                 "track_frame with the joint solve inline every JOINT_PERIOD_NS") + "; a shared 2-core machine")


if __name__ == "__main__":
    main()
