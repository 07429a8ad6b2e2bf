"""Runtime of the fluoroscopy path, beside the reference's Table 4.

Reference: fluoroscopy feature extraction 13.1 s; marker localisation (3D-2D) 139 s (1 view) / 175 s (2 views);
video-to-fluoro registration 1.5 ms per frame; overlay 40 ms per frame. The video-to-fluoro figures here are the joint
solve a registration's first frame runs (the frames after it track on its refinement: benchmarks/frame_path.py).
Run: .venv/bin/python benchmarks/fluoro_registration.py
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

from drillnav.drivers.fluoro_dicom import FluoroImage
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.overlay import draw_axis, draw_detections, to_display
from drillnav.registration.video_fluoro import register_video_to_fluoro
from drillnav.registration.video_markers import VideoMarkerLocator
from drillnav.service.fluoro_polarity import settle_polarity


def display_image(image_log: np.ndarray, view, name: str) -> FluoroImage:
    """The view as a fluoroscopy display stores it without stating its polarity (12 bits, metal dark), read both ways
    as drivers/fluoro_dicom.py reads such a file."""
    shown = np.round(4095.0 * np.clip(np.exp(-image_log) / np.percentile(np.exp(-image_log), 99.9), 0, 1))
    lo, hi = np.percentile(shown, [0.5, 99.5])
    as_range = ((shown - lo) / max(hi - lo, 1e-6) * 6.0).astype(np.float32)
    as_intensity = (-np.log(np.clip(shown, 1e-3, None) / max(np.percentile(shown, 99.5), 1e-3))).astype(np.float32)
    return FluoroImage(pixels_log=as_range, view=view, source_file=f"{name}.dcm", sop_class="XA", frame_index=0, geometry_source="positioner",
                       view_name=name, reading="metal bright", alternative_log=as_intensity, alternative_reading="metal dark")


def main() -> None:
    feat, unstated, reg1, reg2, v2f, v2f1, ovl = [], [], [], [], [], [], []
    for seed in range(5):
        scene = make_scene(seed=200 + seed)
        names = list(scene.views)
        dets = []
        for n in names:
            t = time.perf_counter()
            dets.append(detect_in_view(scene.fluoro_log[n], scene.views[n], scene.marker_set))
            feat.append(time.perf_counter() - t)
            shown = display_image(scene.fluoro_log[n], scene.views[n], n)
            t = time.perf_counter()
            settled = settle_polarity(shown, scene.marker_set)  # both readings detected, the one with more markers taken
            unstated.append(time.perf_counter() - t)
            assert settled.image.reading == "metal dark", settled.note
        t = time.perf_counter()
        poses1 = register_markers(dets[:1], [scene.views[names[0]]], scene.marker_set)
        reg1.append(time.perf_counter() - t)
        t = time.perf_counter()
        poses = register_markers(dets, [scene.views[n] for n in names], scene.marker_set)
        reg2.append(time.perf_counter() - t)
        video = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids).locate(scene.camera_image)
        for _ in range(20):
            t = time.perf_counter()
            reg = register_video_to_fluoro(video, poses, scene.marker_set, scene.calibrated_camera)
            v2f.append(time.perf_counter() - t)
        for _ in range(5):  # one view: the joint solve also tries the constellation's mirror (a registration's first frame)
            t = time.perf_counter()
            register_video_to_fluoro(video, poses1, scene.marker_set, scene.calibrated_camera)
            v2f1.append(time.perf_counter() - t)
        axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
        base = to_display(scene.fluoro_log[names[0]])
        for _ in range(10):
            t = time.perf_counter()
            draw_axis(draw_detections(base, dets[0]), scene.views[names[0]], axis, cone_half_angle_deg=1.0)
            ovl.append(time.perf_counter() - t)
    total2 = 2 * np.median(feat) + np.median(reg2)
    report("fluoro_registration", [
        figure("feature extraction per 976x976 view", float(np.median(feat)), "s", 13.1),
        figure("feature extraction per view, polarity unstated", float(np.median(unstated)), "s", 13.1),
        figure("marker registration 5 markers 1 view", float(np.median(reg1)), "s", 139.0),
        figure("marker registration 5 markers 2 views", float(np.median(reg2)), "s", 175.0),
        figure("shot to registration, 2 views (extraction + registration)", float(total2), "s", 175.0 + 2 * 13.1),
        figure("video-to-fluoro per frame", float(np.median(v2f)) * 1e3, "ms", 1.5),
        figure("video-to-fluoro joint solve, 1 view", float(np.median(v2f1)) * 1e3, "ms", 1.5),
        figure("overlay per frame", float(np.median(ovl)) * 1e3, "ms", 40.0),
    ], note="marker registration is point-based (BB correspondences, joint LM over views), not the reference's GI/CMA-ES")


if __name__ == "__main__":
    main()
