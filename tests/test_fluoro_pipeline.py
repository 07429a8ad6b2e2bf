"""Fluoroscopy marker detection, marker poses in C, video-to-fluoro registration, on twin scenes."""

import numpy as np
import pytest

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.errors import MarkersNotFound
from drillnav.registration.fluoro_markers import detect_markers
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.transforms import from_rotvec
from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro
from drillnav.registration.video_markers import VideoMarkerLocator


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=5)


@pytest.fixture(scope="module")
def solved(scene):
    names = list(scene.views)
    dets = [detect_markers(scene.fluoro_log[n], scene.marker_set) for n in names]
    poses = register_markers(dets, [scene.views[n] for n in names], scene.marker_set)
    video = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids).locate(scene.camera_image)
    return dets, poses, video


def test_every_marker_identified_in_both_views(scene, solved):
    dets, _, _ = solved
    for det in dets:
        assert sorted(det.by_id()) == sorted(scene.carm_from_marker)
        for m in det.markers:
            assert (m.bb_index >= 0).all()


def test_marker_positions_in_carm_sub_half_mm(scene, solved):
    _, poses, _ = solved
    assert len(poses) == 5
    for p in poses:
        assert p.converged and p.n_views == 2
        assert np.linalg.norm(p.position_carm_mm - scene.carm_from_marker[p.marker_id][:3, 3]) < 0.5


def test_video_markers_localised(scene, solved):
    _, _, video = solved
    assert sorted(video.by_id()) == sorted(scene.carm_from_marker)
    truth = scene.camera_from_marker()
    err = [np.linalg.norm(m.position_camera_mm - truth[m.marker_id][:3, 3]) for m in video.markers]
    assert np.median(err) < 2.0


def test_drill_axis_registered(scene, solved):
    _, poses, video = solved
    reg = register_video_to_fluoro(video, poses, scene.marker_set, scene.calibrated_camera)
    axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
    truth = scene.drill_axis_carm
    assert np.linalg.norm(axis.closest_point(scene.corridor_entry_carm_mm) - truth.point_mm) < 2.5
    assert axis.angle_deg(truth) < 2.0
    assert max(reg.fre_mm.values()) < 2.5 and reg.rejected_ids == ()
    pe = predicted_axis_error(video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=scene.corridor_entry_carm_mm)
    assert 0 < pe.position_mm < 10 and 0 < pe.angle_deg < 10


def test_moved_marker_is_rejected_and_named(scene, solved):
    _, poses, video = solved
    moved_id = poses[0].marker_id
    bumped = tuple(
        type(p)(**{**p.__dict__, "carm_from_marker": from_rotvec([0, 0, 0], [12.0, 0, 0]) @ p.carm_from_marker}) if p.marker_id == moved_id else p
        for p in poses
    )
    reg = register_video_to_fluoro(video, bumped, scene.marker_set, scene.calibrated_camera)
    assert reg.rejected_ids == (moved_id,)
    assert reg.fre_mm[moved_id] > 8.0


def test_too_few_common_markers(scene, solved):
    _, poses, video = solved
    with pytest.raises(MarkersNotFound, match="only 2 marker"):
        register_video_to_fluoro(video, poses[:2], scene.marker_set, scene.calibrated_camera)


def test_blank_fluoro_finds_nothing(scene):
    det = detect_markers(np.random.default_rng(0).normal(2.0, 0.02, (976, 976)).astype(np.float32), scene.marker_set)
    assert det.markers == ()


def test_marker_cut_by_the_field_edge_is_reported_not_guessed(scene):
    img = scene.fluoro_log["inlet"]
    view = scene.views["inlet"]
    centres = view.project(np.array([t[:3, 3] for t in scene.carm_from_marker.values()]))
    # Shift the image so the left-most marker's ring crosses the left border.
    shift = int(centres[:, 0].min()) - 20
    moved = np.full_like(img, float(np.median(img)))
    moved[:, : img.shape[1] - shift] = img[:, shift:]
    det = detect_markers(moved, scene.marker_set)
    assert any("outside the field of view" in r.reason for r in det.rejected)
    assert len(det.markers) < len(scene.carm_from_marker)
    ids = [m.marker_id for m in det.markers]
    assert len(ids) == len(set(ids)) and set(ids) <= set(scene.carm_from_marker)
