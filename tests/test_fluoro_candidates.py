"""A ring whose BB pattern matches a marker only at a looser cost: an identity the camera must corroborate.

The twin's markers here are built with 0.5 mm BB errors (0.05 mm by default), so that a pattern matches its
design at over identify's 0.9 mm: seed 23's marker 12 matches at 1.08-1.18 mm in both views.
"""

import cv2
import numpy as np
import pytest

from drillnav.drivers.sim.scene import make_scene, render_fluoro
from drillnav.registration.fluoro_markers import (CORROBORATED_MAX_COST_MM, IDENTIFY_MAX_COST_MM, DetectedBB, DetectedMarker, FluoroDetections,
                                                  RejectedRing, detect_markers)
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.transforms import apply, make_transform
from drillnav.registration.video_fluoro import register_video_to_fluoro
from drillnav.registration.video_markers import VideoDetections, VideoMarker, tag_object_points

LOOSE_ID = 12


@pytest.fixture(scope="module")
def shot():
    scene = make_scene(seed=23, views="inlet,outlet", render=False, bb_manufacturing_sigma_mm=0.5)
    rng = np.random.default_rng(23)
    detections = {n: detect_markers(render_fluoro(scene, n, rng), scene.marker_set) for n in scene.views}
    return scene, detections


def test_a_loosely_matched_ring_is_a_candidate_not_a_marker(shot):
    scene, detections = shot
    for name, det in detections.items():
        assert LOOSE_ID not in det.by_id()
        (candidate,) = [c for c in det.candidates() if c.marker_id == LOOSE_ID]
        assert IDENTIFY_MAX_COST_MM < candidate.identification_cost_mm <= CORROBORATED_MAX_COST_MM
        view = scene.views[name]
        truth_px = view.project(scene.carm_from_marker[LOOSE_ID][:3, 3][None])[0]
        assert np.linalg.norm(np.asarray(candidate.ring_ellipse[0]) - truth_px) < 10.0
        # The ring stays among the rejected, with its reason: nothing downstream takes it for identified.
        assert any(r.candidate is candidate and r.reason.startswith("no marker matches") for r in det.rejected)


def test_a_candidate_is_posed_as_needing_the_camera(shot):
    scene, detections = shot
    poses = {p.marker_id: p for p in register_markers(list(detections.values()), list(scene.views.values()), scene.marker_set)}
    loose = poses[LOOSE_ID]
    assert loose.needs_camera and loose.n_views == 2
    assert np.linalg.norm(loose.position_carm_mm - scene.carm_from_marker[LOOSE_ID][:3, 3]) < 1.5
    assert not any(p.needs_camera for i, p in poses.items() if i != LOOSE_ID)


def _video(scene, carm_from_drill, ids):
    camera = scene.true_camera
    markers = []
    for i, camera_from_marker in sorted(scene.camera_from_marker(carm_from_drill).items()):
        if i not in ids:
            continue
        design = scene.marker_set.by_id(i)
        corners = camera.project(apply(camera_from_marker, design.tag_corners_mm()))
        tag = tag_object_points(design.tag_size_mm)
        _, rv, tv = cv2.solvePnP(tag, corners, camera.camera_matrix, camera.distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        camera_from_tag = make_transform(cv2.Rodrigues(rv)[0], tv.ravel())
        markers.append(VideoMarker(marker_id=i, corners_px=corners, camera_from_tag=camera_from_tag, reprojection_error_px=0.0,
                                   position_camera_mm=apply(camera_from_tag, -np.asarray(design.tag_center_mm)), covariance_mm2=0.01 * np.eye(3)))
    return VideoDetections(markers=tuple(markers), ignored_ids=(), image_size=(camera.width, camera.height))


def test_the_camera_corroborates_a_candidate_or_it_is_left_out(shot):
    scene, detections = shot
    poses = register_markers(list(detections.values()), list(scene.views.values()), scene.marker_set)
    carm_from_drill = scene.drill_pose_towards(np.random.default_rng(4), offset_mm=5.0, tilt_deg=5.0)
    others = sorted(i for i in scene.carm_from_marker if i != LOOSE_ID and any(p.marker_id == i and not p.needs_camera for p in poses))[:2]
    # The camera sees two identified markers and not the candidate: the candidate is not in the registration.
    without = register_video_to_fluoro(_video(scene, carm_from_drill, set(others)), poses, scene.marker_set, scene.true_camera)
    assert LOOSE_ID not in without.used_ids and LOOSE_ID not in without.carm_from_marker
    # Its tag seen, it counts.
    with_it = register_video_to_fluoro(_video(scene, carm_from_drill, set(others) | {LOOSE_ID}), poses, scene.marker_set, scene.true_camera)
    assert LOOSE_ID in with_it.used_ids


def _marker(marker_id: int, centres) -> DetectedMarker:
    bbs = tuple(DetectedBB(center_px=np.array(c, dtype=float), diameter_px=8.0, large=False) for c in centres)
    return DetectedMarker(marker_id=marker_id, bbs=bbs, bb_index=np.arange(len(bbs)), ring_ellipse=((0.0, 0.0), (60.0, 60.0), 0.0), mirrored=False,
                          identification_cost_mm=1.0)


def test_candidates_are_one_per_id_and_none_for_an_identified_id():
    a = _marker(3, [(0, 0), (10, 0), (0, 10), (10, 10)])
    same_bbs = _marker(3, [(0, 0), (10, 0), (0, 10)])
    elsewhere = _marker(4, [(100, 100), (110, 100), (100, 110), (110, 110)])
    elsewhere_again = _marker(4, [(300, 300), (310, 300), (300, 310), (310, 310)])
    identified = _marker(5, [(500, 500), (510, 500), (500, 510), (510, 510)])
    rejected = tuple(RejectedRing(reason="no marker matches", center_px=np.zeros(2), candidate=m)
                     for m in (a, same_bbs, elsewhere, elsewhere_again, identified))
    det = FluoroDetections(markers=(identified,), rejected=rejected)
    # Two pieces of one ring (3 BBs shared) are one candidate; one id on two different rings is not guessed;
    # an id the view identified is no candidate.
    assert [m.marker_id for m in det.candidates()] == [3]
