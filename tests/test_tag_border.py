"""A tag's outline from the width of its black border (``registration/tag_border.py``).

An over-exposed frame clips the white base: each blurred step from the black border to it then has its apparent
middle on the dark side, every edge moves in and the tag looks small, so the camera puts it too far. The border's
second step, to a white code cell behind it, moves into the black by as much: the border looks thinner by twice
the shift, and the outline is moved back by it.
"""

import cv2
import numpy as np
import pytest

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.tag_border import border_shift_px, code_cells, moved_outline
from drillnav.registration.video_markers import VideoMarkerLocator, tag_object_points

from tag_frames import synthetic_tag_frame

TAG = 7
CAMERA = PinholeCamera.from_fov(width=640, height=480, horizontal_fov_deg=76.0)
# A 30 mm tag 90 mm from the camera, tilted 20 deg: its black border's outer corners (4, 2) px.
_ROTATION = cv2.Rodrigues(np.array([np.pi + np.radians(20.0), 0.0, 0.0]))[0] @ cv2.Rodrigues(np.array([0.0, np.radians(10.0), 0.2]))[0]
CORNERS = cv2.projectPoints(tag_object_points(30.0), cv2.Rodrigues(_ROTATION)[0], np.array([4.0, -2.0, 90.0]), CAMERA.camera_matrix,
                            CAMERA.distortion)[0].reshape(4, 2)


def _located(frame, *, border_shift: bool) -> np.ndarray:
    video = VideoMarkerLocator(camera=CAMERA, marker_ids=[TAG], border_shift=border_shift).locate(frame)
    return video.by_id()[TAG].corners_px


def _inward_px(corners: np.ndarray) -> float:
    """Mean offset (px) of ``corners`` from the truth towards the tag's centre."""
    centre = CORNERS.mean(axis=0)
    radial = (centre - CORNERS) / np.linalg.norm(centre - CORNERS, axis=1)[:, None]
    return float(np.mean(np.sum((corners - CORNERS) * radial, axis=1)))


def test_an_over_exposed_tag_is_put_back_where_it_is():
    frame = synthetic_tag_frame(CORNERS, aruco_id=TAG, blur_px=2.0, gain=1.6)
    assert np.mean(frame >= 250) > 0.05  # the base clips
    as_stepped, moved = _located(frame, border_shift=False), _located(frame, border_shift=True)
    # Seeded (a 144 px tag, 10 % of the frame clipped): the steps put the corners 0.88 px inside the truth (0.89 px
    # RMS); moved by the border's width, 0.08 px inside (0.17 px RMS, 0.14 px on the same frame unclipped).
    assert _inward_px(as_stepped) > 0.6, as_stepped - CORNERS
    assert abs(_inward_px(moved)) < 0.2, moved - CORNERS
    assert np.sqrt(np.mean(np.sum((moved - CORNERS) ** 2, axis=1))) < 0.5 * np.sqrt(np.mean(np.sum((as_stepped - CORNERS) ** 2, axis=1)))


def test_a_tag_whose_base_does_not_clip_is_left_as_it_is():
    frame = synthetic_tag_frame(CORNERS, aruco_id=TAG, blur_px=2.0, gain=1.0)
    shift, profiles = border_shift_px(frame.astype(np.float32), _located(frame, border_shift=False), code_cells("DICT_6X6_250", TAG))
    assert (shift, profiles) == (0.0, 0)
    assert np.allclose(_located(frame, border_shift=True), _located(frame, border_shift=False))
    assert abs(_inward_px(_located(frame, border_shift=True))) < 0.15


def test_the_shift_measured_on_the_truth_is_the_steps_bias():
    """Measured from the true outline, the shift says where the steps lie: inward of it by the clip's bias."""
    frame = synthetic_tag_frame(CORNERS, aruco_id=TAG, blur_px=2.0, gain=1.6)
    shift, profiles = border_shift_px(frame.astype(np.float32), CORNERS, code_cells("DICT_6X6_250", TAG))
    assert profiles >= 8
    assert shift == pytest.approx(0.0, abs=0.15)
    as_stepped = _located(frame, border_shift=False)
    shift, _ = border_shift_px(frame.astype(np.float32), as_stepped, code_cells("DICT_6X6_250", TAG))
    assert shift < -0.5  # the outline must move out


def test_moved_outline_moves_every_side_by_the_distance():
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    assert np.allclose(moved_outline(square, 1.0), [[1, 1], [9, 1], [9, 9], [1, 9]])
    assert np.allclose(moved_outline(square, -0.5), [[-0.5, -0.5], [10.5, -0.5], [10.5, 10.5], [-0.5, 10.5]])
    skewed = np.array([[0.0, 0.0], [12.0, 1.0], [11.0, 13.0], [-1.0, 10.0]])
    moved = moved_outline(skewed, 0.7)
    for k in range(4):  # each moved side is parallel to its own, 0.7 px in
        a, b = skewed[k], skewed[(k + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([-d[1], d[0]])
        n *= np.sign(np.dot(skewed.mean(axis=0) - a, n))
        assert np.dot(moved[k] - a, n) == pytest.approx(0.7)
        assert np.dot(moved[(k + 1) % 4] - a, n) == pytest.approx(0.7)


def test_the_code_cells_are_the_printed_tag():
    cells = code_cells("DICT_6X6_250", TAG)
    assert cells.shape == (8, 8)
    assert not cells[0].any() and not cells[-1].any() and not cells[:, 0].any() and not cells[:, -1].any()  # the black border
    assert cells[1:-1, 1:-1].any()
    assert code_cells("DICT_4X4_50", 3).shape == (6, 6)
