"""The drill axis's error against the twin's truth, as the accuracy study scores it."""

import numpy as np

from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, Scene


def axis_error(scene: Scene, carm_from_drill, true_carm_from_drill) -> tuple[float, float]:
    """(mm at the corridor entry, deg) between the calibrated axis through ``carm_from_drill`` (4, 4) and the true
    axis through ``true_carm_from_drill`` (4, 4)."""
    entry = scene.corridor_entry_carm_mm
    axis = scene.calibrated_axis_drill.transformed(carm_from_drill)
    truth = TRUE_DRILL_AXIS_CAMERA.transformed(true_carm_from_drill)
    return float(np.linalg.norm(axis.closest_point(entry) - truth.closest_point(entry))), float(axis.angle_deg(truth))
