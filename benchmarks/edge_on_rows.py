"""What an edge-on marker's rows cost: its ring's stroke, its roll, and the turned search, beside the frame budget.

A joint solve that uses a marker edge-on in a view measures, per round, its ring's stroke
(:func:`~drillnav.registration.edge_on_ring.measure_ring_stroke`) and its roll
(:func:`~drillnav.registration.edge_on_roll.measure_ring_roll`, the marker's shadow rendered at 41 turns); where the
view shows the marker by nothing, the turned search (``video_fluoro._turned_stroke``: a roll at the lower bar, then the
stroke at the turned pose). Each is timed here on the twin with the markers stuck flat on the skin (AP + lateral,
seeds 8, 9 and 15 unless told), from each marker's true pose turned 3 deg about its ring's line in the lateral view,
the median of ``--repeats`` runs per marker; beside the reference's whole video frame (96.2 ms), of which a solved
frame measures a few of each.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/edge_on_rows.py [--seeds 8,9,15] [--repeats 5]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import make_scene, render_fluoro
from drillnav.registration import video_fluoro
from drillnav.registration.edge_on_ring import measure_ring_stroke
from drillnav.registration.edge_on_roll import measure_ring_roll, rolled_about

REFERENCE_FRAME_MS = 96.2  # the reference's video loop, per frame
TURN_DEG = 3.0


def median_ms(call, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        call()
        ts.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(ts))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="8,9,15", help="twin seeds, comma-separated")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per marker (the median is kept)")
    args = parser.parse_args(argv)
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        parser.error(f"--seeds must be integers separated by commas, got {args.seeds!r}")
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")

    stroke_ms, roll_ms, turned_ms = [], [], []
    for seed in seeds:
        scene = make_scene(seed=seed, views="ap,lateral", render=False, degradations=Degradations(surgeon_markers=True, marker_tilt_deg=(0.0, 10.0)))
        lateral = scene.views["lateral"]
        image = render_fluoro(scene, "lateral", np.random.default_rng([seed, 1]))
        for i, truth in scene.carm_from_marker.items():
            design = scene.marker_set.by_id(i)
            at_truth = measure_ring_roll(image, lateral, truth, design, min_correlation=-1.0)
            if at_truth is None:
                continue  # not edge-on, or its window leaves the image
            pose = rolled_about(truth, at_truth.axis_mm, design.ring_center_mm, TURN_DEG)
            stroke_ms.append(median_ms(lambda: measure_ring_stroke(image, lateral, pose, design), args.repeats))
            roll_ms.append(median_ms(lambda: measure_ring_roll(image, lateral, pose, design), args.repeats))
            turned_ms.append(median_ms(lambda: video_fluoro._turned_stroke(image, lateral, pose, design), args.repeats))
    if not roll_ms:
        sys.exit(f"no marker edge-on and wholly in the lateral view on seeds {seeds}: nothing to time")
    figures = [
        figure("stroke measurement (median over markers)", float(np.median(stroke_ms)), "ms", REFERENCE_FRAME_MS),
        figure("roll measurement (median over markers)", float(np.median(roll_ms)), "ms", REFERENCE_FRAME_MS),
        figure("roll measurement (worst marker)", float(np.max(roll_ms)), "ms", REFERENCE_FRAME_MS),
        figure("turned search (median over markers)", float(np.median(turned_ms)), "ms", REFERENCE_FRAME_MS),
        figure("markers timed", float(len(roll_ms)), "n"),
    ]
    report("edge_on_rows", figures, seeds=seeds, repeats=args.repeats, turn_deg=TURN_DEG)


if __name__ == "__main__":
    main()
