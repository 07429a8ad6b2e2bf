"""A ring that identifies no marker, matched against each marker alone: a hypothesis the camera's constellation settles
(the view: tests/loose_scene.py)."""

from dataclasses import replace

import numpy as np
import pytest

from drillnav.drivers.sim.scene import make_scene, render_fluoro
from drillnav.registration.errors import MarkersNotFound
from drillnav.registration.fluoro_markers import LOOSE_MAX_COST_MM, detect_markers
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.video_claims import LOOSE_MIN_CLAIMED_BBS, corroborate_loose
from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro
from drillnav.registration.video_markers import VideoMarkerLocator

from axis_errors import axis_error
from loose_scene import VIEW, loose_shot


@pytest.fixture(scope="module")
def shot():
    scene, bare, ring_id, others, image, carm_from_drill = loose_shot()
    video = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids).locate(image)
    assert len(video.markers) == 3
    return scene, bare, ring_id, list(others), video, carm_from_drill


def test_a_loose_match_is_posed_as_a_hypothesis_that_counts_for_nothing_alone(shot):
    scene, bare, ring_id, others, video, _ = shot
    poses = register_markers([bare], [scene.views[VIEW]], scene.marker_set)
    by_id = {p.marker_id: p for p in poses}
    hyp = by_id[ring_id]
    assert hyp.loose and hyp.needs_camera and hyp.converged
    assert np.linalg.norm(hyp.position_carm_mm - scene.carm_from_marker[ring_id][:3, 3]) < 3.0
    # The wrong design does not fit the ring's BBs as one plane (seeded: 30.8 px RMS): no pose, no hypothesis.
    assert others[0] not in by_id
    # The camera sees only the ring's own marker: nothing bears the hypothesis out, and nothing registers.
    alone = replace(video, markers=tuple(m for m in video.markers if m.marker_id == ring_id))
    with pytest.raises(MarkersNotFound, match="only 0 marker"):
        register_video_to_fluoro(alone, poses, scene.marker_set, scene.calibrated_camera)


def test_the_camera_constellation_bears_out_the_right_hypothesis_and_registers(shot):
    scene, bare, ring_id, others, video, carm_from_drill = shot
    poses = register_markers([bare], [scene.views[VIEW]], scene.marker_set)
    reg = register_video_to_fluoro(video, poses, scene.marker_set, scene.calibrated_camera)
    assert sorted(reg.used_ids) == sorted(scene.carm_from_marker), "the other two markers claim their BBs through the constellation"
    kept = {p.marker_id: p for p in reg.marker_poses}
    assert kept[ring_id].needs_camera and not kept[ring_id].loose
    mm, deg = axis_error(scene, reg.carm_from_drill, carm_from_drill)
    assert mm < 2.0 and deg < 1.0
    pe = predicted_axis_error(video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=scene.corridor_entry_carm_mm)
    assert pe.reliable


def test_a_wrong_identity_puts_the_constellation_where_no_bbs_are(shot):
    scene, bare, ring_id, others, video, _ = shot
    poses = register_markers([bare], [scene.views[VIEW]], scene.marker_set)
    right = next(p for p in poses if p.marker_id == ring_id)
    # The same ring taken for another marker the camera sees (its pose as fitted, its id wrong).
    wrong = replace(right, marker_id=others[1])
    chosen = corroborate_loose(video, (), (wrong, right), scene.marker_set)
    ids = {p.marker_id for p in chosen}
    assert ring_id in ids and not any(p.loose for p in chosen)
    claimed = sum(len(o[1]) for p in chosen for o in p.observations) - sum(len(o[1]) for o in right.observations)
    assert claimed >= LOOSE_MIN_CLAIMED_BBS
    # Alone, the wrong identity is not borne out: nothing is added.
    assert corroborate_loose(video, (), (wrong,), scene.marker_set) == ()


def test_the_detector_matches_a_rejected_ring_against_each_marker_alone():
    # Marker BBs built 0.5 mm off their design (the twin's default is 0.05 mm): seed 23's marker 12 matches its
    # design at over identify's 0.9 mm in the inlet view, and its ring carries the loose match to marker 12.
    scene = make_scene(seed=23, views="inlet", render=False, bb_manufacturing_sigma_mm=0.5)
    det = detect_markers(render_fluoro(scene, "inlet", np.random.default_rng(23)), scene.marker_set)
    (ring,) = [r for r in det.rejected if r.candidate is not None and r.candidate.marker_id == 12]
    match = {m.marker_id: m for m in ring.loose}[12]
    assert abs(match.identification_cost_mm - ring.candidate.identification_cost_mm) < 1e-9
    assert all(m.identification_cost_mm <= LOOSE_MAX_COST_MM and (m.bb_index >= 0).sum() >= 4 for m in ring.loose)
    # Rings rejected for another reason (edge-on, too few BBs, overlapping) carry none.
    assert all(not r.loose for r in det.rejected if not r.reason.startswith(("no marker matches", "ambiguous")))


def test_a_loose_hypothesis_whose_tag_the_detector_missed_is_named_and_borne_out(shot):
    """The ring's own tag missed by ArUco (a glove, a highlight): the frame shares no posed marker with fluoroscopy and
    is refused, unless the tag whose code reads is named among the markers fluoroscopy holds, hypotheses included.
    (Twin seed 8005's AP+lateral pair, first frame, was refused for want of it; 0.66 mm once named.)"""
    from drillnav.registration.pipeline import register_with_recovery

    scene, bare, ring_id, others, video, carm_from_drill = shot
    poses = tuple(register_markers([bare], [scene.views[VIEW]], scene.marker_set))
    assert [p.marker_id for p in poses if p.loose] == [ring_id] and not [p for p in poses if not p.loose]
    image = loose_shot()[4]
    missed = replace(video, markers=tuple(m for m in video.markers if m.marker_id != ring_id))
    locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)
    common = dict(locator=locator, camera=scene.calibrated_camera, poses=poses, marker_set=scene.marker_set)
    with pytest.raises(MarkersNotFound, match="only 0 marker"):
        register_with_recovery(image, missed, name_outlines=False, **common)
    found, reg = register_with_recovery(image, missed, **common)
    named = [m for m in found.markers if m.named_among_posed]
    assert [m.marker_id for m in named] == [ring_id]
    np.testing.assert_allclose(named[0].corners_px, video.by_id()[ring_id].corners_px, atol=3.0)
    assert sorted(reg.used_ids) == sorted(scene.carm_from_marker)
    mm, deg = axis_error(scene, reg.carm_from_drill, carm_from_drill)
    assert mm < 2.0 and deg < 1.0
    # Named as another marker of the scene (one whose tag the frame then lacks too), the hypothesis is not borne out.
    right = VideoMarkerLocator.name_among_posed
    wrong = lambda self, *a: tuple(replace(m, marker_id=others[0]) for m in right(self, *a))  # noqa: E731
    fewer = replace(missed, markers=tuple(m for m in missed.markers if m.marker_id != others[0]))
    assert ring_id in register_with_recovery(image, fewer, **common)[1].used_ids  # named rightly, that frame registers
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(VideoMarkerLocator, "name_among_posed", wrong)
        with pytest.raises(MarkersNotFound):
            register_with_recovery(image, fewer, **common)
