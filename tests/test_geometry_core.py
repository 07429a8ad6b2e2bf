"""Round trips and hand-worked cases for the geometry core."""

import numpy as np
import pytest

from drillnav.registration import carm, transforms as tf
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.errors import DegenerateInput
from drillnav.registration.horn import absolute_orientation, absolute_orientation_batch
from drillnav.registration.line import Line3D

RNG = np.random.default_rng(7)


def random_transform(rng, scale_mm=100.0):
    return tf.from_rotvec(rng.normal(size=3), rng.normal(size=3) * scale_mm)


def test_invert_round_trip():
    for _ in range(20):
        t = random_transform(RNG)
        np.testing.assert_allclose(tf.invert(t) @ t, np.eye(4), atol=1e-12)
        tf.check_transform(t)


def test_quaternion_and_rotvec_round_trip():
    for _ in range(20):
        t = random_transform(RNG)
        q = tf.to_quaternion(t)
        assert q[0] >= 0
        np.testing.assert_allclose(tf.from_quaternion(q, t[:3, 3]), t, atol=1e-12)
        rv, tr = tf.to_rotvec(t)
        np.testing.assert_allclose(tf.from_rotvec(rv, tr), t, atol=1e-12)


def test_tiny_angle_rotvec():
    t = tf.from_rotvec([1e-12, 0, 0])
    assert tf.rotation_angle_deg(t) == pytest.approx(0.0, abs=1e-8)


def test_check_transform_rejects_non_rigid():
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="rotation"):
        tf.check_transform(bad)
    with pytest.raises(ValueError, match="4x4"):
        tf.check_transform(np.eye(3))


def test_horn_exact_and_noisy():
    t = random_transform(RNG)
    src = RNG.normal(size=(6, 3)) * 50
    fit = absolute_orientation(src, tf.apply(t, src))
    np.testing.assert_allclose(fit.target_from_source, t, atol=1e-9)
    assert fit.fre_mm < 1e-9
    noisy = tf.apply(t, src) + RNG.normal(scale=0.1, size=src.shape)
    fit = absolute_orientation(src, noisy)
    assert tf.rotation_angle_deg(tf.invert(t) @ fit.target_from_source) < 0.5
    assert 0.02 < fit.fre_mm < 0.3


def test_horn_weights_ignore_outlier():
    t = random_transform(RNG)
    src = RNG.normal(size=(6, 3)) * 50
    dst = tf.apply(t, src)
    dst[0] += 30.0
    w = np.ones(6)
    w[0] = 0.0
    fit = absolute_orientation(src, dst, w)
    np.testing.assert_allclose(fit.target_from_source, t, atol=1e-9)
    assert fit.residuals_mm[0] == pytest.approx(np.linalg.norm([30, 30, 30]), rel=1e-6)


def test_horn_batch_matches_one_at_a_time():
    src = RNG.normal(size=(20, 5, 3)) * 50
    dst = np.stack([tf.apply(random_transform(RNG), p) for p in src]) + RNG.normal(scale=2.0, size=src.shape)
    batch = absolute_orientation_batch(src, dst)
    for b in range(len(src)):
        np.testing.assert_allclose(batch[b], absolute_orientation(src[b], dst[b]).target_from_source, atol=1e-9)
    with pytest.raises(DegenerateInput, match="shape"):
        absolute_orientation_batch(src[:, :2], dst[:, :2])


def test_horn_refuses_collinear():
    src = np.outer(np.arange(4.0), [1, 2, 3])
    with pytest.raises(DegenerateInput, match="collinear"):
        absolute_orientation(src, src)


def test_pinhole_project_backproject_round_trip():
    cam = PinholeCamera.from_fov(width=1280, height=720, horizontal_fov_deg=75, distortion=[-0.2, 0.08, 0.001, -0.0005, -0.01])
    pts = np.column_stack([RNG.uniform(-60, 60, 50), RNG.uniform(-35, 35, 50), RNG.uniform(150, 250, 50)])
    px = cam.project(pts)
    rays = cam.backproject(px)
    np.testing.assert_allclose(rays, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-7)


def test_pinhole_matches_opencv():
    import cv2

    cam = PinholeCamera.from_fov(width=1920, height=1080, horizontal_fov_deg=78, distortion=[0.1, -0.05, 0.002, 0.001, 0.01])
    pts = np.column_stack([RNG.uniform(-60, 60, 20), RNG.uniform(-35, 35, 20), RNG.uniform(150, 250, 20)])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.camera_matrix, cam.distortion)
    np.testing.assert_allclose(cam.project(pts), ref.reshape(-1, 2), atol=1e-8)


PAPER = dict(source_to_detector_mm=1164.0, source_to_isocenter_mm=624.0, pixel_spacing_mm=(0.304, 0.304), rows=976, columns=976)


def test_positioner_ap_hand_worked():
    view = carm.CArmView.from_positioner(primary_deg=0, secondary_deg=0, **PAPER)
    np.testing.assert_allclose(view.source_position_mm, [0, 624, 0], atol=1e-9)  # posterior, under the table
    c = 487.5
    f = 1164 / 0.304
    # Isocentre at the principal point; 10 mm to the patient's left (+x) goes to smaller columns.
    np.testing.assert_allclose(view.project([[0, 0, 0]]), [[c, c]], atol=1e-9)
    np.testing.assert_allclose(view.project([[10, 0, 0]]), [[c - f * 10 / 624, c]], atol=1e-9)
    # 10 mm superior (+z) goes up the image (smaller rows).
    np.testing.assert_allclose(view.project([[0, 0, 10]]), [[c, c - f * 10 / 624]], atol=1e-9)
    assert view.magnification([[0, 0, 0]])[0] == pytest.approx(1164 / 624)


def test_positioner_lao90_and_cra30():
    lao = carm.CArmView.from_positioner(primary_deg=90, secondary_deg=0, **PAPER)
    np.testing.assert_allclose(lao.source_position_mm, [-624, 0, 0], atol=1e-9)  # source at patient's right
    cra = carm.CArmView.from_positioner(primary_deg=0, secondary_deg=30, **PAPER)
    s = np.radians(30)
    np.testing.assert_allclose(cra.source_position_mm, [0, 624 * np.cos(s), -624 * np.sin(s)], atol=1e-9)  # source caudal
    for view in (lao, cra):
        k, source_from_carm = view.decompose()
        tf.check_transform(source_from_carm)
        assert k[0, 0] == pytest.approx(1164 / 0.304)
        assert view.source_to_detector_mm == pytest.approx(1164)


def test_positioner_rejects_nonsense():
    with pytest.raises(ValueError, match="secondary"):
        carm.CArmView.from_positioner(primary_deg=0, secondary_deg=120, **PAPER)
    with pytest.raises(ValueError, match="source-to-isocenter"):
        carm.CArmView.from_positioner(primary_deg=0, secondary_deg=0, **{**PAPER, "source_to_isocenter_mm": 2000})


def test_backproject_and_triangulate():
    ap = carm.CArmView.from_positioner(primary_deg=0, secondary_deg=0, **PAPER)
    lat = carm.CArmView.from_positioner(primary_deg=90, secondary_deg=0, **PAPER)
    x = np.array([12.0, -30.0, 41.0])
    src, d = ap.backproject(ap.project(x))
    assert Line3D(point_mm=src, direction=d[0]).distance_to_point(x) < 1e-8
    np.testing.assert_allclose(carm.triangulate([ap, lat], np.vstack([ap.project(x), lat.project(x)])), x, atol=1e-8)
    with pytest.raises(DegenerateInput):
        carm.triangulate([ap], ap.project(x))


def test_line_projection_and_metrics():
    view = carm.CArmView.from_positioner(primary_deg=20, secondary_deg=-15, **PAPER)
    axis = Line3D(point_mm=[5, 2, -3], direction=[0.3, 0.2, 1.0])
    abc = axis.project(view.projection_matrix)
    px = view.project(axis.at([-50, 0, 70]))
    np.testing.assert_allclose(px @ abc[:2] + abc[2], 0, atol=1e-8)
    other = axis.transformed(tf.from_rotvec([0, 0, np.radians(3)], [1, 0, 0]))
    assert 0 < axis.angle_deg(other) < 4
    centre = axis.at(40.0)[0]
    sphere = lambda p: np.linalg.norm(p - centre, axis=1) - 10.0
    hit = axis.first_crossing(sphere, start_mm=-100, stop_mm=100)
    assert hit is not None and abs(np.linalg.norm(hit - centre) - 10) < 1e-6
    np.testing.assert_allclose(hit, axis.at(30.0)[0], atol=1e-6)


def test_binned_view_matches_block_centres():
    view = carm.CArmView.from_positioner(primary_deg=10, secondary_deg=5, **PAPER)
    small = view.binned(4)
    assert (small.rows, small.columns) == (244, 244)
    x = np.array([[3.0, -7.0, 20.0]])
    np.testing.assert_allclose(small.project(x), (view.project(x) - 1.5) / 4.0, atol=1e-9)


def test_axis_and_transform_json_round_trip():
    from drillnav.schemas.geometry_json import axis_from_json, axis_to_json, transform_from_json, transform_to_json

    t = random_transform(RNG)
    np.testing.assert_allclose(transform_from_json(transform_to_json(t)), t, atol=1e-12)
    axis = Line3D(point_mm=[1, 2, 3], direction=[0, 0, 2])
    back = axis_from_json(axis_to_json(axis))
    np.testing.assert_allclose(back.direction, [0, 0, 1])
    with pytest.raises(ValueError, match="carm_from_drill"):
        transform_from_json([[1, 0], [0, 1]], name="carm_from_drill")
