"""The predicted 90 % bound covers about 90 % of the errors, also when the measurement noise is larger than assumed.

A Monte-Carlo over everything the product is uncertain about, each drawn at its stated size: the camera
calibration (focal length, principal point and distortion: joint_solve's priors), the drill axis calibration
(drill.json's 0.1 mm / 0.12 deg RMS tilt), the fluoroscopy BB centres and the tag corners (the noise the joint
solve assumes, then twice that: only the residuals can tell, and the bound must follow them). Geometry from
the twin; the detections are the design's BBs and tag corners projected with that noise, so each draw is fast.
"""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drillnav.drivers.sim.scene import NAMED_VIEWS, PAPER_CARM, TRUE_DRILL_AXIS_CAMERA, _perturbed_axis, make_scene
from drillnav.registration.axis_uncertainty import AxisUncertainty
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.camera_uncertainty import DEFAULT_INTRINSICS_UNCERTAINTY, IntrinsicsUncertainty
from drillnav.registration.carm import CArmView
from drillnav.registration.errors import DrillnavError
from drillnav.registration.fluoro_markers import DetectedBB, DetectedMarker, FluoroDetections
from drillnav.registration.joint_solve import BB_COMMON_SIGMA_PX, BB_SCALE_SIGMA_PX, CORNER_COMMON_PER_SIGMA, CORNER_SCALE_PER_SIGMA
from drillnav.registration.line import Line3D
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.transforms import apply, make_transform
from drillnav.registration.video_fluoro import RELIABLE_ANGLE_DEG, DrillRegistration, predicted_axis_error, register_video_to_fluoro
from drillnav.registration.video_markers import VideoDetections, VideoMarker

BB_SIGMA_PX, CORNER_SIGMA_PX = 0.35, 0.3  # joint_solve's noise model
DRAWS = 40


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=11, views="inlet,outlet", render=False)


def _video(camera: PinholeCamera, marker_set, corners: dict) -> VideoDetections:
    """Tag poses from noisy corners with the calibrated camera, as the locator solves them (IPPE for squares)."""
    out = []
    for i, c in sorted(corners.items()):
        design = marker_set.by_id(i)
        obj = design.tag_corners_mm() - design.tag_center_mm
        _, rv, tv = cv2.solvePnP(obj, c, camera.camera_matrix, camera.distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        camera_from_tag = make_transform(cv2.Rodrigues(rv)[0], tv.ravel())
        out.append(VideoMarker(marker_id=i, corners_px=c, camera_from_tag=camera_from_tag, position_camera_mm=apply(camera_from_tag, -np.asarray(design.tag_center_mm)),
                               covariance_mm2=0.01 * np.eye(3), reprojection_error_px=0.0))
    return VideoDetections(markers=tuple(out), ignored_ids=(), image_size=(camera.width, camera.height))


def _shared(rng, px: np.ndarray, shift_px: float, scale_px: float) -> np.ndarray:
    """A group's image points (N, 2) moved together: one shift (per axis) and one scale (radial, at the mean radius)."""
    rel = px - px.mean(axis=0)
    radius = float(np.mean(np.linalg.norm(rel, axis=1)))
    return px + rng.normal(scale=shift_px, size=2) + rng.normal(scale=scale_px) * rel / radius


def _draw(scene, rng, noise_scale: float, names=None, *, full: bool = False, views=None, marker_ids=None, shared: bool = False,
          drill: AxisUncertainty = AxisUncertainty(), stated: tuple[AxisUncertainty, ...] = (),
          intrinsics: IntrinsicsUncertainty = DEFAULT_INTRINSICS_UNCERTAINTY, state_intrinsics: bool = False):
    """One registration: (position error mm, angle error deg, 90 % position bound, 90 % angle bound).

    ``drill``: the drill axis's calibration error is drawn at this size, and the bound states it; ``stated``: the
    bound also with each of these (two more bounds each, after the first four). ``intrinsics``: the camera
    calibration's error is drawn at this size; ``state_intrinsics``: its camera states it (camera.json's
    ``intrinsics_sigma``).

    ``names``: the scene's views used (default all), or ``views``: CArmViews of other positioner angles;
    ``marker_ids``: the markers placed (default all); ``full``: also the registration and the predicted error;
    ``shared``: each tag's corners and each marker's BBs in each view also moved together, by the shift and scale
    the joint solve states (as the operating room's blur, exposure and image-intensifier distortion move them).
    """
    true = scene.true_camera
    k = true.camera_matrix.copy()
    f = 1.0 + rng.normal(scale=intrinsics.focal_rel)
    k[0, 0] *= f
    k[1, 1] *= f
    k[:2, 2] += rng.normal(scale=intrinsics.principal_px, size=2)
    distortion = true.distortion.copy()
    distortion[:5] += rng.normal(scale=intrinsics.distortion)
    camera = PinholeCamera(width=true.width, height=true.height, camera_matrix=k, distortion=distortion, uncertainty=intrinsics if state_intrinsics else None)
    perp = np.linalg.svd(TRUE_DRILL_AXIS_CAMERA.direction[None])[2][1:]  # (2, 3): the two tilt directions
    tilt = np.radians(drill.per_direction_deg) * rng.normal(size=2) @ perp
    axis = Line3D(point_mm=TRUE_DRILL_AXIS_CAMERA.point_mm + rng.normal(scale=drill.sigma_mm, size=3),
                  direction=Rotation.from_rotvec(tilt).apply(TRUE_DRILL_AXIS_CAMERA.direction))
    carm_from_drill = scene.drill_pose_towards(rng, offset_mm=5.0, tilt_deg=5.0)
    if views is None:
        views = [scene.views[n] for n in (list(scene.views) if names is None else names)]
    placed = {i: t for i, t in scene.carm_from_marker.items() if marker_ids is None or i in marker_ids}
    dets = []
    for view in views:
        found = []
        for i, pose in placed.items():
            design = scene.marker_set.by_id(i)
            px = view.project(apply(pose, design.bb_centers_mm)) + rng.normal(scale=BB_SIGMA_PX * noise_scale, size=(len(design.bbs), 2))
            if shared:
                px = _shared(rng, px, BB_COMMON_SIGMA_PX, BB_SCALE_SIGMA_PX)
            bbs = tuple(DetectedBB(center_px=p, diameter_px=10.0, large=False) for p in px)
            found.append(DetectedMarker(marker_id=i, bbs=bbs, bb_index=np.arange(len(px)), ring_ellipse=((0.0, 0.0), (1.0, 1.0), 0.0), mirrored=False, identification_cost_mm=0.0))
        dets.append(FluoroDetections(markers=tuple(found), rejected=()))
    poses = register_markers(dets, views, scene.marker_set)
    corners = {i: true.project(apply(t, scene.marker_set.by_id(i).tag_corners_mm())) + rng.normal(scale=CORNER_SIGMA_PX * noise_scale, size=(4, 2))
               for i, t in scene.camera_from_marker(carm_from_drill).items() if i in placed}
    if shared:
        corners = {i: _shared(rng, c, CORNER_SIGMA_PX * CORNER_COMMON_PER_SIGMA, CORNER_SIGMA_PX * CORNER_SCALE_PER_SIGMA) for i, c in corners.items()}
    video = _video(camera, scene.marker_set, corners)
    reg = register_video_to_fluoro(video, poses, scene.marker_set, camera)
    entry = scene.corridor_entry_carm_mm
    found_axis = axis.transformed(reg.carm_from_drill)
    true_axis = TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
    pe, *others = [predicted_axis_error(video, poses, reg, axis, working_point_carm_mm=entry, axis_sigma_mm=u.sigma_mm, axis_sigma_deg=u.per_direction_deg)
                   for u in (drill, *stated)]
    pos = float(np.linalg.norm(found_axis.closest_point(entry) - true_axis.closest_point(entry)))
    out = (pos, found_axis.angle_deg(true_axis), pe.position90_mm, pe.angle90_deg, *(b for o in others for b in (o.position90_mm, o.angle90_deg)))
    return (*out, reg, pe) if full else out


@pytest.mark.parametrize("noise_scale", [1.0, 2.0])
def test_the_90_percent_bound_covers_about_90_percent(scene, noise_scale):
    rng = np.random.default_rng(20261129)
    a = np.array([_draw(scene, rng, noise_scale) for _ in range(DRAWS)])
    cover_pos, cover_ang = float(np.mean(a[:, 0] <= a[:, 2])), float(np.mean(a[:, 1] <= a[:, 3]))
    # 40 draws (seeded, so the figures are fixed: 0.80 / 0.875 at the assumed noise, 0.75 / 0.85 at twice it;
    # 200 draws at the assumed noise: 0.87 / 0.90): a true 90 % coverage lands in 0.78-0.98 with 95 %
    # probability. The former single chi-square scaling, which also scaled the calibration prior, covered
    # 1.0 / 1.0 here at twice the noise.
    assert 0.75 <= cover_pos <= 0.975 and 0.75 <= cover_ang <= 0.975, (cover_pos, cover_ang)
    # The bound is not inflated: the typical error is about half its bound (the median of a 2-D Rayleigh is
    # 0.55 of its 90th percentile; the former scaling gave 0.34 for the position at twice the noise).
    assert 0.45 <= float(np.median(a[:, 0] / a[:, 2])) <= 0.75
    assert 0.45 <= float(np.median(a[:, 1] / a[:, 3])) <= 0.75


@pytest.mark.parametrize("names", [None, ["outlet"]])
def test_the_bound_covers_errors_shared_by_a_tag_and_by_a_marker_view(scene, names):
    """Each tag's corners and each marker's BBs in a view also moved together, at the sizes the joint solve states
    (blur and exposure move a tag's edges together, an image intensifier a marker's BBs): the pose absorbs
    such errors, so the residuals cannot show them, and the bound must carry them from the stated model.
    Measured (40 seeded draws, position / angle): two views 0.875 / 0.90, outlet alone 0.825 / 0.875; without the
    shared terms in the joint solve (the former model) two views 0.775 / 0.775 and outlet alone 0.65 / 0.65, which fails."""
    rng = np.random.default_rng(20261130)
    a = np.array([_draw(scene, rng, 1.0, names, shared=True) for _ in range(DRAWS)])
    cover_pos, cover_ang = float(np.mean(a[:, 0] <= a[:, 2])), float(np.mean(a[:, 1] <= a[:, 3]))
    assert 0.75 <= cover_pos <= 0.975 and 0.75 <= cover_ang <= 0.975, (cover_pos, cover_ang)
    assert 0.4 <= float(np.median(a[:, 0] / a[:, 2])) <= 0.75 and 0.4 <= float(np.median(a[:, 1] / a[:, 3])) <= 0.75


def test_a_drill_calibration_stated_worse_widens_the_bound_to_its_errors(scene):
    """drill.json states the axis's calibration uncertainty, and the bound must carry it as stated: drill-axis
    errors drawn at 0.4 mm / 0.5 deg RMS tilt (4 times the default), bounded with that statement, are covered
    about 90 %; bounded with the defaults they are not (30 seeded draws, position / angle: 0.87 / 0.87 stated,
    0.27 / 0.47 with the defaults)."""
    worse = AxisUncertainty(sigma_mm=0.4, rms_tilt_deg=0.5)
    rng = np.random.default_rng(20261201)
    a = np.array([_draw(scene, rng, 1.0, drill=worse, stated=(AxisUncertainty(),)) for _ in range(30)])
    stated = float(np.mean(a[:, 0] <= a[:, 2])), float(np.mean(a[:, 1] <= a[:, 3]))
    default = float(np.mean(a[:, 0] <= a[:, 4])), float(np.mean(a[:, 1] <= a[:, 5]))
    assert 0.75 <= stated[0] <= 0.975 and 0.75 <= stated[1] <= 0.975, (stated, default)
    assert default[0] < 0.65 and default[1] < 0.65, (stated, default)


def test_a_camera_calibration_stated_worse_widens_the_priors_and_the_bound(scene):
    """camera.json may state its intrinsics' uncertainty; the joint solve's priors (so the bound) take it where
    it is over a typical calibration's. A camera calibrated 5 times worse than typical (focal 1 %, principal
    point 4 px, distortion 3x), stated: covered about 90 %; not stated, the priors hold the camera too tightly
    and the bound does not cover its errors (30 seeded draws each, position / angle: 0.97 / 0.97 stated, 0.33 /
    0.57 not)."""
    worse = IntrinsicsUncertainty(focal_rel=0.01, principal_px=4.0, distortion=tuple(3 * v for v in DEFAULT_INTRINSICS_UNCERTAINTY.distortion))
    cover = {}
    for state in (True, False):
        rng = np.random.default_rng(20261202)
        a = np.array([_draw(scene, rng, 1.0, intrinsics=worse, state_intrinsics=state) for _ in range(30)])
        cover[state] = float(np.mean(a[:, 0] <= a[:, 2])), float(np.mean(a[:, 1] <= a[:, 3]))
    assert 0.75 <= min(cover[True]) and max(cover[True]) <= 0.975, cover
    assert min(cover[False]) < 0.7, cover
    # Stated smaller than typical (OpenCV's formal figures often are): the priors stay at the typical size.
    from drillnav.registration.camera_uncertainty import camera_priors

    small = IntrinsicsUncertainty(focal_rel=0.0002, principal_px=0.1, distortion=(0.0,) * 5)
    assert camera_priors(small) == DEFAULT_INTRINSICS_UNCERTAINTY and camera_priors(None) == DEFAULT_INTRINSICS_UNCERTAINTY


def test_drill_json_states_the_uncertainty_and_an_unknown_one_takes_the_defaults(tmp_path):
    from drillnav.schemas.calibration import read_drill_uncertainty, write_drill_calibration

    write_drill_calibration(tmp_path / "d.json", TRUE_DRILL_AXIS_CAMERA, method="jig", residual_mm=0.3, residual_deg=0.4, label="t")
    assert read_drill_uncertainty(tmp_path / "d.json") == AxisUncertainty(sigma_mm=0.3, rms_tilt_deg=0.4)
    write_drill_calibration(tmp_path / "z.json", TRUE_DRILL_AXIS_CAMERA, method="held as an object", residual_mm=0.0, residual_deg=0.0, label="t")
    assert read_drill_uncertainty(tmp_path / "z.json") == AxisUncertainty()
    assert AxisUncertainty().per_direction_deg == pytest.approx(0.12 / np.sqrt(2))
    with pytest.raises(ValueError, match="sigma_mm"):
        AxisUncertainty(sigma_mm=float("nan"))


def test_single_view_with_weak_geometry_is_flagged(scene):
    """One view whose BB centres scatter far more than assumed (blur, low dose): the depth along the beam is
    poorly fixed, so the predicted angle grows with the residuals and the axis is flagged. Past ~20 px the
    constellation's mirror image (depth swapped) is no longer ruled out: the bound then reaches its axis."""
    rng = np.random.default_rng(7)
    *_, reg, pe = _draw(scene, rng, 1.0, ["inlet"], full=True)
    assert reg.mirror_carm_from_drill is None and pe.reliable
    *_, reg, pe = _draw(scene, rng, 30.0, ["inlet"], full=True)  # ~10 px
    assert pe.angle90_deg > 3.0 and not pe.reliable
    mirrors = 0
    # Eight draws: the mirror stays open in about half of them (3-7 of 8 over three seeds of this rng), so four left
    # the test to one draw sequence's luck.
    for _ in range(8):
        *_, reg, pe = _draw(scene, rng, 60.0, ["inlet"], full=True)  # ~20 px
        assert not pe.reliable
        if reg.mirror_carm_from_drill is not None:
            mirrors += 1
            axis = TRUE_DRILL_AXIS_CAMERA.transformed(reg.carm_from_drill)
            mirror_deg = axis.angle_deg(TRUE_DRILL_AXIS_CAMERA.transformed(reg.mirror_carm_from_drill))
            assert pe.angle90_deg >= mirror_deg - 0.5  # measured with the calibrated axis, not the true one
    assert mirrors >= 1


def test_the_twin_draws_the_axis_calibration_error_from_its_stated_distribution():
    """drill.json's 0.12 deg is an RMS tilt, and the bound assumes a 2-D Gaussian of that RMS (90 % within
    0.18 deg). The twin drew it at exactly 0.12 deg about a random axis (0.098 deg RMS across the drill axis,
    never over 0.12): its errors were smaller than stated, and the bound covered 100 % of them."""
    rng = np.random.default_rng(3)
    tilt = np.array([_perturbed_axis(rng, TRUE_DRILL_AXIS_CAMERA).angle_deg(TRUE_DRILL_AXIS_CAMERA) for _ in range(4000)])
    assert 0.114 <= float(np.sqrt(np.mean(tilt**2))) <= 0.126
    # A 2-D Gaussian with 0.12 deg RMS is over 0.12 deg with probability exp(-1) = 0.37, over 0.18 with 0.10.
    assert 0.33 <= float(np.mean(tilt > 0.12)) <= 0.41 and 0.08 <= float(np.mean(tilt > 0.182)) <= 0.12


def test_no_large_single_view_error_goes_unflagged(scene):
    """Single views at random positioner angles, inlet and lateral, three of the markers, BB centres and tag
    corners three times noisier than assumed: where the depth along the beam is poorly fixed the error can
    reach tens of degrees, and every error over 10 deg must be flagged unreliable (issue 17's bar)."""
    rng = np.random.default_rng(17)
    rows = []
    for k in range(24):
        a, b = (rng.uniform(-90, 90), rng.uniform(-25, 25)) if k % 3 == 0 else NAMED_VIEWS["inlet" if k % 3 == 1 else "lateral"]
        view = CArmView.from_positioner(primary_deg=a, secondary_deg=b, **PAPER_CARM)
        ids = rng.choice(sorted(scene.carm_from_marker), 3, replace=False).tolist()
        try:
            pos, ang, _, a90, _, pe = _draw(scene, rng, 3.0, views=[view], marker_ids=ids, full=True)
        except DrillnavError:
            continue
        rows.append((ang, a90, pe.reliable))
    a = np.array(rows, dtype=float)
    assert len(a) >= 20
    # Weak geometries among them: with the former noise model, blind to errors shared by a group, one was off by
    # 28 deg (bound 28, flagged); weighing the shared shifts and scales, the worst is 1.8 deg (bound 2.3).
    assert a[:, 0].max() > 1.0, a.max(axis=0)
    assert not np.any((a[:, 0] > 10.0) & (a[:, 2] > 0.5)), a[a[:, 0] > 10.0]
    assert not np.any((a[:, 0] > RELIABLE_ANGLE_DEG) & (a[:, 2] > 0.5)), a[a[:, 0] > RELIABLE_ANGLE_DEG]


def test_the_bound_reaches_an_open_mirror_where_its_axis_meets_the_working_point():
    """A mirror turned far from the registered axis (a one-marker registration whose single-view pose is 62 deg off,
    twin seed 11001's inlet view: 123.7 mm off under a 101.5 mm bound) is scored as an error is: its point nearest
    the working point against the registered axis's. Its foot from the registered axis's point lies far nearer."""
    axis = Line3D(point_mm=np.zeros(3), direction=np.array([0.0, 0.0, 1.0]))
    turn = Rotation.from_euler("x", 62.0, degrees=True).as_matrix()
    pivot = np.array([0.0, 60.0, 150.0])
    mirror = make_transform(turn, pivot - turn @ pivot)
    reg = DrillRegistration(carm_from_drill=np.eye(4), carm_from_drill_horn=np.eye(4), fre_mm={7: 0.1}, used_ids=(7,), rejected_ids=(),
                            corner_rms_px=0.2, covariance_drill=np.diag([1e-8] * 3 + [1e-4] * 3), pivot_carm_mm=np.zeros(3),
                            mirror_carm_from_drill=mirror)
    working = np.array([20.0, 50.0, 120.0])
    ref = axis.closest_point(working)
    alt = axis.transformed(mirror)
    at_working = float(np.linalg.norm(alt.closest_point(working) - ref))  # 44.5 mm
    assert at_working - float(np.linalg.norm(alt.closest_point(ref) - ref)) > 30.0  # the foot from ref: 5.3 mm
    pe = predicted_axis_error(VideoDetections(markers=(), ignored_ids=(), image_size=(1280, 720)), (), reg, axis, working_point_carm_mm=working)
    assert pe.position90_mm == pytest.approx(at_working, abs=0.1)
    assert pe.angle90_deg == pytest.approx(62.0, abs=0.1) and not pe.reliable
