"""Camera and drill-axis calibration on twin images with known truth and on real photographs."""

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA as AXIS
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.camera_uncertainty import IntrinsicsUncertainty
from drillnav.registration.camera_calibration import calibrate_camera, detect_board, parse_board
from drillnav.registration.drill_axis import (
    JigNotFound, detect_jig, find_jig_poses, fit_axis_cylinder, fit_axis_screw, jig_pose, jig_size_mm, jig_tag_corners_mm,
)
from drillnav.registration.errors import DegenerateInput
from drillnav.registration.transforms import apply, make_transform
from drillnav.schemas.calibration import read_camera_calibration, read_drill_calibration
from drillnav.service.cli import main

from twin_images import board_views as shared_board_views  # noqa: E402
from twin_images import field_marker_frame  # noqa: E402
from twin_images import jig_frames as shared_jig_frames  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
TRUE = PinholeCamera.from_fov(width=1280, height=720, horizontal_fov_deg=76, distortion=[-0.12, 0.09, 0.0006, -0.0004, -0.02])


def board_views(n, *, tilt_deg=30.0, seed=0):
    return shared_board_views(TRUE, n, tilt_deg=tilt_deg, seed=seed)


@pytest.fixture(scope="module")
def twin_views():
    return board_views(15)


def test_twin_intrinsics_recovered(twin_views):
    cal = calibrate_camera(twin_views, parse_board("checkerboard:9x6:25mm"))
    fx, fy = cal.camera.focal_px
    assert abs(fx / TRUE.focal_px[0] - 1) < 0.005 and abs(fy / TRUE.focal_px[1] - 1) < 0.005
    assert np.hypot(*(np.subtract(cal.camera.principal_point_px, TRUE.principal_point_px))) < 2.0
    assert cal.rms_px < 0.5
    # Its stated uncertainty (OpenCV's standard deviations of the intrinsics, written to camera.json): the errors
    # above are a few of its sigmas at most (formal figures are optimistic; the priors never take them under typical).
    u = cal.camera.uncertainty
    assert u is not None and 0 < u.focal_rel < 0.005 and 0 < u.principal_px < 2.0 and u.distortion is None, u
    assert abs(fx / TRUE.focal_px[0] - 1) < 10 * u.focal_rel


def test_fronto_parallel_set_refused():
    with pytest.raises(DegenerateInput, match="fronto-parallel"):
        calibrate_camera(board_views(4, tilt_deg=0.5, seed=3), parse_board("checkerboard:9x6:25mm"))


def test_board_spec_errors():
    with pytest.raises(ValueError, match="bad board"):
        parse_board("checkerboard:9by6")


@pytest.mark.skipif(not (DATA / "chessboard-right").is_dir(), reason="../shared/data/chessboard-right is not present")
def test_real_chessboard_agrees_with_opencv(tmp_path):
    paths = sorted((DATA / "chessboard-right").glob("*.jpg"))
    out = tmp_path / "camera.json"
    assert main(["calibrate", "camera", *map(str, paths), "--board", "checkerboard:9x6:25mm", "--out", str(out)]) == 0
    ours = read_camera_calibration(out)
    # OpenCV's own calibration of the same photographs, straight from its corner finder.
    obj, img = [], []
    for p in paths:
        g = cv2.imread(str(p), 0)
        ok, c = cv2.findChessboardCorners(g, (9, 6))
        assert ok
        c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 1e-3))
        obj.append(parse_board("checkerboard:9x6:25mm").object_points().astype(np.float32))
        img.append(c)
    _, k, _, _, _ = cv2.calibrateCamera(obj, img, (640, 480), None, None)
    np.testing.assert_allclose(ours.camera_matrix[[0, 1, 0, 1], [0, 1, 2, 2]], k[[0, 1, 0, 1], [0, 1, 2, 2]], rtol=0.01)


@pytest.mark.skipif(not (DATA / "aruco").is_dir(), reason="../shared/data/aruco is not present")
def test_real_charuco_photo(tmp_path):
    img = cv2.imread(str(DATA / "aruco" / "choriginal.jpg"), 0)
    found = detect_board(img, parse_board("charuco:5x7:40mm:30mm"))
    assert found is not None and len(found[0]) >= 20
    out = tmp_path / "det.json"
    assert main(["markers", "detect", str(DATA / "aruco" / "choriginal.jpg"), "--camera", str(DATA / "aruco" / "tutorial_camera_charuco.yml"), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert sorted(m["id"] for m in doc["markers"]) == list(range(17))
    assert all("camera_from_tag" in m and np.asarray(m["camera_from_tag"])[2, 3] > 0 for m in doc["markers"])


def jig_frames(n=8, span=120.0, seed=0):
    return shared_jig_frames(TRUE, AXIS, n, span_deg=span, seed=seed)


def test_drill_axis_both_methods():
    poses = [jig_pose(f, TRUE) for f in jig_frames()]
    screw = fit_axis_screw(poses)
    assert screw.axis.angle_deg(AXIS) < 0.3 and AXIS.distance_to_line(screw.axis) < 0.3
    s = jig_size_mm()
    cyl = fit_axis_cylinder(poses, np.array([[0, 0, 0], [s, 0, 0], [s, s, 0], [0, s, 0], [s / 2, s / 2, 0]], float))
    assert cyl.axis.angle_deg(AXIS) < 1.0 and AXIS.distance_to_line(cyl.axis) < 1.0


def test_drill_axis_refusals(tmp_path):
    poses = [jig_pose(f, TRUE) for f in jig_frames(4, span=0.0)]
    with pytest.raises(DegenerateInput, match="static"):
        fit_axis_screw(poses)
    poses = [jig_pose(f, TRUE) for f in jig_frames(4, span=10.0)]
    with pytest.raises(DegenerateInput, match="too small"):
        fit_axis_screw(poses)
    bad = [jig_pose(f, TRUE) for f in jig_frames()]  # test_drill_axis_both_methods's frames (rendered once)
    bad[3] = make_transform(Rotation.from_euler("y", 40, degrees=True).as_matrix(), [0, 0, 0]) @ bad[3]
    with pytest.raises(DegenerateInput, match="disagree"):
        fit_axis_screw(bad)


def test_drill_axis_cli(tmp_path, capsys):
    from drillnav.schemas.calibration import write_camera_calibration

    cam = tmp_path / "camera.json"
    write_camera_calibration(cam, TRUE, rms_px=0.2, per_view_errors_px=[], label="twin")
    paths = []
    for i, f in enumerate(jig_frames()):  # test_drill_axis_both_methods's frames (rendered once)
        paths.append(tmp_path / f"f{i}.png")
        cv2.imwrite(str(paths[-1]), f)
    out = tmp_path / "drill.json"
    assert main(["calibrate", "drill-axis", *map(str, paths), "--camera", str(cam), "--out", str(out)]) == 0
    axis = read_drill_calibration(out)
    assert axis.angle_deg(AXIS) < 0.3
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n junk")
    assert main(["calibrate", "drill-axis", str(tmp_path / "corrupt.png"), "--camera", str(cam), "--out", str(out)]) == 1
    assert "not a readable image" in capsys.readouterr().err


def test_calibration_files_validated(tmp_path):
    from drillnav.schemas.calibration import write_camera_calibration

    p = tmp_path / "camera.json"
    write_camera_calibration(p, TRUE, rms_px=0.2, per_view_errors_px=[0.1, 0.3], label="t")
    assert read_camera_calibration(p).focal_px == TRUE.focal_px and read_camera_calibration(p).uncertainty is None  # none stated
    stated = IntrinsicsUncertainty(focal_rel=0.004, principal_px=1.5, distortion=(0.01, 0.02, 0.001, 0.001, 0.01))
    write_camera_calibration(p, dataclasses.replace(TRUE, uncertainty=stated), rms_px=0.2, per_view_errors_px=[0.1, 0.3], label="t")
    assert read_camera_calibration(p).uncertainty == stated
    partial = IntrinsicsUncertainty(focal_rel=0.004, principal_px=1.5)  # what a calibration job states: no distortion sigmas
    write_camera_calibration(p, dataclasses.replace(TRUE, uncertainty=partial), rms_px=0.2, per_view_errors_px=[0.1, 0.3], label="t")
    assert read_camera_calibration(p).uncertainty == partial and "distortion" not in json.loads(p.read_text())["intrinsics_sigma"]
    write_camera_calibration(p, dataclasses.replace(TRUE, uncertainty=stated), rms_px=0.2, per_view_errors_px=[0.1, 0.3], label="t")
    doc = json.loads(p.read_text())
    p.write_text(json.dumps({**doc, "intrinsics_sigma": {**doc["intrinsics_sigma"], "focal_rel": -1}}))
    with pytest.raises(ValueError, match="intrinsics_sigma"):
        read_camera_calibration(p)
    doc["distortion"] = [0.1, 0.2]
    p.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="invalid at distortion"):
        read_camera_calibration(p)
    (tmp_path / "drill.json").write_text(json.dumps({"axis_camera": {"point_mm": [0, 0]}}))
    with pytest.raises(ValueError, match="axis_camera"):
        read_drill_calibration(tmp_path / "drill.json")


def test_no_board_found_and_one_view(tmp_path, capsys):
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    assert main(["calibrate", "camera", str(blank), str(blank), str(blank), "--board", "checkerboard:9x6:25mm", "--out", str(tmp_path / "c.json")]) == 1
    assert "was not found in any of the 3 views" in capsys.readouterr().err
    assert main(["calibrate", "camera", str(blank), "--board", "checkerboard:9x6:25mm", "--out", str(tmp_path / "c.json")]) == 1
    assert "at least 3 views" in capsys.readouterr().err


def test_the_jig_pose_comes_from_the_jig_s_own_board_points():
    frame = jig_frames(1, span=0.0)[0]
    det = detect_jig(frame, TRUE)
    assert det.jig_ids == tuple(range(100, 116)) and det.other_ids == () and det.points == 64
    # Covering all but a few of its tags: the jig is named as seen, but too little of it for a pose.
    covered = frame.copy()
    for tag_id, corners_mm in jig_tag_corners_mm().items():
        if tag_id not in (100, 101, 102):
            px = TRUE.project(apply(det.camera_from_board, corners_mm))
            cv2.fillConvexPoly(covered, np.round(px).astype(np.int32), 200)
    part = detect_jig(covered, TRUE)
    assert part.camera_from_board is None and part.jig_ids == (100, 101, 102) and part.points == 0
    with pytest.raises(JigNotFound, match=r"saw only the jig's tags 100, 101, 102 \(4 or more of its 16 tags are needed in one frame\)"):
        find_jig_poses([("covered.png", covered)] * 3, TRUE)


def test_field_markers_instead_of_the_jig_is_one_line_naming_them(tmp_path, capsys):
    from drillnav.schemas.calibration import write_camera_calibration

    cam = tmp_path / "camera.json"
    write_camera_calibration(cam, TRUE, rms_px=0.2, per_view_errors_px=[], label="twin")
    frame = field_marker_frame(TRUE)  # four field markers: before, OpenCV's solvePnP asserted on them
    assert detect_jig(frame, TRUE).other_ids == (3, 7, 12, 20)
    paths = []
    for i, f in enumerate([frame] * 3 + jig_frames(2)):
        paths.append(tmp_path / f"f{i}.png")
        cv2.imwrite(str(paths[-1]), f)
    assert main(["calibrate", "drill-axis", *map(str, paths), "--camera", str(cam), "--out", str(tmp_path / "drill.json")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and "OpenCV" not in err, err
    assert ("drillnav calibrate: error: the jig board was found in only 2 of 5 frames (at least 3 are needed): "
            "saw tags 3, 7, 12, 20 (field markers), none of the jig's 16 tags (ids 100-115)") in err
    assert not (tmp_path / "drill.json").exists()
