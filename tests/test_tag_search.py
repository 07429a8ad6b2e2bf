"""Tags ArUco made no candidate of, found with no prediction (``registration/tag_search.py``).

The twin frame of ``test_tag_recovery.py`` (seed 5000, glove on): marker 2's tag has a gloved finger over a corner,
ArUco loses it, and with only marker 2 posed in fluoroscopy the frame shares no marker with it, so there is no
registration to predict the tag from. The search finds it from its bitten outline, within a pixel of the truth,
and the frame registers; a drape with no tag, and ids not asked for, give nothing.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from tag_detection import _true_corners  # noqa: E402  (the twin's true corners, as the detection benchmark scores them)

from drillnav.drivers.sim.degradations import CAMERA, Degradations
from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, make_scene, render_fluoro
from drillnav.registration.aruco_detect import detect_aruco
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.errors import DrillnavError
from drillnav.registration.fluoro_markers import detect_markers
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.pipeline import LiveCalibration, register_with_recovery, track_frame
from drillnav.registration.tag_hypotheses import outline_hypotheses
from drillnav.registration.tag_recovery import RECOVERED_CORNER_SIGMA_PX, dictionary_codes, read_code
from drillnav.registration.tag_search import QUADS_PER_HULL, _quads_of_hull, _same_as_any, identify_quad, search_tags
from drillnav.registration.video_markers import VideoDetections, VideoMarkerLocator, detect_tags
from tag_frames import synthetic_tag_frame, tag_points_px  # noqa: E402  (tests/: a rendered tag, a glove over it)
from twin_images import GLOVED_MARKER, GLOVED_SEED, gloved_frame  # noqa: E402  (tests/: shared twin images)

SEED, GLOVED = GLOVED_SEED, GLOVED_MARKER


@pytest.fixture(scope="module")
def gloved():
    return gloved_frame()


def test_a_bitten_square_gives_back_its_hidden_corner():
    # A 100 px square whose bottom-right corner a finger covers: a five-sided outline.
    bitten = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 70.0], [70.0, 100.0], [0.0, 100.0]])
    fill, quad = _quads_of_hull(bitten)[0]
    assert fill == pytest.approx((100 * 100 - 0.5 * 30 * 30) / 100**2)
    assert {tuple(np.round(c, 6)) for c in quad} == {(0.0, 0.0), (100.0, 0.0), (100.0, 100.0), (0.0, 100.0)}
    # The same outline with the bite on another corner, listed from another vertex: the same square.
    other = np.array([[100.0, 0.0], [100.0, 100.0], [0.0, 100.0], [0.0, 25.0], [25.0, 0.0]])
    fill, quad = _quads_of_hull(other)[0]
    assert {tuple(np.round(c, 6)) for c in quad} == {(0.0, 0.0), (100.0, 0.0), (100.0, 100.0), (0.0, 100.0)}


def test_a_gloved_tag_is_found_with_no_prediction_within_a_pixel(gloved):
    scene, pose, image, locator = gloved
    truth = _true_corners(scene, pose)
    video = locator.locate(image)
    assert GLOVED in truth and GLOVED not in video.by_id(), "the glove no longer hides the tag from ArUco"
    more = locator.search(image, video, scene.marker_set.ids)
    marker = more.by_id()[GLOVED]
    assert marker.recovered and marker.corner_sigma_px == RECOVERED_CORNER_SIGMA_PX
    err = np.linalg.norm(marker.corners_px - truth[GLOVED], axis=1)
    print(f"gloved tag found with no prediction: corners {np.round(err, 2)} px from the truth")
    assert err.max() <= 1.0
    # Nothing else was added, and nothing already found was touched.
    assert set(more.by_id()) == set(video.by_id()) | {GLOVED}
    assert all(more.by_id()[m.marker_id] is m for m in video.markers)
    # Asked only for ids that are not in the frame: nothing, although the gloved tag's outline is a candidate.
    absent = [i for i in range(250) if i not in truth]
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    assert search_tags(gray, dictionary="DICT_6X6_250", wanted=absent) == []


def test_a_frame_that_shares_no_marker_with_fluoroscopy_registers_through_the_search(gloved):
    scene, pose, image, locator = gloved
    image_rng = np.random.default_rng([SEED, 1])
    dets = [detect_markers(render_fluoro(scene, n, image_rng), scene.marker_set) for n in scene.views]
    only = tuple(p for p in register_markers(dets, list(scene.views.values()), scene.marker_set) if p.marker_id == GLOVED)
    assert only and only[0].converged
    video = locator.locate(image)
    common = dict(locator=locator, camera=scene.calibrated_camera, poses=only, marker_set=scene.marker_set)
    with pytest.raises(DrillnavError, match="only 0 marker"):
        register_with_recovery(image, video, search=False, name_outlines=False, **common)
    # Without the search, the gloved tag's outline is named among the posed markers; its code, read on 20 cells or
    # more, identifies it dictionary-wide, so the name stands alone (tests/test_named_alone.py).
    named, reg = register_with_recovery(image, video, search=False, **common)
    assert named.by_id()[GLOVED].identified_by_code and reg.used_ids == (GLOVED,)
    found, reg = register_with_recovery(image, video, **common)
    assert found.by_id()[GLOVED].recovered and reg.used_ids == (GLOVED,)
    entry = scene.corridor_entry_carm_mm
    axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
    error = float(np.linalg.norm(axis.closest_point(entry) - TRUE_DRILL_AXIS_CAMERA.transformed(pose).closest_point(entry)))
    print(f"one marker, found by the search: {error:.2f} mm at the corridor entry")
    assert error < 5.0
    # The live frame path does the same.
    calibration = LiveCalibration.build(camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill, marker_set=scene.marker_set)
    fa = track_frame(image, calibration=calibration, poses=only, marker_set=scene.marker_set)
    assert fa.video.by_id()[GLOVED].recovered and fa.registration.used_ids == (GLOVED,)


def test_a_drape_with_no_tag_gives_nothing():
    """Every camera degradation on (blood specks, glare, blur, compression), the drill pointed far past the markers."""
    for seed in (3000, 3001):
        scene = make_scene(seed=seed, render=False, degradations=Degradations.parse(",".join(CAMERA)))
        rng = np.random.default_rng([seed, 4])
        away = scene.drill_pose_towards(rng)
        away[:3, 3] += 5000.0 * away[:3, 2]
        frame = scene.render_camera(rng, carm_from_drill=away)
        locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=range(250))
        video = locator.locate(frame)
        assert not video.markers
        assert locator.search(frame, video, range(250)) is video


DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.mark.skipif(not (DATA / "aruco").is_dir(), reason="../shared/data/aruco is not present")
def test_a_real_photograph_gives_no_id_that_is_not_in_it():
    """A real photograph of a ChArUco board (DICT_6X6_250, ids 0-16): its 17 black chessboard squares and 17 tags
    are dark four-sided outlines; asked for every other id of the dictionary, the search names none."""
    from drillnav.schemas.calibration import camera_calibration_from_json
    from drillnav.schemas.camera_yaml import from_opencv_yaml

    image = cv2.imread(str(DATA / "aruco" / "choriginal.jpg"))
    camera = camera_calibration_from_json(from_opencv_yaml((DATA / "aruco" / "tutorial_camera_charuco.yml").read_text()))
    locator = VideoMarkerLocator(camera=camera, marker_ids=range(250), tag_size_mm=20.0)
    video = locator.locate(image)
    assert sorted(video.by_id()) == list(range(17))
    assert locator.search(image, video, range(17, 250)) is video
    # Nothing excluded: the 17 tags in the photograph are candidates too, and none is read as an absent id.
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    assert search_tags(gray, dictionary="DICT_6X6_250", wanted=range(17, 250)) == []


# Twin seed 5006, a random view pair (the accuracy study's third pair of that seed), the surgeon's markers and every
# camera degradation, the study's second freehand frame: ArUco finds marker 21 only; the registration on it predicts
# marker 38's tag in the frame, but not within the recovery's reach of where it is.
OFF_SEED, OFF_VIEWS, OFF_MARKER = 5006, "43:-3,-21:-1", 38


def test_a_tag_the_prediction_misplaces_is_searched_for_in_the_whole_frame():
    deg = Degradations.parse(",".join(("surgeon_markers",) + CAMERA))
    scene = make_scene(seed=OFF_SEED, views=OFF_VIEWS, render=False, degradations=deg)
    image_rng = np.random.default_rng([OFF_SEED, 2, 1])
    dets = [detect_markers(render_fluoro(scene, n, image_rng), scene.marker_set) for n in scene.views]
    poses = register_markers(dets, list(scene.views.values()), scene.marker_set)
    pose_rng, camera_rng = np.random.default_rng([OFF_SEED, 2, 2]), np.random.default_rng([OFF_SEED, 2, 3])
    for _ in range(2):
        pose = scene.drill_pose_towards(pose_rng, offset_mm=5.0, tilt_deg=5.0)
        image = scene.render_camera(camera_rng, carm_from_drill=pose)
    truth = _true_corners(scene, pose)
    locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)
    video = locator.locate(image)
    posed = {p.marker_id for p in poses if p.converged}
    assert OFF_MARKER in truth and OFF_MARKER in posed and OFF_MARKER not in video.by_id(), "the frame no longer loses the tag"
    common = dict(locator=locator, camera=scene.calibrated_camera, poses=poses, marker_set=scene.marker_set)
    before, _ = register_with_recovery(image, video, search=False, **common)
    assert OFF_MARKER not in before.by_id(), "the recovery from the prediction now finds the tag: this test no longer tests the search"
    found, reg = register_with_recovery(image, video, **common)
    marker = found.by_id()[OFF_MARKER]
    err = np.linalg.norm(marker.corners_px - truth[OFF_MARKER], axis=1)
    entry = scene.corridor_entry_carm_mm
    axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
    error = float(np.linalg.norm(axis.closest_point(entry) - TRUE_DRILL_AXIS_CAMERA.transformed(pose).closest_point(entry)))
    print(f"misplaced tag found by the search: corners {np.round(err, 2)} px from the truth; registration on {reg.used_ids}, "
          f"{error:.2f} mm at the corridor entry")
    assert marker.recovered and err.max() <= 1.0
    assert OFF_MARKER in reg.used_ids and error < 2.0
    # Only posed markers whose tag the registration puts in the frame are searched for: nothing else was added.
    assert set(found.by_id()) - set(before.by_id()) == {OFF_MARKER}
    # The live frame path does the same on a frame that runs the joint solve (the first of a registration).
    calibration = LiveCalibration.build(camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill, marker_set=scene.marker_set)
    fa = track_frame(image, calibration=calibration, poses=poses, marker_set=scene.marker_set)
    assert OFF_MARKER in fa.video.by_id() and OFF_MARKER in fa.registration.used_ids


def test_a_glove_over_a_corner_is_tried_past_the_best_filled_quadrilateral():
    # A unit tag whose corner (0, 1) a glove covers, its edge leaving 45 % of the bottom edge and 45 % of the left
    # one: dropping either short stretch's side and extending the glove's edge fills the hull better (0.89) than
    # the tag itself (0.85), so the tag is the hull's third quadrilateral.
    hull = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.55, 1.0], [0.0, 0.45]]) * 100.0
    quads = _quads_of_hull(hull)
    tag = {(0.0, 0.0), (100.0, 0.0), (100.0, 100.0), (0.0, 100.0)}
    ranks = [i for i, (_, q) in enumerate(quads) if {tuple(np.round(c, 6)) for c in q} == tag]
    assert ranks == [2] and ranks[0] < QUADS_PER_HULL, [np.round(q, 1).tolist() for _, q in quads]
    hull_area = 1 - 0.55 * 0.55 / 2
    assert quads[0][0] == pytest.approx(hull_area / 0.95) and quads[1][0] == pytest.approx(hull_area / 0.95) and quads[2][0] == pytest.approx(hull_area)


def test_candidates_are_one_only_when_their_corners_are():
    # Two candidates of one gloved tag (twin seed 7006, AP+lateral): they share two corners and the sums x + y of all
    # four within 3 px, yet two corners lie 58 px apart; the right one (within 5 px of the tag) must not be dropped
    # as the other's duplicate.
    right = np.array([[300.0, 188.0], [390.0, 282.0], [284.0, 388.0], [194.0, 291.0]])
    wrong = np.array([[300.0, 188.0], [390.0, 282.0], [227.0, 446.0], [236.0, 250.0]])
    assert not _same_as_any(right, wrong[None])
    assert _same_as_any(np.roll(right, 1, axis=0) + 2.0, np.stack([wrong, right]))
    assert not _same_as_any(right, np.zeros((0, 4, 2)))


def test_a_tag_with_a_gloved_corner_whose_best_filled_outline_is_not_it_is_found():
    corners = np.array([[250.0, 140.0], [390.0, 160.0], [375.0, 300.0], [235.0, 285.0]])
    # A glove over corner BL (the unit square's (0, 1)) as in the test above, its edge straight: 45 % of the bottom
    # and left edges left in view. Both the search (its code reads in full) and the naming find it.
    slope = 0.55 / 0.55
    glove = [[-0.6, 0.45 - 0.6 * slope], [(1.6 - 0.45) / slope, 1.6], [-0.6, 1.6]]
    gray = synthetic_tag_frame(corners, aruco_id=23, glove_tag_xy=glove)
    detected, _ = detect_aruco(cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)), gray)
    assert detected == [], "ArUco reads the gloved tag: this frame no longer tests the search"
    found = search_tags(gray, dictionary="DICT_6X6_250", wanted=[5, 23, 40])
    assert [t.aruco_id for t in found] == [23]
    err = np.linalg.norm(found[0].corners_px - corners, axis=1)
    print(f"gloved tag: corners {np.round(err, 2)} px from the truth")
    assert err.max() < 1.5
    named = outline_hypotheses(gray, dictionary="DICT_6X6_250", wanted=[5, 23, 40])
    assert [h.aruco_id for h in named] == [23] and np.linalg.norm(named[0].corners_px - corners, axis=1).max() < 1.5


def _search_finds_it_alone(corners, *, aruco_id: int, other_id: int, what: str):
    """Render one tag at ``corners`` (4, 2) (``synthetic_tag_frame``), check that ArUco does not read it and that the search,
    asked for it and ``other_id``, finds it alone within 1.5 px at every corner. Returns the frame."""
    gray = synthetic_tag_frame(corners, aruco_id=aruco_id)
    detected, _ = detect_aruco(cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)), gray)
    assert detected == [], "ArUco reads the tag: this frame no longer tests the search"
    found = search_tags(gray, dictionary="DICT_6X6_250", wanted=[aruco_id, other_id])
    assert [t.aruco_id for t in found] == [aruco_id]
    err = np.linalg.norm(found[0].corners_px - corners, axis=1)
    print(f"{what}: corners {np.round(err, 2)} px from the truth")
    assert err.max() < 1.5
    return gray


def test_a_tag_partly_out_of_the_frame_is_found_on_what_is_in_it():
    # Turned 28 deg, its top-left corner 30 px above the frame's top row, and the white base around it out of the frame
    # along the top of the tag.
    corners = np.array([[320.0, -30.0], [450.0, 40.0], [380.0, 170.0], [250.0, 100.0]])
    gray = _search_finds_it_alone(corners, aruco_id=8, other_id=14, what="tag partly out of the frame")
    # Asked only for another id: nothing.
    assert search_tags(gray, dictionary="DICT_6X6_250", wanted=[14]) == []


def test_a_tag_cut_close_to_its_corner_is_outlined_with_that_corner_beyond_the_edge():
    """Its top corner 10 px above the frame: the dark region runs along the top row for a few pixels only, and the
    closed outline's simplification merged the two points where the tag's sides leave the frame into one vertex on the
    edge, about 10 px from the sides' crossing, beyond the edge fit's reach. Seen on the operating-room twin (seed
    7002, inlet+outlet, its second frame): marker 37, sharp and plainly readable, was not found. The ends of the
    hull's stretch along the edge are now kept as vertices, and the corner beyond the edge is where the sides' lines
    cross."""
    corners = np.array([[236.0, 150.0], [304.0, -10.0], [454.0, 55.0], [383.0, 207.0]])
    _search_finds_it_alone(corners, aruco_id=37, other_id=14, what="tag cut close to its corner")


def _tag_read_in_part(corners_px, *, aruco_id: int, read_cells, size=(480, 640)):
    """A frame (H, W) uint8 with one DICT_6X6_250 tag at ``corners_px`` whose code cells outside ``read_cells`` (a set of
    (row, column) of the 6 x 6 code) are painted mid-grey (halfway between its black and white: unread, as under a
    haze of glare), on a white base over a plain grey drape."""
    h, w = size
    frame = np.full((h, w), 110.0)
    tag = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250), aruco_id, 800).astype(np.float64)
    for r in range(6):
        for c in range(6):
            if (r, c) not in read_cells:
                tag[100 * (r + 1):100 * (r + 2), 100 * (c + 1):100 * (c + 2)] = 127.5
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)
    to_frame = cv2.getPerspectiveTransform(unit, np.asarray(corners_px, dtype=np.float32))
    base = cv2.perspectiveTransform(((unit - 0.5) * 1.6 + 0.5).reshape(-1, 1, 2), to_frame).reshape(-1, 2)
    cv2.fillConvexPoly(frame, np.round(base * 16).astype(np.int32), 235.0, lineType=cv2.LINE_AA, shift=4)
    warped = cv2.warpPerspective(tag, to_frame @ np.diag([1 / 800, 1 / 800, 1]), (w, h), flags=cv2.INTER_AREA)
    inside = cv2.warpPerspective(np.ones_like(tag), to_frame @ np.diag([1 / 800, 1 / 800, 1]), (w, h), flags=cv2.INTER_AREA)
    frame = np.where(inside > 0.5, warped * 0.85 + 25, frame)
    return np.clip(cv2.GaussianBlur(frame, (0, 0), 0.8), 0, 255).astype(np.uint8)


def test_a_tag_read_in_part_that_an_id_outside_the_marker_set_nearly_fits_is_named_by_the_set():
    """Twin seed 9305, AP+lateral, second drill pose: marker 2's tag, a finger over a corner and a highlight over its
    code, read in 21 cells of which 20 agree with id 2; an id outside the marker set agrees in 18. The
    dictionary-wide rule refused it, and the frame, sharing no other tag with fluoroscopy, was refused. Here: a tag
    read in 22 cells, an id from outside the set agreeing in all but two of them, every id of the set far off."""
    codes = dictionary_codes("DICT_6X6_250")
    mine = 23
    flat = codes.reshape(len(codes), -1)
    rot = np.stack([np.rot90(codes[i], k).reshape(-1) for i in range(len(codes)) for k in range(4)])
    # The id (any rotation) nearest to tag 23, and 22 cells: those where the two agree, and 2 where they differ.
    agree = (rot == flat[mine][None, :]).sum(axis=1)
    agree[4 * mine:4 * mine + 4] = -1
    near = int(np.argmax(agree))
    same, differ = np.nonzero(rot[near] == flat[mine])[0], np.nonzero(rot[near] != flat[mine])[0]
    cells = list(same[:20]) + list(differ[:2])
    assert len(cells) == 22
    read_cells = {(int(i) // 6, int(i) % 6) for i in cells}
    corners = np.array([[250.0, 140.0], [390.0, 160.0], [375.0, 300.0], [235.0, 285.0]])
    gray = _tag_read_in_part(corners, aruco_id=mine, read_cells=read_cells)
    set_ids = [5, mine, 40]
    assert near // 4 not in set_ids
    gray_f = gray.astype(np.float32)
    # The dictionary-wide rule alone: id near // 4 fits 20 of the 22 cells, 23 all 22: within 4, refused.
    assert identify_quad(gray_f, corners, dictionary="DICT_6X6_250", wanted=set_ids) is None
    # Judged among the marker set's ids (every one far from these cells): named, at its rotation.
    tag = identify_quad(gray_f, corners, dictionary="DICT_6X6_250", wanted=set_ids, rivals=set_ids)
    assert tag is not None and tag.aruco_id == mine and (tag.cells_read, tag.cells_agreeing, tag.runner_up_agreeing) == (22, 22, 20)
    assert np.allclose(tag.corners_px, corners)
    # The near id in the set: a rival within 4 cells, refused; so is an id that fits the cells better than the one asked for.
    assert identify_quad(gray_f, corners, dictionary="DICT_6X6_250", wanted=set_ids, rivals=set_ids + [near // 4]) is None
    assert identify_quad(gray_f, corners, dictionary="DICT_6X6_250", wanted=[near // 4], rivals=[near // 4, mine]) is None
    # Fewer than the 20 cells the search needs with no place to vouch: refused whatever the rivals.
    few = _tag_read_in_part(corners, aruco_id=mine, read_cells=set(list(read_cells)[:18]))
    assert identify_quad(few.astype(np.float32), corners, dictionary="DICT_6X6_250", wanted=set_ids, rivals=set_ids) is None
    # The search end to end: its outline found, named by the set's rule, refused by the dictionary-wide one.
    found = search_tags(gray, dictionary="DICT_6X6_250", wanted=set_ids, rivals=set_ids)
    assert [t.aruco_id for t in found] == [mine] and np.linalg.norm(found[0].corners_px - corners, axis=1).max() < 1.5
    assert search_tags(gray, dictionary="DICT_6X6_250", wanted=set_ids) == []
    # The locator's search (the registration's recovery and the live path call it) judges by its marker set's ids.
    camera = PinholeCamera(width=640, height=480, camera_matrix=np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]]))
    none = VideoDetections(markers=(), ignored_ids=(), image_size=(640, 480))
    more = VideoMarkerLocator(camera=camera, marker_ids=set_ids).search(gray, none, set_ids)
    assert [m.marker_id for m in more.markers] == [mine] and more.markers[0].recovered
    assert VideoMarkerLocator(camera=camera, marker_ids=set_ids + [near // 4]).search(gray, none, set_ids) is none


def test_a_gloved_tag_in_an_over_exposed_frame_is_found_on_its_clipped_white_cells():
    """An over-exposed frame clips the white base and every white code cell at 255. Read as glare (a clipped cell
    unknown, and any white cell beside one), such a tag kept 21 of its 36 cells, its border's; a glove over a corner
    then cost ArUco the tag and the search its name. Seen on the operating-room twin (seed 10802, random views, first
    frame): marker 43, gloved in a clipped frame, was not found, the frame shared one marker with fluoroscopy, and the
    registration was refused. With the base clipped, a clipped cell is taken for white unless a highlight shows beside
    it."""
    corners = np.array([[250.0, 150.0], [400.0, 165.0], [390.0, 315.0], [240.0, 300.0]])
    glove = [[-0.3, 0.4], [0.6, 1.3], [-0.3, 1.3]]
    gray = synthetic_tag_frame(corners, aruco_id=7, glove_tag_xy=glove, gain=1.12, blur_px=2.0)
    base = tag_points_px(corners, [[-0.1, 0.5], [1.1, 0.5], [0.5, -0.1]])
    assert all(gray[int(round(y)), int(round(x))] == 255 for x, y in base), "the base no longer clips"
    assert 7 not in [i for i, _ in detect_tags(gray)], "the glove no longer hides the tag from ArUco"
    read = read_code(gray.astype(np.float32), corners, code_size=6, partial=True)
    code = dictionary_codes("DICT_6X6_250")[7].reshape(-1)
    assert read.known.sum() >= 30 and (read.bits[read.known] == code[read.known]).all()
    found = search_tags(gray, dictionary="DICT_6X6_250", wanted=[7])
    assert [t.aruco_id for t in found] == [7]
    assert np.linalg.norm(found[0].corners_px - corners, axis=1).max() <= 0.5


def test_a_bitten_outline_whose_hidden_corner_is_loose_is_fitted_again_from_where_its_edges_meet():
    """A glove over a tag's corner at a slant: the hull's sides can put the hidden corner 14-17 px off (seed 11700, flat
    markers). The edges found near the other corners cross at the hidden corner, beyond the 9 px the first fit allows;
    fitted once more from there the tag is placed (here a corner put 10 px off: refused before, now within 0.5 px)."""
    from drillnav.registration.tag_recovery import fit_tag_edges
    from drillnav.registration.tag_search import _fit_outline

    corners = np.array([[220.0, 160.0], [372.0, 150.0], [380.0, 300.0], [226.0, 310.0]])
    glove = [(-0.7, -0.7), (0.4, -0.7), (0.4, 0.0), (0.0, 0.3), (-0.7, 0.3)]  # over the top-left corner
    gray = synthetic_tag_frame(corners, aruco_id=22, glove_tag_xy=glove, size=(480, 640)).astype(np.float32)
    outline = corners.copy()
    outline[0] += 10.0 * (corners[3] - corners[0]) / np.linalg.norm(corners[3] - corners[0])  # the hidden corner 10 px down its edge
    first = fit_tag_edges(gray, outline, tolerance_px=6.0, partial=True)
    assert not first.accepted and "from the prediction" in first.reason
    fitted = _fit_outline(gray, outline, tolerance_px=6.0)
    assert fitted.accepted, fitted.reason
    assert np.abs(fitted.corners_px - corners).max() < 0.5
    assert identify_quad(gray, fitted.corners_px, dictionary="DICT_6X6_250", wanted=[22], partial=True) is not None
