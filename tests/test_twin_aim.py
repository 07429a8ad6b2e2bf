"""The twin surgeon can aim beside the plan ([twin_scene] aim_off_mm): every pose of the camera loop moves sideways by
that much, square to the corridor, and nothing else changes."""

import numpy as np

from drillnav.drivers.sim.devices import freehand_loop
from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, make_scene


def test_the_loop_aims_beside_the_corridor_by_the_offset_asked():
    scene = make_scene(seed=5, render=False)
    entry = scene.corridor_entry_carm_mm
    at = freehand_loop(scene, np.random.default_rng(5), loop_frames=30, keyposes=4)
    off = freehand_loop(scene, np.random.default_rng(5), loop_frames=30, keyposes=4, aim_off_mm=12.0)
    miss = lambda poses: np.array([np.linalg.norm(TRUE_DRILL_AXIS_CAMERA.transformed(p).closest_point(entry) - entry) for p in poses])  # noqa: E731
    assert miss(at).max() < 5.0
    assert 8.0 < miss(off).min() and miss(off).max() < 16.0
    for a, b in zip(at, off):
        np.testing.assert_allclose(a[:3, :3], b[:3, :3])  # the same orientations, moved sideways by 12 mm
        assert abs(np.linalg.norm(b[:3, 3] - a[:3, 3]) - 12.0) < 1e-9
    again = freehand_loop(scene, np.random.default_rng(5), loop_frames=30, keyposes=4, aim_off_mm=0.0)
    for a, b in zip(at, again):
        np.testing.assert_array_equal(a, b)
