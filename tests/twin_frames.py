"""Twin camera frames shared by test modules (not a test module itself)."""

import numpy as np

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.video_markers import VideoMarkerLocator

GLOVED_SEED, GLOVED_MARKER = 5000, 2


def gloved_frame():
    """Twin seed 5000 (inlet+outlet, the glove on), its first freehand frame, in which a gloved finger hides a corner
    of marker 2's tag and ArUco loses it: (scene, true carm_from_drill, frame (read-only), locator)."""
    scene = make_scene(seed=GLOVED_SEED, views="inlet,outlet", render=False, degradations=Degradations(glove=True))
    rng = np.random.default_rng(GLOVED_SEED)
    pose = scene.drill_pose_towards(rng, offset_mm=5.0, tilt_deg=5.0)
    image = scene.render_camera(rng, carm_from_drill=pose)
    image.setflags(write=False)
    locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)
    return scene, pose, image, locator
