"""A tag whose code, read in part on its outline, identifies it among the whole dictionary stands alone in a registration.

A tag named among the posed markers was kept only beside another marker: a handful of cells can agree with a wanted
id by chance. A name read on 20 cells or more that meets the dictionary-wide rule of a tag found with no prediction
is no such chance; only its corners are loose (its outline's, its edges not fitted). On the operating-room twin
(seed 11702, the random pair, the study's second drill pose: every degradation, the real CT) the camera's frame is
defocused; ArUco finds no tag, marker 0's is glared and gloved, and marker 15's outline reads 32 cells, every one
agreeing with 15. The frame was refused ("only 0 marker(s) seen by both the camera and fluoroscopy"); it registers
on marker 15 alone, flagged unreliable, within its bound (1.3 mm off). Since the tags still missing are looked for where
such a registration puts them, marker 0's tag is then recovered there and the frame registers on both (0.9 mm).

A name that does not meet the dictionary-wide rule stands alone only in a frame otherwise refused, and only when the
cells read give no other tag of the marker set (every rotation) as good a fit: the registration is then flagged
unreliable whatever its bound (nothing checks the name). Seed 10402, the random pair, the second drill pose: marker 44's
tag, the one posed tag in the frame, is glared; 7 cells read, all agreeing with 44, no other tag of the set fitting
more than 5. The frame was refused with three markers identified in each view; it registers on 44 alone.
"""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from twin_images import operating_room_scene  # noqa: E402  (tests/: the study's scene of a seed and pair)

from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, render_fluoro
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.pipeline import _registration_with_named_tags
from drillnav.registration.video_fluoro import lone_name_unchecked, predicted_axis_error

SEED, POSE, MARKER = 11702, 1, 15


def test_a_tag_whose_partial_code_identifies_it_dictionary_wide_registers_alone():
    import accuracy

    scene, k = operating_room_scene(SEED, "random")
    image_rng = np.random.default_rng([SEED, k, 1])
    names = list(scene.views)
    dets = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in names}
    poses = tuple(register_markers([dets[n] for n in names], [scene.views[n] for n in names], scene.marker_set))
    pose, video, image = accuracy.camera_shots(scene, seed=SEED, k=k, poses=POSE + 1)[POSE]
    assert not video.markers, "ArUco finds a tag in the frame: the scene no longer tests it"
    entry = scene.corridor_entry_carm_mm
    truth = TRUE_DRILL_AXIS_CAMERA.transformed(pose)
    # The named tag alone: the frame's first registration (refused) gives way to it.
    alone = _registration_with_named_tags(image, video, locator=accuracy._locator(scene), camera=scene.calibrated_camera, poses=poses,
                                          every=poses, marker_set=scene.marker_set, used_before=0)
    assert alone is not None
    named_video, reg = alone
    assert tuple(reg.used_ids) == (MARKER,), reg.used_ids
    named = {m.marker_id: m for m in named_video.markers}[MARKER]
    assert named.named_among_posed and named.identified_by_code
    axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
    off_mm = float(np.linalg.norm(axis.closest_point(entry) - truth.closest_point(entry)))
    pe = predicted_axis_error(named_video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=entry)
    assert off_mm < 3.0, off_mm  # 0.8 mm (1.3 before rings were measured around their ellipses): the tag's outline corners place it loosely, one marker holds the drill
    assert off_mm <= pe.position90_mm and axis.angle_deg(truth) <= pe.angle90_deg
    assert not pe.reliable  # one marker, placed by its outline: flagged
    # The frame as the product registers it: 0's tag recovered where the registration on 15 puts it.
    video, reg = accuracy._register(scene, image, video, poses, joint=True)
    assert set(reg.used_ids) == {0, MARKER}, reg.used_ids
    assert {m.marker_id: m for m in video.markers}[0].recovered
    axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
    both_mm = float(np.linalg.norm(axis.closest_point(entry) - truth.closest_point(entry)))
    pe = predicted_axis_error(video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=entry)
    # 1.2 mm, within its bound: marker 15 alone is now as near (0.8 mm), its ring measured around its ellipse.
    assert both_mm < 2.0 and both_mm <= pe.position90_mm and axis.angle_deg(truth) <= pe.angle90_deg, (both_mm, off_mm)


def test_a_tag_named_among_the_whole_set_registers_alone_in_a_frame_otherwise_refused_and_is_flagged():
    import accuracy

    seed, pose_index, marker = 10402, 1, 44
    scene, k = operating_room_scene(seed, "random")
    image_rng = np.random.default_rng([seed, k, 1])
    names = list(scene.views)
    dets = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in names}
    poses = tuple(register_markers([dets[n] for n in names], [scene.views[n] for n in names], scene.marker_set))
    assert marker in {p.marker_id for p in poses}
    pose, video, image = accuracy.camera_shots(scene, seed=seed, k=k, poses=pose_index + 1)[pose_index]
    assert not video.markers, "ArUco finds a tag in the frame: the scene no longer tests it"
    video, reg = accuracy._register(scene, image, video, poses, joint=True)
    assert tuple(reg.used_ids) == (marker,), reg.used_ids
    named = video.by_id()[marker]
    assert named.named_among_posed and named.named_among_set and not named.identified_by_code
    assert lone_name_unchecked(reg, video)
    entry = scene.corridor_entry_carm_mm
    truth = TRUE_DRILL_AXIS_CAMERA.transformed(pose)
    axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
    off_mm = float(np.linalg.norm(axis.closest_point(entry) - truth.closest_point(entry)))
    pe = predicted_axis_error(video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=entry, position_limit_mm=100.0, angle_limit_deg=100.0)
    assert off_mm < 5.0, off_mm  # 3.1 mm measured
    assert off_mm <= pe.position90_mm  # 3.1 under 3.2 mm
    # Its angle, 1.6 deg, lies beyond its 90 % bound (1.2 deg), as a tenth of errors should: shown, flagged.
    assert axis.angle_deg(truth) < 2.5
    assert not pe.reliable  # flagged although its bounds lie within these (wide) limits: the name is unchecked


def test_a_name_among_the_set_on_an_outline_whose_edges_were_not_fitted_does_not_stand_alone():
    """Seed 3001, the inlet+outlet pair, first drill pose: marker 41's tag, its code read in part, is named among the
    whole set, but the tag runs off the frame's bottom edge: its outline's two lower corners lie on that edge (its edges
    not fitted) and lie 12 and 28 px from the tag's. Alone it put the axis 36.7 mm off (in the study's three-marker subsets
    without marker 14): it is a hypothesis only, kept beside another marker that bears it out, as before."""
    import accuracy

    from drillnav.registration.tag_hypotheses import OUTLINE_CORNER_SIGMA_PX
    from drillnav.registration.cut_corners import cut_corner_slides_px

    scene, k = operating_room_scene(3001, "inlet+outlet")
    _, video, image = accuracy.camera_shots(scene, seed=3001, k=k, poses=1)[0]
    named = {m.marker_id: m for m in accuracy._locator(scene).name_among_posed(image, replace(video, markers=()), [16, 41])}
    assert 41 in named, "marker 41's outline is no longer named: the frame no longer tests it"
    bitten = named[41]
    # Its two corners on the frame's edge slide along their sides (across them it fits a view of its square).
    slides = cut_corner_slides_px(bitten.corners_px, width=scene.calibrated_camera.width, height=scene.calibrated_camera.height)
    assert bitten.corner_sigma_px == OUTLINE_CORNER_SIGMA_PX and int(np.sum(np.any(slides != 0, axis=1))) == 2
    assert not bitten.named_among_set
