"""ArUco detection through the product's one wrapper: "no tag" is an empty result whatever OpenCV's version returns."""

import cv2
import numpy as np

from drillnav.registration.aruco_detect import detect_aruco


def _detector() -> cv2.aruco.ArucoDetector:
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250))


def test_a_frame_without_a_tag_gives_two_empty_lists():
    assert detect_aruco(_detector(), np.full((480, 640), 120, np.uint8)) == ([], [])


def test_a_printed_tag_gives_its_id_and_its_four_corners():
    tag = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250), 17, 160)
    frame = np.full((480, 640), 255, np.uint8)
    frame[100:260, 200:360] = tag
    ids, corners = detect_aruco(_detector(), frame)
    assert ids == [17]
    assert corners[0].shape == (4, 2) and corners[0].dtype == np.float64
    # Clockwise from the tag's top-left; the pixel grid's corners lie half a pixel outside the pixel centres.
    expected = np.array([[199.5, 99.5], [359.5, 99.5], [359.5, 259.5], [199.5, 259.5]])
    assert np.abs(corners[0] - expected).max() < 1.0
