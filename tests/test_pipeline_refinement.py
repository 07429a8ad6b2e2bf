"""The live pipeline's joint refinement: the joint solve at most every JOINT_PERIOD_NS, the frames between on its refined markers."""

from pathlib import Path

import numpy as np
import pytest

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.fluoro_markers import detect_markers
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.pipeline import JOINT_PERIOD_NS, LiveCalibration, track_frame
from drillnav.schemas import messages as msg
from drillnav.service.replay import iter_recording

RECORDING = Path(__file__).resolve().parents[1] / "recordings" / "twin-seed21.mcap"


@pytest.fixture(scope="module")
def live():
    scene = make_scene(seed=21, render=False)
    rec = list(iter_recording(RECORDING))
    shots = [msg.FluoroShot.from_bytes(d) for t, _, d in rec if t.endswith("fluoro/shot")]
    dets = [detect_markers(s.image_log, scene.marker_set, pixel_spacing_mm=s.carm_view.pixel_spacing_mm[1]) for s in shots]
    poses = tuple(register_markers(dets, [s.carm_view for s in shots], scene.marker_set))
    cal = LiveCalibration.build(camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill, marker_set=scene.marker_set)
    frames = [msg.decode_compressed_image(d)[0] for t, _, d in rec if t.endswith("camera/image")]
    return scene, poses, cal, frames


def test_frames_between_joint_solves_use_its_refined_markers_and_agree_with_it(live):
    scene, poses, cal, frames = live
    first = track_frame(frames[0], calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=None, now_ns=0)
    assert first.registration.method == "joint" and first.refinement is not None
    ref = first.refinement
    for k, frame in enumerate(frames[1:8], start=1):
        fa = track_frame(frame, calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=ref, now_ns=k * 33_000_000)
        assert fa.registration.method == "horn+pnp on joint-refined markers" and fa.refinement is ref
        full = track_frame(frame, calibration=cal, poses=poses, marker_set=scene.marker_set)  # the joint solve on this frame
        assert np.linalg.norm(fa.axis_carm.point_mm - full.axis_carm.point_mm) < 0.3
        assert np.degrees(np.arccos(min(1.0, float(fa.axis_carm.direction @ full.axis_carm.direction)))) < 0.2
        # The carried covariance gives a predicted error of the joint solve's size, not the Monte-Carlo fallback's.
        assert fa.predicted_error.position90_mm == pytest.approx(full.predicted_error.position90_mm, rel=0.3)


def test_a_new_registration_calibration_or_period_runs_the_joint_solve_again(live):
    scene, poses, cal, frames = live
    ref = track_frame(frames[0], calibration=cal, poses=poses, marker_set=scene.marker_set, now_ns=0).refinement
    again = track_frame(frames[1], calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=ref, now_ns=JOINT_PERIOD_NS)
    assert again.registration.method == "joint" and again.refinement is not ref
    new_poses = tuple(list(poses))  # another registration (a new tuple), though equal
    assert track_frame(frames[1], calibration=cal, poses=new_poses, marker_set=scene.marker_set, refinement=ref, now_ns=1).registration.method == "joint"
    new_cal = LiveCalibration.build(camera=cal.camera, axis_drill=cal.axis_drill, marker_set=scene.marker_set)
    assert track_frame(frames[1], calibration=new_cal, poses=poses, marker_set=scene.marker_set, refinement=ref, now_ns=1).registration.method == "joint"
