"""A tag ArUco decodes under the wrong id, or an id decoded at two places (``VideoMarkerLocator.locate``).

ArUco corrects bit errors: a foreshortened, blurred tag can decode as another id of the dictionary. On the twin
(seed 3010, every camera degradation, second drill pose) marker 25's tag decoded as 43 while 43's own tag was
decoded too; the frame then held two markers 43, one 250 px from its tag, and the registration took whichever came
last. A decoded tag whose code cells, read again through its refined corners, another id of the marker set fits
better than its own is now set aside and named on ``misread_ids``; an id decoded at two places names neither. On a
real photograph's small blurred tags the cells read again disagree with the right id in up to 8 of 23 cells: such
tags, rightly decoded, must stand.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from tag_detection import _true_corners  # noqa: E402  (the twin's true corners, as the detection benchmark scores them)
from tag_frames import synthetic_tag_frame  # noqa: E402

from drillnav.drivers.sim.degradations import CAMERA as CAMERA_DEGRADATIONS
from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.aruco_detect import detect_aruco
from drillnav.registration.camera import PinholeCamera
from drillnav.schemas.calibration import camera_calibration_from_json
from drillnav.schemas.camera_yaml import from_opencv_yaml
from drillnav.registration.video_markers import VideoMarkerLocator, tag_object_points
from drillnav.schemas import messages as msg

CAMERA = PinholeCamera.from_fov(width=640, height=480, horizontal_fov_deg=76.0)
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MISREAD_SEED, MISREAD_POSE, READ_AS, TRUE_MARKER = 3010, 1, 43, 25


def _twin_frame():
    scene = make_scene(seed=MISREAD_SEED, render=False, degradations=Degradations.parse(",".join(CAMERA_DEGRADATIONS)))
    pose_rng, camera_rng = np.random.default_rng([MISREAD_SEED, 2]), np.random.default_rng([MISREAD_SEED, 3])
    for _ in range(MISREAD_POSE + 1):  # the detection benchmark's poses, in order (benchmarks/tag_detection.py)
        pose = scene.drill_pose_towards(pose_rng, offset_mm=5.0, tilt_deg=5.0)
        frame = scene.render_camera(camera_rng, carm_from_drill=pose)
    return scene, frame, _true_corners(scene, pose)


def test_a_tag_decoded_under_another_markers_id_is_set_aside():
    scene, frame, truth = _twin_frame()
    locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_set=scene.marker_set)
    # ArUco itself reads the id twice: once at 43's tag, once at 25's.
    gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
    small = cv2.resize(gray, (gray.shape[1] // 2, gray.shape[0] // 2), interpolation=cv2.INTER_AREA)
    ids, corners = detect_aruco(locator._detectors["DICT_6X6_250"][1], small)
    at_25 = [np.linalg.norm(c.reshape(4, 2).mean(axis=0) * 2.0 - truth[TRUE_MARKER].mean(axis=0)) < 5.0 for c in corners]
    assert sum(i == READ_AS for i in ids) == 2 and any(a and i == READ_AS for i, a in zip(ids, at_25)), \
        f"ArUco no longer misreads marker {TRUE_MARKER}'s tag: the frame no longer tests the check ({ids})"
    video = locator.locate(frame)
    assert video.misread_ids == (READ_AS,)
    found = video.by_id()
    assert [m.marker_id for m in video.markers].count(READ_AS) == 1
    assert np.linalg.norm(found[READ_AS].corners_px - truth[READ_AS], axis=1).max() < 1.0  # its own tag, not 25's
    # No marker is posed at 25's tag under another id.
    for m in video.markers:
        if m.marker_id != TRUE_MARKER:
            assert np.linalg.norm(m.corners_px.mean(axis=0) - truth[TRUE_MARKER].mean(axis=0)) > 20.0, m.marker_id
    wire = msg.VideoMarkers(stamp_ns=1, image_size=video.image_size, markers=(), misread_ids=video.misread_ids).to_bytes()
    assert msg.VideoMarkers.from_bytes(wire).misread_ids == (READ_AS,)


def _tag_at(shift_x: float):
    r = cv2.Rodrigues(np.array([np.pi + np.radians(15.0), 0.0, 0.0]))[0]
    return cv2.projectPoints(tag_object_points(30.0), cv2.Rodrigues(r)[0], np.array([shift_x, 0.0, 130.0]), CAMERA.camera_matrix,
                             CAMERA.distortion)[0].reshape(4, 2)


def test_an_id_decoded_at_two_places_names_neither():
    left, right = _tag_at(-45.0), _tag_at(45.0)
    a, b = synthetic_tag_frame(left, aruco_id=7), synthetic_tag_frame(right, aruco_id=7)  # same background (seed 0)
    frame = np.where(np.arange(a.shape[1])[None, :] < a.shape[1] // 2, a, b)
    locator = VideoMarkerLocator(camera=CAMERA, marker_ids=[7, 8])
    ids, _ = detect_aruco(locator._detectors["DICT_6X6_250"][0], frame)
    assert sorted(ids) == [7, 7], ids
    video = locator.locate(frame)
    assert video.markers == () and video.misread_ids == (7,)
    # Either tag alone is found, and is no misread.
    alone = locator.locate(a)
    assert [m.marker_id for m in alone.markers] == [7] and alone.misread_ids == ()
    assert np.linalg.norm(alone.markers[0].corners_px - left, axis=1).max() < 0.5


@pytest.mark.parametrize("gain", [0.5, 1.0, 1.5])
@pytest.mark.parametrize("blur_px", [1.5, 2.0, 2.5])
def test_rightly_decoded_tags_of_a_real_photograph_stand_though_their_cells_read_poorly(gain, blur_px):
    """The ChArUco photograph's 17 tags (26 px, 3 px cells), exposed at ``gain`` and blurred: every tag ArUco decodes
    lies where the sharp photograph puts that id, and none of them is set aside (the first rule tried, 2 cells and 10 %
    of those read disagreeing, set aside 1-4 of them in 8 of these 9 conditions; another id fitting as well as the
    tag's own, one in 2)."""
    image = cv2.imread(str(DATA / "aruco" / "choriginal.jpg"))
    camera = camera_calibration_from_json(from_opencv_yaml((DATA / "aruco" / "tutorial_camera_charuco.yml").read_text()))
    locator = VideoMarkerLocator(camera=camera, marker_ids=range(17), tag_size_mm=20.0)
    sharp = locator.locate(image).by_id()
    assert sorted(sharp) == list(range(17))
    frame = cv2.GaussianBlur(np.clip(image.astype(np.float64) * gain, 0, 255), (0, 0), blur_px).astype(np.uint8)
    ids, corners = detect_aruco(locator._detectors["DICT_6X6_250"][0], cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    assert ids, "ArUco decodes nothing: the condition no longer tests the check"
    for i, c in zip(ids, corners):
        assert np.linalg.norm(c.reshape(4, 2).mean(axis=0) - sharp[i].corners_px.mean(axis=0)) < 5.0
    video = locator.locate(frame)
    assert video.misread_ids == ()
