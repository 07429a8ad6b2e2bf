"""A glove or a highlight's halo over a tag lifts black code cells to white: the recovery leaves the cells beside
such a sign unread (``read_code(covers=True)``) instead of counting them against the tag's id.

Twin seed 11701, the markers flat on the skin (``--marker-tilt 0,10``), AP + lateral, the study's second drill pose:
marker 24's tag, a glove over one corner and a highlight on its middle, read 7 of 8 cells agreeing with its id (one
black cell under the glove read white) and was refused, from where the registration on markers 3 and 33 put it and at
its true corners alike; the axis was 2.89 mm off. Read with the rule, its 7 cells all agree, the tag is recovered
and the registration uses marker 24.
"""

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from tag_detection import _true_corners  # noqa: E402  (the twin's true corners, as the detection benchmark scores them)
from tag_frames import synthetic_tag_frame  # noqa: E402
from twin_images import study_shot  # noqa: E402

from drillnav.registration.tag_recovery import dictionary_codes, read_code, recover_tag

CODES = dictionary_codes("DICT_6X6_250")
CORNERS = np.array([[250.0, 150.0], [420.0, 160.0], [410.0, 330.0], [240.0, 320.0]])
GLOVE = [(-0.4, -0.4), (0.9, -0.4), (-0.4, 0.9)]  # over the tag's top-left corner, in its unit square


def _wrong(read, aruco_id: int) -> int:
    """Cells read that disagree with ``aruco_id``'s code."""
    return int(((read.bits != CODES[aruco_id].reshape(-1)) & read.known).sum())


def test_black_cells_under_a_glove_read_white_and_are_left_unread_beside_its_sign():
    lifted = 0
    for aruco_id in range(12):
        frame = synthetic_tag_frame(CORNERS, aruco_id=aruco_id, glove_tag_xy=GLOVE).astype(np.float32)
        plain = read_code(frame, CORNERS, code_size=6)
        covered = read_code(frame, CORNERS, code_size=6, covers=True)
        assert not plain.reason and not covered.reason
        lifted += _wrong(plain, aruco_id) > 0
        assert _wrong(covered, aruco_id) == 0, aruco_id
        assert not (covered.known & ~plain.known).any()  # the rule only leaves cells unread
        assert covered.known.sum() >= 28  # the rest of the tag still reads
        # the cells it leaves unread read white: a black read stands
        assert np.all(plain.bits[plain.known & ~covered.known] == 1)
    assert lifted >= 6, "the glove no longer lifts a black cell: the frame no longer tests the rule"


def test_a_clean_tag_loses_no_cell_to_the_rule():
    for aruco_id in range(12):
        frame = synthetic_tag_frame(CORNERS, aruco_id=aruco_id).astype(np.float32)
        plain = read_code(frame, CORNERS, code_size=6)
        covered = read_code(frame, CORNERS, code_size=6, covers=True)
        assert plain.known.sum() == 36 and np.array_equal(covered.known, plain.known)
        assert _wrong(covered, aruco_id) == 0


def test_a_gloved_and_glared_tag_of_the_twin_is_recovered_and_registered():
    import accuracy

    scene, poses, pose, video, image = study_shot(11701, "ap+lateral", 1, marker_tilt_deg=(0.0, 10.0))
    assert 24 not in {m.marker_id for m in video.markers}, "ArUco finds marker 24's tag: the frame no longer tests it"
    truth = _true_corners(scene, pose)[24]
    locator = accuracy._locator(scene)
    name, aruco_id, spec = next((n, a, s) for n, per in locator._specs.items() for a, s in per.items() if s.marker_id == 24)
    gray = (cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image).astype(np.float32)
    got = recover_tag(gray, truth, aruco_id=aruco_id, dictionary=name, rivals=(), placed_here=True, partial=True,
                      square=lambda steps: locator._square_fit(steps, spec=spec, predicted_px=truth))
    assert got.accepted, got.reason  # without the rule: "7 of 8 code cells agree with id 24"
    assert np.linalg.norm(got.corners_px - truth, axis=1).max() < 1.5
    plain = read_code(gray, got.corners_px, code_size=6, partial=True)
    assert _wrong(plain, aruco_id) >= 1, "no black cell reads white there: the frame no longer tests the rule"
    assert _wrong(read_code(gray, got.corners_px, code_size=6, partial=True, covers=True), aruco_id) == 0

    video, reg = accuracy._register(scene, image, video, poses, joint=True)
    assert 24 in reg.used_ids, reg.used_ids
