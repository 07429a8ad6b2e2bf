"""One intensifier view: the constellation's mirror image may not fit better than the truth by bending the image
into a barrel (``joint_solve.BARREL_SHARE``).

An image intensifier's input screen is curved and its output flat: its radial distortion is pincushion (outward at
the edge), never barrel. Twin seed 23702, markers stuck flat (``accuracy.py --marker-tilt 0,10``), the random
pair's first view alone, the first drill pose: two markers nearly in one plane, so in one view the pair has the
planar ambiguity of a single marker. Held by a prior symmetric about zero, the mirror image's solve took a barrel
distortion (-7.7 px at the field's corner; the truth's solve +12.2, the twin's intensifier +8) and fitted better
than the truth (chi-square 10.7 against 40.7): the axis came out 76.7 mm / 36.6 deg off under a 6.1 mm / 3.0 deg
bound (flagged, the bound over its limit, but a bound that did not reach the error).
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from twin_images import operating_room_scene  # noqa: E402  (tests/: the study's scene)

from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, render_fluoro
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.video_fluoro import predicted_axis_error


def _single_view_shot():
    import accuracy

    scene, k = operating_room_scene(23702, "random", marker_tilt_deg=(0.0, 10.0))
    image_rng = np.random.default_rng([23702, k, 1])
    name = next(iter(scene.views))
    detections = detect_in_view(render_fluoro(scene, name, image_rng), scene.views[name], scene.marker_set)
    poses = tuple(register_markers([detections], [scene.views[name]], scene.marker_set))
    pose, video, image = accuracy.camera_shots(scene, seed=23702, k=k, poses=1)[0]
    return scene, name, poses, pose, video, image


def test_the_mirror_image_of_a_flat_pair_takes_no_barrel_distortion():
    import accuracy

    scene, name, poses, pose, video, image = _single_view_shot()
    assert scene.views[name].distortion_sigma_px > 0  # an intensifier's view: its distortion is estimated
    video, reg = accuracy._register(scene, image, video, poses, joint=True)
    entry = scene.corridor_entry_carm_mm
    axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
    true_axis = TRUE_DRILL_AXIS_CAMERA.transformed(pose)
    off_mm = float(np.linalg.norm(axis.closest_point(entry) - true_axis.closest_point(entry)))
    pe = predicted_axis_error(video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=entry)
    # 76.7 mm under a 6.1 mm bound with the symmetric prior.
    assert off_mm <= pe.position90_mm and axis.angle_deg(true_axis) <= pe.angle90_deg, (off_mm, pe)
    assert off_mm < 5.0, off_mm
    for _, coefficients in reg.detector_distortion_px:
        assert coefficients[0] > -2.0, reg.detector_distortion_px  # no barrel beyond the prior's 1 px sigma
