"""Video loop: time per frame of detection + localisation (one thread), and X_D accuracy at ~20 cm.

Reference (Vagdargi et al. 2021, Table 4): video feature extraction + marker localisation 56.9 ms;
X_D error medians: in-plane 0.46 mm, depth 1.6 mm.
Run: .venv/bin/python benchmarks/video_loop.py [--frames 200]
"""

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.video_markers import VideoMarkerLocator


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    figs = []
    for size in [(1280, 720), (1920, 1080)]:
        times, depth, inplane, found = [], [], [], []
        per_scene = max(1, args.frames // 10)
        for seed in range(10):
            scene = make_scene(seed=100 + seed, image_size=size, render=False)
            loc = VideoMarkerLocator(camera=scene.true_camera, marker_ids=scene.marker_set.ids)
            rng = np.random.default_rng(seed)
            for _ in range(per_scene):
                pose = scene.drill_pose_towards(rng, offset_mm=6.0, tilt_deg=6.0)
                img = scene.render_camera(rng, carm_from_drill=pose)
                t = time.perf_counter()
                det = loc.locate(img)
                times.append((time.perf_counter() - t) * 1e3)
                found.append(len(det.markers))
                truth = scene.camera_from_marker(pose)
                for m in det.markers:
                    x = truth[m.marker_id][:3, 3]
                    e = m.position_camera_mm - x
                    u = x / np.linalg.norm(x)
                    depth.append(abs(e @ u))
                    inplane.append(np.linalg.norm(e - (e @ u) * u))
        w, h = size
        figs.append(figure(f"detect+localise {w}x{h} median", float(np.median(times)), "ms", 56.9))
        figs.append(figure(f"detect+localise {w}x{h} p99", float(np.percentile(times, 99)), "ms", 56.9))
        if size == (1280, 720):
            figs.append(figure("X_D depth error median (true lens)", float(np.median(depth)), "mm", 1.6))
            figs.append(figure("X_D in-plane error median (true lens)", float(np.median(inplane)), "mm", 0.46))
            figs.append(figure("markers found per frame (of 5)", float(np.mean(found)), "n", None))
            n_frames = len(times)
    report("video_loop", figs, frames_per_size=n_frames, note="one thread (cv2.setNumThreads(1)); twin frames, 5 markers at ~20 cm")


if __name__ == "__main__":
    main()
