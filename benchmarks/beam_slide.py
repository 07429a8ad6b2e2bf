"""What looking for a missed tag along a fluoroscopy view's beam costs a joint registration (issue 17).

A marker posed in one fluoroscopy view has its depth from its BB pattern's scale alone; when the camera misses its tag
where that depth puts it, the joint solve's frame also looks for it with the marker slid along the view's beam
(:func:`~drillnav.registration.pipeline.predict_slid_tags`, then ``VideoMarkerLocator.recover`` by code alone).
This benchmark registers the study's frames as the product does (``register_with_recovery``: the hard twin, every
degradation, the real CT as the patient where ``../shared/data`` has it; inlet+outlet, AP+lateral and random view
pairs, both views and each alone; the five placed markers) and, on each registration, times the slide step by itself
as the recovery's first pass runs it: the slid predictions from the registration on the detector's tags, and the
recovery that looks there (the pass gets the tags the other recoveries found first, so this times a little more). Reported: the share of
registrations that have a slid tag to look for, the step's time where they do, and the whole registration's time
(slide included) beside it and beside the reference's 96.2 ms video-loop frame (Vagdargi et al. 2021, Table 4; the
joint solve runs in a worker beside the 30 frames/s frame path, ``benchmarks/frame_path.py``).

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/beam_slide.py [--seeds 3 --first-seed 2300 --poses 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402
from accuracy import CT, load_patient, study_scenes  # noqa: E402

from drillnav.drivers.sim.degradations import Degradations
from drillnav.registration.errors import DrillnavError
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.pipeline import predict_slid_tags, predict_tag_places, register_with_recovery
from drillnav.registration.video_fluoro import register_video_to_fluoro
from drillnav.registration.video_markers import VideoMarkerLocator

REFERENCE_FRAME_MS = 96.2  # the reference's whole video loop per frame (Table 4)


def measure(*, seeds: int, first_seed: int, poses: int) -> dict:
    deg = Degradations.parse("all")
    patient = load_patient(CT) if CT.exists() else None
    if patient is None:
        deg = replace(deg, ct_anatomy=False)
    registration_ms, step_ms, slid_counts, refused = [], [], [], 0
    for _, _, scene, dets, frames in study_scenes(seeds=seeds, first_seed=first_seed, poses=poses, degradations=deg, patient=patient):
        names = list(scene.views)
        locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)
        for vs in [names] + [[n] for n in names]:
            marker_poses = register_markers([dets[n] for n in vs], [scene.views[n] for n in vs], scene.marker_set)
            for _, video, image in frames:
                t = time.perf_counter()
                try:
                    register_with_recovery(image, video, locator=locator, camera=scene.calibrated_camera, poses=marker_poses,
                                                      marker_set=scene.marker_set)
                except DrillnavError:
                    refused += 1
                    continue
                registration_ms.append(1e3 * (time.perf_counter() - t))
                # The slide step alone, as the recovery's first pass runs it: on the detector's tags and the
                # registration on them (the tags the other recoveries find before it are still missing here, so
                # this times a little more than the pass does).
                try:
                    first = register_video_to_fluoro(video, marker_poses, scene.marker_set, scene.calibrated_camera, joint=True)
                except DrillnavError:
                    continue  # the first registration needed the search or the named tags: no slide on it
                settled_poses = tuple(p for p in marker_poses if not p.loose)
                t = time.perf_counter()
                slid = predict_slid_tags(video, locator=locator, camera=scene.calibrated_camera, poses=settled_poses,
                                         marker_set=scene.marker_set, carm_from_drill=first.carm_from_drill)
                if slid:
                    settled = predict_tag_places(locator=locator, camera=scene.calibrated_camera, poses=settled_poses,
                                                 marker_set=scene.marker_set, carm_from_drill=first.carm_from_drill,
                                                 carm_from_marker=first.carm_from_marker)
                    locator.recover(image, video, slid, placed_px=settled, by_place=False)
                    step_ms.append(1e3 * (time.perf_counter() - t))
                    slid_counts.append(sum(len(c) for c in slid.values()))
    return {"registration_ms": np.array(registration_ms), "step_ms": np.array(step_ms), "slid": np.array(slid_counts), "refused": refused}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=2300)
    ap.add_argument("--poses", type=int, default=2)
    args = ap.parse_args()
    m = measure(seeds=args.seeds, first_seed=args.first_seed, poses=args.poses)
    reg, step = m["registration_ms"], m["step_ms"]
    if reg.size == 0:
        raise SystemExit("every registration was refused: nothing to time")
    share = step.size / reg.size
    figures = [
        figure("registrations timed", float(reg.size), "count"),
        figure("registrations refused", float(m["refused"]), "count"),
        figure("registrations with a slid tag to look for", 100.0 * share, "%"),
        figure("slid predictions per such registration, median", float(np.median(m["slid"])) if m["slid"].size else 0.0, "count"),
        figure("joint registration, median", float(np.median(reg)), "ms", REFERENCE_FRAME_MS),
        figure("joint registration, 95th percentile", float(np.percentile(reg, 95)), "ms", REFERENCE_FRAME_MS),
    ]
    if step.size:
        figures += [
            figure("slide step where it runs, median", float(np.median(step)), "ms", REFERENCE_FRAME_MS),
            figure("slide step where it runs, max", float(step.max()), "ms", REFERENCE_FRAME_MS),
            figure("slide step, mean over all registrations", float(step.sum() / reg.size), "ms", REFERENCE_FRAME_MS),
        ]
    report("beam_slide", figures, seeds=args.seeds, first_seed=args.first_seed, poses=args.poses, ct_patient=CT.exists())


if __name__ == "__main__":
    main()
