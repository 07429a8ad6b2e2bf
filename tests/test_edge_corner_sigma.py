"""A detected tag states its corner noise from its own edges (``video_markers.edge_corner_sigma_px``).

Most of a tag's corner error moves its corners as another view of its square would: the tag's pose absorbs it and no
residual shows it. Its edges' scatter about their fitted lines does: on the twin under every camera degradation, a
640x480 frame's tags were 0.47 px off (independently of their shared shift and scale) where a 1280x720 frame's were
0.15 px, and the joint solve, re-estimating from residuals from 0.3 px, stated about 0.3 px for both; its angle bounds
then covered 82-83 % of the errors at 640x480.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from noise_decomposition import split  # noqa: E402  (the benchmark's split of a tag's error into shift, scale and rest)

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.transforms import apply, invert
from drillnav.registration.video_markers import EDGE_SIGMA_GAIN, EDGE_SIGMA_PER_SAMPLE, VideoMarkerLocator, edge_corner_sigma_px


def test_the_edges_scatter_and_the_blur_set_the_corner_noise():
    one = edge_corner_sigma_px(np.full(4, 0.2), 100.0, 3.0)
    assert one == pytest.approx(EDGE_SIGMA_GAIN * EDGE_SIGMA_PER_SAMPLE * 0.2 / np.sqrt(20.0))
    assert edge_corner_sigma_px(np.full(4, 0.4), 100.0, 3.0) == pytest.approx(2.0 * one)  # twice the scatter
    # A blur twice as wide leaves half the independent samples.
    assert edge_corner_sigma_px(np.full(4, 0.2), 100.0, 6.0) == pytest.approx(one * np.sqrt(2.0))
    # A sharp edge's samples count only as many as were taken; a tiny tag's at least two.
    assert edge_corner_sigma_px(np.full(4, 0.2), 400.0, 1.0, samples=24) == pytest.approx(EDGE_SIGMA_GAIN * EDGE_SIGMA_PER_SAMPLE * 0.2 / np.sqrt(24.0))
    assert edge_corner_sigma_px(np.full(4, 0.2), 10.0, 12.0) == pytest.approx(EDGE_SIGMA_GAIN * EDGE_SIGMA_PER_SAMPLE * 0.2 / np.sqrt(2.0))


def _stated_and_true(size: tuple[int, int]) -> tuple[float, float]:
    deg = Degradations.parse("motion_blur,defocus,tag_glare,glove,blood,mjpeg,colour,auto_exposure,surgeon_markers")
    stated, true = [], []
    for seed in (9200, 9201, 9202):
        scene = make_scene(seed=seed, views="inlet,outlet", render=False, degradations=deg, image_size=size)
        locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)
        pose_rng, camera_rng = np.random.default_rng([seed, 2]), np.random.default_rng([seed, 3])
        for _ in range(2):
            carm_from_drill = scene.drill_pose_towards(pose_rng, offset_mm=5.0, tilt_deg=5.0)
            seen = locator.locate(scene.render_camera(camera_rng, carm_from_drill=carm_from_drill))
            for v in seen.markers:
                truth = scene.true_camera.project(apply(invert(carm_from_drill) @ scene.carm_from_marker[v.marker_id],
                                                        scene.marker_set.by_id(v.marker_id).tag_corners_mm()))
                err = np.asarray(v.corners_px) - truth
                if np.linalg.norm(err, axis=1).max() > 4.0:
                    continue
                _, _, rest = split(err, truth)
                stated.append(v.edge_sigma_px)
                true.append(float(np.sqrt(np.sum(rest**2) / 5)))
    assert len(stated) >= 10, len(stated)
    return float(np.sqrt(np.mean(np.square(stated)))), float(np.sqrt(np.mean(np.square(true))))


def test_a_smaller_frames_tags_state_the_larger_noise_their_edges_show():
    stated_hd, true_hd = _stated_and_true((1280, 720))
    stated_vga, true_vga = _stated_and_true((640, 480))
    assert true_vga > 2.0 * true_hd  # the twin's smaller frame is the noisier (0.47 against 0.15 px over 8 seeds)
    assert stated_vga > 1.5 * stated_hd, (stated_vga, stated_hd)
    # Within a factor of two of what the tags were off, where the locator's fixed 0.1 px was five times under.
    assert 0.5 * true_vga < stated_vga < 2.0 * true_vga, (stated_vga, true_vga)
    assert 0.5 * true_hd < stated_hd < 2.0 * true_hd, (stated_hd, true_hd)
