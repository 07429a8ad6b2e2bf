"""A tag with one border edge hidden, placed by its pose fitted to the other three (registration/tag_square_fit.py).

Border steps are drawn on the projected edges of a 30 mm tag 250 mm from a camera with lens distortion, with
0.15 px noise (what the recovery's steps scatter by on the twin). The fit must place every corner within the
1-sigma it states (its covariance is the only thing that decides whether such a tag is taken), place the
corners beside the hidden edge within a fraction of a pixel when the geometry allows it, and refuse a geometry
that cannot place them. Then two twin frames: a glared tag ArUco misses, recovered from its prediction; and a
tag ArUco decodes but whose edges do not fit, placed from the detector's corners.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from tag_detection import _true_corners  # noqa: E402  (the twin's true corners, as the detection benchmark scores them)

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.tag_recovery import RECOVERED_CORNER_SIGMA_PX, predict_tag_corners, recover_tag
from drillnav.registration.tag_square_fit import fit_square_to_edges
from drillnav.registration.video_markers import VideoMarkerLocator, tag_object_points

CAMERA = PinholeCamera(width=1280, height=720, camera_matrix=np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]]),
                       distortion=np.array([-0.12, 0.05, 0.001, -0.001, 0.0]))
TAG = tag_object_points(30.0)
STEP_NOISE_PX = 0.15


def _steps(rng, camera_from_tag_rot, t, hidden):
    """Border steps (4, 48, 2) along the tag's projected edges with noise, the hidden edge's not kept."""
    pts = TAG @ camera_from_tag_rot.T + t
    along = np.linspace(0.06, 0.94, 48)
    steps = np.stack([CAMERA.project(pts[k] + along[:, None] * (pts[(k + 1) % 4] - pts[k])) for k in range(4)])
    kept = np.ones((4, 48), dtype=bool)
    kept[hidden] = False
    return steps + rng.normal(0.0, STEP_NOISE_PX, steps.shape), kept, CAMERA.project(pts)


def test_a_tag_with_one_edge_hidden_is_placed_within_the_sigma_it_states():
    rng = np.random.default_rng(0)
    rot, _ = cv2.Rodrigues(np.array([np.radians(10.0), 0.1, 0.3]))
    t = np.array([20.0, -10.0, 250.0])
    errors, sigmas = [], []
    for _ in range(60):
        steps, kept, truth = _steps(rng, rot, t, hidden=0)
        predicted = truth + rng.normal(0.0, 2.0, 2) + rng.normal(0.0, 1.0, (4, 2))  # a registration's prediction, px off
        fit = fit_square_to_edges(steps, kept, camera=CAMERA, object_points_mm=TAG, predicted_px=predicted, max_corner_sigma_px=0.5)
        assert fit is not None
        errors.append(np.linalg.norm(fit.corners_px - truth, axis=1))
        sigmas.append(fit.corner_sigma_px)
        assert fit.rms_px == pytest.approx(STEP_NOISE_PX, rel=0.3)  # the steps scatter across their line by their noise
    rms = np.sqrt(np.mean(np.square(errors), axis=0) / 2.0)  # per corner, per axis
    stated = np.mean(sigmas, axis=0)
    # Corners 0 and 1 lie on the hidden edge 0: placed from the others, and stated so.
    assert np.all(rms[:2] > 2.0 * rms[2:]) and np.all(stated[:2] > 2.0 * stated[2:])
    assert np.all(rms < 0.3), rms
    assert np.all((rms > 0.7 * stated) & (rms < 1.4 * stated)), (rms, stated)


def test_a_geometry_that_cannot_place_the_hidden_edge_is_refused():
    """Tilted 50 deg about the hidden edge's direction: the sides beside it are foreshortened and their convergence
    is all that says how long they are; the corners on the hidden edge move by tens of pixels."""
    rng = np.random.default_rng(1)
    rot, _ = cv2.Rodrigues(np.array([np.radians(50.0), 0.1, 0.3]))
    t = np.array([20.0, -10.0, 250.0])
    refused = 0
    for _ in range(20):
        steps, kept, truth = _steps(rng, rot, t, hidden=1)
        fit = fit_square_to_edges(steps, kept, camera=CAMERA, object_points_mm=TAG, predicted_px=truth + rng.normal(0.0, 1.0, (4, 2)),
                                  max_corner_sigma_px=0.5)
        refused += fit is None
        if fit is not None:  # what is taken is within the limit it was held to
            assert np.linalg.norm(fit.corners_px - truth, axis=1).max() < 5 * 0.5
    assert refused >= 18


@pytest.mark.parametrize("tilt_deg", [30.0, 45.0, 65.0])
def test_a_prediction_far_off_at_one_corner_does_not_settle_the_fit_on_another_pose(tilt_deg):
    """Tilted about the sides beside the hidden edge (foreshortening it), a few steps of that edge seen beside one of
    its corners, the other corner predicted 15-30 px off (as a pose from three corners with one displaced predicts
    it). Twin seed 3006: started from such a prediction alone, the fit settled on a pose 17 px off at that corner and
    stated 0.22 px."""
    rng = np.random.default_rng(3)
    rot, _ = cv2.Rodrigues(np.array([0.0, np.radians(tilt_deg), 0.3]))
    t = np.array([20.0, -10.0, 250.0])
    for _ in range(20):
        steps, kept, truth = _steps(rng, rot, t, hidden=0)
        kept[0, -5:] = True  # edge 0's last steps, beside corner 1
        predicted = truth + rng.normal(0.0, 0.3, (4, 2))
        angle = rng.uniform(0.0, 2 * np.pi)
        predicted[0] = truth[0] + rng.uniform(15.0, 30.0) * np.array([np.cos(angle), np.sin(angle)])
        fit = fit_square_to_edges(steps, kept, camera=CAMERA, object_points_mm=TAG, predicted_px=predicted, max_corner_sigma_px=0.25)
        assert fit is not None
        err = np.linalg.norm(fit.corners_px - truth, axis=1)
        assert err.max() < 0.4, (err, fit.corner_sigma_px)


def test_too_few_steps_or_wrong_shapes():
    rng = np.random.default_rng(2)
    rot, _ = cv2.Rodrigues(np.array([0.2, 0.1, 0.3]))
    steps, kept, truth = _steps(rng, rot, np.array([0.0, 0.0, 250.0]), hidden=0)
    few = np.zeros_like(kept)
    few[1, :3] = few[2, :3] = True
    assert fit_square_to_edges(steps, few, camera=CAMERA, object_points_mm=TAG, predicted_px=truth, max_corner_sigma_px=0.5) is None
    with pytest.raises(ValueError, match="points_px"):
        fit_square_to_edges(steps[:3], kept[:3], camera=CAMERA, object_points_mm=TAG, predicted_px=truth, max_corner_sigma_px=0.5)


# A twin frame (surgeon's markers, glare on glossy tags; seed 5114, inlet+outlet, the study's second freehand pose):
# marker 33's tag has a highlight over most of its edge 1, and ArUco misses it. Found by a scan of seeds 5100-5139.
GLARED_SEED, GLARED_POSE, GLARED_MARKER = 5114, 1, 33


def test_a_glared_tag_with_one_edge_hidden_is_recovered_by_the_square_fit():
    scene = make_scene(seed=GLARED_SEED, views="inlet,outlet", render=False, degradations=Degradations.parse("surgeon_markers,tag_glare"))
    pose_rng, camera_rng = np.random.default_rng([GLARED_SEED, 0, 2]), np.random.default_rng([GLARED_SEED, 0, 3])
    for _ in range(GLARED_POSE + 1):  # the study's freehand poses, in order (benchmarks/accuracy.py camera_shots)
        pose = scene.drill_pose_towards(pose_rng, offset_mm=5.0, tilt_deg=5.0)
        image = scene.render_camera(camera_rng, carm_from_drill=pose)
    locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_set=scene.marker_set)
    video = locator.locate(image)
    truth = _true_corners(scene, pose)[GLARED_MARKER]
    assert GLARED_MARKER not in video.by_id()
    predicted = predict_tag_corners(carm_from_drill=pose, carm_from_marker=scene.carm_from_marker[GLARED_MARKER],
                                    tag_corners_marker_mm=scene.marker_set.by_id(GLARED_MARKER).tag_corners_mm(), camera=scene.calibrated_camera)
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float32) if image.ndim == 3 else image.astype(np.float32)
    four_edges = recover_tag(gray, predicted, aruco_id=scene.marker_set.by_id(GLARED_MARKER).aruco_id, partial=True)
    assert not four_edges.accepted and four_edges.reason.startswith("edge 1: a clean border step along only"), four_edges.reason
    found = locator.recover(image, video, {GLARED_MARKER: predicted}).by_id()
    assert GLARED_MARKER in found and found[GLARED_MARKER].recovered
    assert found[GLARED_MARKER].corner_sigma_px == RECOVERED_CORNER_SIGMA_PX
    assert np.linalg.norm(found[GLARED_MARKER].corners_px - truth, axis=1).max() < 0.3  # measured 0.03 px


def test_a_decoded_tag_with_one_edge_hidden_gets_its_corners_from_the_other_three():
    """Twin seed 5012, every camera degradation, second drill pose: ArUco decodes marker 36, but a highlight leaves
    one edge with no clean stretch, so neither the edge-line fit nor the four-edge search places it, and the
    detector's own corners are 3.47 px off at worst. Its other three edges place it within a pixel (0.74 px
    measured)."""
    from drillnav.drivers.sim.degradations import CAMERA

    seed, marker = 5012, 36
    scene = make_scene(seed=seed, views="inlet,outlet", render=False, degradations=Degradations.parse(",".join(CAMERA)))
    rng = np.random.default_rng(seed)
    for _ in range(2):
        pose = scene.drill_pose_towards(rng, offset_mm=5.0, tilt_deg=5.0)
        frame = scene.render_camera(rng, carm_from_drill=pose)
    found = VideoMarkerLocator(camera=scene.calibrated_camera, marker_set=scene.marker_set).locate(frame).by_id()
    assert marker in found, "ArUco no longer decodes the tag"
    err = np.linalg.norm(found[marker].corners_px - _true_corners(scene, pose)[marker], axis=1)
    assert err.max() < 1.0, err
    assert not found[marker].recovered
