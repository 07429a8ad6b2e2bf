"""The registration node's frame path alone: per-frame time with the periodic joint solve inline and in the worker.

The recording's camera frames, paced at 30 frames/s with 30 frames/s capture stamps, go through
(a) ``track_frame`` with the joint solve every ``JOINT_PERIOD_NS`` on the frame path (the node before), and
(b) ``JointSolveWorker.track`` (the node now: the periodic solve in a worker process, adopted on capture time).
Per frame it reports the wall time and the frame thread's own CPU time (``time.thread_time_ns``: what the frame
path computed, less sensitive than wall time to other load on a shared machine).

Reference: 96.2 ms per frame (10 frames/s) for the whole video loop (Vagdargi et al. 2021, Table 4).
Run: .venv/bin/python benchmarks/frame_path.py [--frames 600]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from twin_replay import recorded_live_inputs  # noqa: E402  (the tests' own reading of the reference recording)

from drillnav.registration.pipeline import track_frame
from drillnav.service.joint_worker import JointSolveWorker

PERIOD_NS = 33_333_333


def _run(step, frames: list[np.ndarray], n: int) -> tuple[np.ndarray, np.ndarray]:
    wall, cpu = [], []
    t0 = time.monotonic_ns()
    for k in range(n):
        time.sleep(max(0.0, (t0 + k * PERIOD_NS - time.monotonic_ns()) / 1e9))  # paced as a camera
        w, c = time.perf_counter_ns(), time.thread_time_ns()
        step(frames[k % len(frames)], 1_000_000_000 + k * PERIOD_NS)
        cpu.append(time.thread_time_ns() - c)
        wall.append(time.perf_counter_ns() - w)
    return np.array(wall) / 1e6, np.array(cpu) / 1e6


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=600, help="frames per mode (30 per second of capture time)")
    args = ap.parse_args()
    scene, poses, cal, frames = recorded_live_inputs()

    carried = {"ref": None}

    def inline(image, stamp):
        fa = track_frame(image, calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=carried["ref"], now_ns=stamp)
        carried["ref"] = fa.refinement

    wall_a, cpu_a = _run(inline, frames, args.frames)
    with JointSolveWorker(marker_set=scene.marker_set) as worker:
        worker.wait_ready()
        wall_b, cpu_b = _run(lambda image, stamp: worker.track(image, calibration=cal, poses=poses, stamp_ns=stamp), frames, args.frames)
        counters = worker.counters
    pct = lambda a, q: float(np.percentile(a, q))  # noqa: E731
    report("frame_path", [
        figure("inline joint solve: frame wall p50", pct(wall_a, 50), "ms", 96.2),
        figure("inline joint solve: frame wall p99", pct(wall_a, 99), "ms", 96.2),
        figure("inline joint solve: frame CPU p50", pct(cpu_a, 50), "ms", None),
        figure("inline joint solve: frame CPU p99", pct(cpu_a, 99), "ms", None),
        figure("worker joint solve: frame wall p50", pct(wall_b, 50), "ms", 96.2),
        figure("worker joint solve: frame wall p99", pct(wall_b, 99), "ms", 96.2),
        figure("worker joint solve: frame CPU p50", pct(cpu_b, 50), "ms", None),
        figure("worker joint solve: frame CPU p99", pct(cpu_b, 99), "ms", None),
        figure("worker joint solve: frame wall max", float(wall_b.max()), "ms", None),
        figure("periodic solves adopted from the worker", float(counters.adopted), "n", None),
        figure("periodic solves adopted late (worker late)", float(counters.late), "n", None),
    ], frames_per_mode=args.frames, load_average_1min=round(os.getloadavg()[0], 1),
        note="one process, the recording's frames paced at 30 frames/s; 2-core machine shared with other work")


if __name__ == "__main__":
    main()
