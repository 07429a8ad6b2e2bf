"""markers.json honoured in full by the video locator: each marker's ArUco dictionary, id, tag size and offset."""

from dataclasses import replace

import numpy as np
import pytest

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.markers import MarkerSet
from drillnav.registration.video_markers import VideoMarkerLocator


@pytest.fixture(scope="module")
def mixed():
    """The twin's scene with one marker made differently: a 24 mm 4x4 tag (id 7) off-centre, 3 mm above its BBs."""
    scene = make_scene(seed=5, views="ap", render=False)
    odd = scene.marker_set.ids[0]
    change = dict(aruco_dictionary="DICT_4X4_50", aruco_id=7, tag_size_mm=24.0, tag_center_mm=np.array([1.5, -2.0, 3.0]))
    designs = tuple(replace(m, **change) if m.marker_id == odd else m for m in scene.marker_set.markers)
    manufactured = {i: replace(m, **change) if i == odd else m for i, m in scene.manufactured.items()}
    scene = replace(scene, marker_set=MarkerSet(markers=designs), manufactured=manufactured)
    return scene, odd, scene.render_camera(np.random.default_rng(3))


def test_every_marker_located_with_its_own_tag(mixed):
    scene, odd, image = mixed
    video = VideoMarkerLocator(camera=scene.calibrated_camera, marker_set=scene.marker_set).locate(image)
    assert sorted(video.by_id()) == sorted(scene.marker_set.ids)
    truth = scene.camera_from_marker()
    for m in video.markers:
        # X_D is the central BB: the tag's own offset is undone (about 1 mm is the depth error of a lone tag).
        assert np.linalg.norm(m.position_camera_mm - truth[m.marker_id][:3, 3]) < 2.0, m.marker_id


def test_single_size_locator_misses_the_odd_marker(mixed):
    scene, odd, image = mixed
    video = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids).locate(image)
    assert odd not in video.by_id()
    assert len(video.markers) == len(scene.marker_set.ids) - 1


def test_shared_aruco_id_refused(mixed):
    scene, odd, _ = mixed
    clash = MarkerSet(markers=tuple(replace(m, aruco_id=5, aruco_dictionary="DICT_6X6_250") for m in scene.marker_set.markers[:2]))
    with pytest.raises(ValueError, match="share ArUco id 5"):
        VideoMarkerLocator(camera=scene.calibrated_camera, marker_set=clash)
