"""Camera calibrations through OpenCV's YAML and ROS's camera_info YAML and back, unchanged; the CLI; bad files."""

import json

import cv2
import numpy as np
import pytest

from drillnav.drivers.sim.scene import make_scene
from drillnav.schemas.calibration import camera_calibration_to_json, read_camera_calibration
from drillnav.schemas.camera_yaml import CalibrationFormat, convert, detect_format, from_opencv_yaml, from_ros_yaml, to_opencv_yaml, to_ros_yaml
from drillnav.service.cli import main

# What ROS's cameracalibrator writes (the layout of camera_calibration_parsers' YAML), numbers of a 1280x720 webcam.
ROS_FILE = """image_width: 1280
image_height: 720
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [912.3456, 0, 641.25, 0, 910.875, 361.5, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.0912, -0.2101, 0.0011, -0.0007, 0.0954]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [912.3456, 0, 641.25, 0, 0, 910.875, 361.5, 0, 0, 0, 1, 0]
"""


@pytest.fixture(scope="module")
def camera_doc():
    cam = make_scene(seed=3, render=False).calibrated_camera  # irrational-looking numbers, all 17 digits used
    return camera_calibration_to_json(cam, rms_px=0.2718281828459045, per_view_errors_px=[0.1, 0.31415926535897931, 0.25], label="drill camera, OR 2")


def test_round_trips_are_exact(camera_doc):
    assert from_opencv_yaml(to_opencv_yaml(camera_doc)) == camera_doc
    assert from_ros_yaml(to_ros_yaml(camera_doc)) == camera_doc
    # Through both, in either order.
    via = json.loads(convert(convert(convert(json.dumps(camera_doc), CalibrationFormat.OPENCV), CalibrationFormat.ROS), CalibrationFormat.JSON))
    assert via == camera_doc


def test_files_other_tools_write(camera_doc, tmp_path):
    # OpenCV's own FileStorage, as its calibration sample writes a camera (no drillnav keys).
    path = str(tmp_path / "opencv.yaml")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 720)
    k = np.array([[900.5, 0, 640.1], [0, 901.5, 359.9], [0, 0, 1]])
    fs.write("camera_matrix", k)
    fs.write("distortion_coefficients", np.array([[0.1], [-0.2], [0.001], [0.002], [0.05]]))
    fs.write("avg_reprojection_error", 0.31)
    fs.release()
    text = open(path).read()
    assert detect_format(text) is CalibrationFormat.OPENCV
    doc = from_opencv_yaml(text)
    assert doc == {"image_size": [1280, 720], "camera_matrix": k.tolist(), "distortion": [0.1, -0.2, 0.001, 0.002, 0.05], "rms_px": 0.31}
    # ROS's: the model keeps its numbers and OpenCV's written copy reads back in OpenCV.
    assert detect_format(ROS_FILE) is CalibrationFormat.ROS
    ros = from_ros_yaml(ROS_FILE)
    assert ros["camera_matrix"] == [[912.3456, 0, 641.25], [0, 910.875, 361.5], [0, 0, 1]] and ros["distortion"][4] == 0.0954
    fs = cv2.FileStorage(to_opencv_yaml(ros), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    assert np.array_equal(fs.getNode("camera_matrix").mat(), np.asarray(ros["camera_matrix"]))
    fs.release()


@pytest.mark.parametrize("edit, message", [
    (("distortion_model: plumb_bob", "distortion_model: rational_polynomial"), "rational_polynomial"),
    (("data: [1, 0, 0, 0, 1, 0, 0, 0, 1]", "data: [1, 0, 0, 0, 0.9, 0.1, 0, -0.1, 0.9]"), "rectification_matrix"),
    (("data: [0.0912, -0.2101, 0.0011, -0.0007, 0.0954]", "data: [0.0912, -0.2101]"), "distortion_coefficients must hold 5"),
    (("data: [912.3456, 0, 641.25, 0, 910.875, 361.5, 0, 0, 1]", "data: [-912.3456, 0, 641.25, 0, 910.875, 361.5, 0, 0, 1]"), "fx, fy > 0"),
    (("image_width: 1280", "image_width: wide"), "image_width"),
])
def test_bad_ros_files_are_refused_with_the_field_named(edit, message):
    with pytest.raises(ValueError, match=message):
        from_ros_yaml(ROS_FILE.replace(*edit))


def test_bad_opencv_file():
    with pytest.raises(ValueError, match="missing 'camera_matrix'"):
        from_opencv_yaml("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ndistortion_coefficients: !!opencv-matrix\n"
                         "   rows: 5\n   cols: 1\n   dt: d\n   data: [0., 0., 0., 0., 0.]\n")


def test_cli_convert(camera_doc, tmp_path, capsys):
    src = tmp_path / "camera.json"
    src.write_text(json.dumps(camera_doc))
    assert main(["calibration", "convert", str(src), str(tmp_path / "ros.yaml"), "--to", "ros"]) == 0
    assert main(["calibration", "convert", str(tmp_path / "ros.yaml"), str(tmp_path / "cv.yml"), "--to", "opencv"]) == 0
    assert main(["calibration", "convert", str(tmp_path / "cv.yml"), str(tmp_path / "back.json")]) == 0
    assert json.loads((tmp_path / "back.json").read_text()) == camera_doc
    read_camera_calibration(tmp_path / "back.json")  # a camera.json the daemon loads
    capsys.readouterr()
    assert main(["calibration", "convert", str(src), str(tmp_path / "x.yaml")]) == 1
    assert "needs --to opencv or --to ros" in capsys.readouterr().err
    assert main(["calibration", "convert", str(tmp_path / "none.json"), str(tmp_path / "y.json")]) == 1
    assert "no such file" in capsys.readouterr().err
