"""A registration on one marker whose fluoroscopy pose leaves its mirror open over two views.

The camera ties the drill rigidly to the marker's tag, so with one marker it cannot tell which of the marker's
orientations in frame C is the true one: a mirror the views leave open turns the drill with it. On the operating-room
twin (seed 11702, AP+lateral, the study's second drill pose: every degradation, the real CT) the registration rested on
marker 15 alone, whose fluoroscopy pose was 27 deg off with its mirror open; the axis came out 75 mm and 31 deg off at
the corridor's entry under a 90 % bound of 6.7 mm. The joint solve now starts again from each other solution the
marker's views leave open, keeps the better, and keeps the other open when it fits nearly as well, so the bound
reaches it (``video_fluoro._settle_lone_marker_mirror``); the recovery then looks for the missing tags where either
solution puts them, and names one found there by its place (marker 0's, here). The other solution is the best of
those that turn the drill otherwise: a start that reaches the best solution again does not stand in for it (seed
10901, below).
"""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from twin_images import operating_room_scene  # noqa: E402  (tests/: the study's scene of a seed and pair)

from drillnav.drivers.sim.scene import PAPER_CARM, TRUE_DRILL_AXIS_CAMERA, render_fluoro
from drillnav.registration import fluoro_markers
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro

SEED, POSE, MARKER = 11702, 1, 15


def _frame(seed: int, pose_index: int, **scene_args):
    """The study's AP+lateral frame of ``seed`` at drill pose ``pose_index`` (``scene_args``: the twin's, e.g. ``carm``):
    (scene, marker poses over both views, true carm_from_drill, the detector's tags, the camera frame, off_mm) with
    ``off_mm(carm_from_drill)`` the axis's distance from the truth at the corridor's entry."""
    import accuracy

    scene, k = operating_room_scene(seed, "ap+lateral", **scene_args)
    image_rng = np.random.default_rng([seed, k, 1])
    dets = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in scene.views}
    poses = tuple(register_markers([dets[n] for n in ("ap", "lateral")], [scene.views[n] for n in ("ap", "lateral")], scene.marker_set))
    pose, video, image = accuracy.camera_shots(scene, seed=seed, k=k, poses=pose_index + 1)[pose_index]
    entry = scene.corridor_entry_carm_mm
    truth = TRUE_DRILL_AXIS_CAMERA.transformed(pose).closest_point(entry)

    def off_mm(carm_from_drill):
        return float(np.linalg.norm(TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill).closest_point(entry) - truth))

    return scene, poses, pose, video, image, off_mm


def test_one_marker_with_its_mirror_open_over_two_views_is_bounded_by_the_mirror(monkeypatch):
    import accuracy

    # The lateral view identified no other marker the camera sees while rings under a quarter as wide as long were
    # taken for edge-on; from 0.2 it identifies more and the registration no longer rests on marker 15 alone. The
    # former limit recreates the case this tests.
    monkeypatch.setattr(fluoro_markers, "EDGE_ON_MINOR_RATIO", 0.25)

    scene, poses, pose, video, image, off_mm = _frame(SEED, POSE)
    lone = {p.marker_id: p for p in poses}[MARKER]
    assert lone.n_views == 2 and lone.mirror_carm_from_marker is not None, "marker 15's mirror is no longer open: the scene no longer tests it"
    found, whole = accuracy._register(scene, image, video, poses, joint=True)
    assert MARKER in {m.marker_id for m in found.markers}
    # The frame's tags as found, but for marker 15's alone: the registration on it (the frame's first, before the
    # recovery named marker 0's tag by the place either solution puts it).
    video = replace(found, markers=tuple(m for m in found.markers if m.marker_id == MARKER))
    reg = register_video_to_fluoro(video, poses, scene.marker_set, scene.calibrated_camera)
    assert tuple(reg.used_ids) == (MARKER,), reg.used_ids
    entry = scene.corridor_entry_carm_mm
    # The better of the two is the true one (4.2 mm, one marker's error); the mirror (75 mm off) is kept open.
    assert off_mm(reg.carm_from_drill) < 10.0
    assert reg.mirror_carm_from_drill is not None and off_mm(reg.mirror_carm_from_drill) > 50.0
    pe = predicted_axis_error(video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=entry)
    assert not pe.reliable
    assert pe.position90_mm >= off_mm(reg.mirror_carm_from_drill)  # the bound reaches the mirror's axis
    # With the whole recovery, marker 0's tag, found where the mirror's solution puts it, settles it: 2.0 mm off under
    # a 2.3 mm bound.
    assert set(whole.used_ids) == {0, MARKER}, whole.used_ids
    assert whole.mirror_carm_from_drill is None and off_mm(whole.carm_from_drill) < 3.0
    pe = predicted_axis_error(found, poses, whole, scene.calibrated_axis_drill, working_point_carm_mm=entry)
    assert off_mm(whole.carm_from_drill) <= pe.position90_mm


SEED_10901 = 10901
OTHER_CARM = dict(PAPER_CARM, source_to_detector_mm=1000.0, source_to_isocenter_mm=600.0)


def test_a_start_that_reaches_the_best_again_does_not_close_the_mirror():
    """The camera's detector finds marker 14's tag alone; marker 14 is posed in the AP view with two BBs claimed in the
    lateral one. From one of its planar solutions (3.4 deg from the joint solve's pose) the solve reached that same pose
    again, 19.6 deg off the truth (chi-square 37.6); from the other, a pose 1.5 deg off (38.8). The first start's copy
    stood in for the mirror, which was then closed: the axis lay 46 mm off under a 6.5 mm bound. Both fit alike, so
    the mirror stays open and the bound reaches it (the registration before any tag is recovered)."""
    import accuracy

    scene, poses, pose, video, image, off_mm = _frame(SEED_10901, 1, carm=OTHER_CARM)
    assert sorted(m.marker_id for m in video.markers) == [14], "the detector finds other tags: the scene no longer tests a lone marker"
    video, reg = accuracy._register(scene, image, video, poses, joint=True, recover=False)
    assert tuple(reg.used_ids) == (14,)
    assert reg.mirror_carm_from_drill is not None
    # The axis drawn is the better fit, the wrong one; the one left open is the true one.
    assert off_mm(reg.carm_from_drill) > 30.0 and off_mm(reg.mirror_carm_from_drill) < 10.0
    pe = predicted_axis_error(video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=scene.corridor_entry_carm_mm)
    assert not pe.reliable
    assert pe.position90_mm >= off_mm(reg.carm_from_drill)


def test_a_tag_where_the_open_mirror_puts_it_is_named_by_its_place():
    """The same frame with the recovery: marker 3's tag, glared, lies within 1 px of where the mirror puts it. Its code
    read in part does not name it against marker 16 (posed in both views, a rival by code); neither solution puts 16's
    tag there, so it is named by its place, and the registration on markers 3 and 14 settles the mirror (0.7 mm off)."""
    import accuracy

    scene, poses, pose, video, image, off_mm = _frame(SEED_10901, 1, carm=OTHER_CARM)
    found, reg = accuracy._register(scene, image, video, poses, joint=True)
    assert set(reg.used_ids) == {3, 14}, reg.used_ids
    assert next(m for m in found.markers if m.marker_id == 3).recovered
    assert reg.mirror_carm_from_drill is None
    assert off_mm(reg.carm_from_drill) < 2.0
    pe = predicted_axis_error(found, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=scene.corridor_entry_carm_mm)
    assert pe.reliable and off_mm(reg.carm_from_drill) <= pe.position90_mm
