"""An image intensifier's distortion: told by the DICOM, estimated per view by the joint solve, carried by the bound.

Pincushion and S distortion move a BB near the field's corner by several pixels, smoothly, so a marker's BBs
still fit a slightly wrong pose: the residuals do not show it, and one view's depth along the beam (its
magnification) is pulled off. The camera knows the markers' constellation in 3D, so markers at different radii
reveal the distortion when the view says it comes from an intensifier. Detections are the design's BBs
projected, moved by a known distortion and 0.35 px of noise; the tag corners are projected with 0.3 px.
"""

import cv2
import numpy as np
import pytest

from drillnav.drivers.fluoro_dicom import read_fluoro
from drillnav.drivers.sim.dicom_io import write_xa
from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, make_scene
from drillnav.registration.carm import IMAGE_INTENSIFIER_DISTORTION_PX, CArmView, intensifier_shift_px
from drillnav.registration.fluoro_markers import DetectedBB, DetectedMarker, FluoroDetections
from drillnav.registration.joint_solve import joint_solve, project_distorted
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.transforms import apply, make_transform
from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro
from drillnav.registration.video_markers import VideoDetections, VideoMarker
from drillnav.schemas.projection import read_projection, write_projection

TRUE_SHIFT_PX = np.array([8.0, -6.0])  # pincushion and S at the field's corner


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=11, views="inlet,outlet", render=False)


def _register(scene, rng, sigma_px: float, name: str = "outlet", true_shift_px=TRUE_SHIFT_PX):
    """One single-view registration of the 5 markers: (position error mm, 90 % bound mm, registration)."""
    plain = scene.views[name]
    view = CArmView(projection_matrix=plain.projection_matrix, rows=plain.rows, columns=plain.columns,
                    pixel_spacing_mm=plain.pixel_spacing_mm, distortion_sigma_px=sigma_px)
    found = []
    for i, pose in scene.carm_from_marker.items():
        uv = view.project(apply(pose, scene.marker_set.by_id(i).bb_centers_mm))
        uv = uv + intensifier_shift_px(uv, view.center_px, view.corner_radius_px, true_shift_px) + rng.normal(scale=0.35, size=uv.shape)
        bbs = tuple(DetectedBB(center_px=p, diameter_px=10.0, large=False) for p in uv)
        found.append(DetectedMarker(marker_id=i, bbs=bbs, bb_index=np.arange(len(uv)), ring_ellipse=((0.0, 0.0), (1.0, 1.0), 0.0), mirrored=False,
                                    identification_cost_mm=0.0))
    poses = register_markers([FluoroDetections(markers=tuple(found), rejected=())], [view], scene.marker_set)
    camera = scene.true_camera
    carm_from_drill = scene.drill_pose_towards(rng, offset_mm=5.0, tilt_deg=5.0)
    markers = []
    for i, camera_from_marker in sorted(scene.camera_from_marker(carm_from_drill).items()):
        design = scene.marker_set.by_id(i)
        corners = camera.project(apply(camera_from_marker, design.tag_corners_mm())) + rng.normal(scale=0.3, size=(4, 2))
        _, rv, tv = cv2.solvePnP(design.tag_corners_mm() - design.tag_center_mm, corners, camera.camera_matrix, camera.distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        camera_from_tag = make_transform(cv2.Rodrigues(rv)[0], tv.ravel())
        markers.append(VideoMarker(marker_id=i, corners_px=corners, camera_from_tag=camera_from_tag, reprojection_error_px=0.0,
                                   position_camera_mm=apply(camera_from_tag, -np.asarray(design.tag_center_mm)), covariance_mm2=0.01 * np.eye(3)))
    video = VideoDetections(markers=tuple(markers), ignored_ids=(), image_size=(camera.width, camera.height))
    reg = register_video_to_fluoro(video, poses, scene.marker_set, camera)
    entry = scene.corridor_entry_carm_mm
    axis, true_axis = TRUE_DRILL_AXIS_CAMERA.transformed(reg.carm_from_drill), TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
    pe = predicted_axis_error(video, poses, reg, TRUE_DRILL_AXIS_CAMERA, working_point_carm_mm=entry)
    return float(np.linalg.norm(axis.closest_point(entry) - true_axis.closest_point(entry))), pe.position90_mm, reg


def test_an_intensifier_view_has_its_distortion_estimated_and_bounded(scene):
    rng = np.random.default_rng(2026)
    flat = np.array([_register(scene, rng, 0.0)[:2] for _ in range(8)])
    rng = np.random.default_rng(2026)
    runs = [_register(scene, rng, IMAGE_INTENSIFIER_DISTORTION_PX) for _ in range(8)]
    ii = np.array([r[:2] for r in runs])
    # Taken for a flat panel, the distorted view's errors are several times the bound that claims them;
    # told it is an intensifier, the solve finds the distortion and the error falls within its bound.
    # (Seeded: 1.79 mm median against 0.97, the bound covering 8 of 8 then. Taken for a flat panel, the bound still
    # covers 6 of 8 here: the BBs' shared shift and scale, stated at an unmodelled intensifier's size for every
    # view, carry part of it, but the error stays.)
    assert np.median(flat[:, 0]) > 1.5 * np.median(ii[:, 0]), (flat[:, 0], ii[:, 0])
    assert np.mean(ii[:, 0] <= ii[:, 1]) >= 0.75, ii
    # Markers within half the field's radius see an eighth of the corner's shift, so one view's estimate is
    # rough (2-11 px here), but it moves towards the truth: the bound carries the rest.
    estimates = np.array([reg.detector_distortion_px[0][1] for _, _, reg in runs])
    assert np.mean(np.linalg.norm(estimates - TRUE_SHIFT_PX, axis=1)) < 0.7 * np.linalg.norm(TRUE_SHIFT_PX), estimates
    view, coef = runs[-1][2].detector_distortion_px[0]
    # The estimate moves the projection as the detector did (what an overlay on that image needs).
    corner = np.array([[view.columns - 1.0, view.rows - 1.0]])
    moved = intensifier_shift_px(corner, view.center_px, view.corner_radius_px, TRUE_SHIFT_PX)
    assert np.allclose(np.linalg.norm(moved), np.linalg.norm(TRUE_SHIFT_PX))
    point = np.array([[10.0, 20.0, 30.0]])
    assert np.allclose(project_distorted(view, point, ((view, coef),)) - view.project(point),
                       intensifier_shift_px(view.project(point), view.center_px, view.corner_radius_px, coef))


def test_an_intensifier_is_pincushion_never_barrel(scene):
    """Its curved input screen makes an intensifier's radial distortion outward at the edge: the solve holds a barrel
    (which no intensifier makes) to a tenth of the prior a pincushion gets. Fed a barrel of the pincushion's size,
    it estimates about none of it, where it finds most of the pincushion."""
    def estimate(shift):
        rng = np.random.default_rng(7)
        return np.array([_register(scene, rng, IMAGE_INTENSIFIER_DISTORTION_PX, true_shift_px=shift)[2].detector_distortion_px[0][1] for _ in range(4)])

    pincushion = estimate(np.array([10.0, 0.0]))
    barrel = estimate(np.array([-10.0, 0.0]))
    assert np.median(pincushion[:, 0]) > 4.0, pincushion
    assert np.all(barrel[:, 0] > -2.0), barrel


def test_a_flat_panel_view_adds_no_distortion(scene):
    _, _, reg = _register(scene, np.random.default_rng(5), 0.0)
    assert reg.detector_distortion_px == ()


@pytest.mark.parametrize("intensifier", [True, False])
@pytest.mark.parametrize("pixel_mm", [0.304, 0.608])
def test_the_dicom_says_which_detector(tmp_path, intensifier, pixel_mm):
    """An intensifier's distortion prior is a size at the detector: 10 px of 0.304 mm, 5 px read out binned 2 x 2."""
    path = write_xa(tmp_path / "shot.dcm", np.full((64, 64), 2.0, np.float32), primary_deg=0, secondary_deg=-25, source_to_detector_mm=1164,
                    source_to_isocenter_mm=624, pixel_spacing_mm=(pixel_mm, pixel_mm), study_uid="1.2.3", series_uid="1.2.3.4", instance_number=1,
                    image_intensifier=intensifier)
    (image,) = read_fluoro(path)
    assert image.view.distortion_sigma_px == pytest.approx(IMAGE_INTENSIFIER_DISTORTION_PX * 0.304 / pixel_mm if intensifier else 0.0)
    # A calibrated projection JSON says it itself (0 when absent: a dewarped image or a flat panel).
    write_projection(tmp_path / "p.json", image.view)
    assert read_projection(tmp_path / "p.json").distortion_sigma_px == image.view.distortion_sigma_px
    (again,) = read_fluoro(path, projection=tmp_path / "p.json")
    assert again.view.distortion_sigma_px == image.view.distortion_sigma_px


def test_a_negative_distortion_size_is_refused():
    with pytest.raises(ValueError, match="distortion_sigma_px"):
        CArmView(projection_matrix=np.hstack([np.eye(3), np.zeros((3, 1))]), rows=10, columns=10, pixel_spacing_mm=(0.3, 0.3), distortion_sigma_px=-1.0)


def test_the_shot_on_the_bus_keeps_the_detector(scene):
    """The node builds its views from the bus's FluoroShot: an intensifier's view must stay one there."""
    from drillnav.schemas.messages import FluoroShot

    plain = scene.views["outlet"]
    view = CArmView(projection_matrix=plain.projection_matrix, rows=plain.rows, columns=plain.columns, pixel_spacing_mm=plain.pixel_spacing_mm,
                    distortion_sigma_px=IMAGE_INTENSIFIER_DISTORTION_PX)
    shot = FluoroShot.build(np.full((plain.rows, plain.columns), 1.0, np.float32), view, stamp_ns=1, view_name="outlet")
    again = FluoroShot.from_bytes(shot.to_bytes())
    assert again.carm_view.distortion_sigma_px == IMAGE_INTENSIFIER_DISTORTION_PX
    flat = FluoroShot.build(np.full((plain.rows, plain.columns), 1.0, np.float32), plain, stamp_ns=1, view_name="outlet")
    assert flat.carm_view.distortion_sigma_px == 0.0


def _two_view_shots(scene, rng):
    """Both views of ``scene`` as intensifier views, every marker's BBs moved by TRUE_SHIFT_PX and 0.35 px noise."""
    views = [CArmView(projection_matrix=v.projection_matrix, rows=v.rows, columns=v.columns, pixel_spacing_mm=v.pixel_spacing_mm,
                      distortion_sigma_px=IMAGE_INTENSIFIER_DISTORTION_PX) for v in scene.views.values()]
    detections = []
    for view in views:
        found = []
        for i, pose in scene.carm_from_marker.items():
            uv = view.project(apply(pose, scene.marker_set.by_id(i).bb_centers_mm))
            uv = uv + intensifier_shift_px(uv, view.center_px, view.corner_radius_px, TRUE_SHIFT_PX) + rng.normal(scale=0.35, size=uv.shape)
            found.append(DetectedMarker(marker_id=i, bbs=tuple(DetectedBB(center_px=p, diameter_px=10.0, large=False) for p in uv),
                                        bb_index=np.arange(len(uv)), ring_ellipse=((0.0, 0.0), (1.0, 1.0), 0.0), mirrored=False,
                                        identification_cost_mm=0.0))
        detections.append(FluoroDetections(markers=tuple(found), rejected=()))
    return {p.marker_id: p for p in register_markers(detections, views, scene.marker_set)}


def test_markers_the_camera_does_not_see_help_estimate_the_distortion(scene):
    """Two views, the camera on two of the five markers: the other three, posed in both views, join the solve with
    poses of their own. Their BBs show the distortion over more of the field (seeded: the two views' estimates
    3.98 -> 2.03 px off the truth on average over 8 draws, the axis at the entry 0.17 -> 0.14 mm at the median)."""
    rng = np.random.default_rng(7)
    seen = sorted(scene.carm_from_marker)[:2]
    entry = scene.corridor_entry_carm_mm
    off_px, axis_mm = [], []
    for _ in range(8):
        poses = _two_view_shots(scene, rng)
        carm_from_drill = scene.drill_pose_towards(rng, offset_mm=5.0, tilt_deg=5.0)
        camera = scene.true_camera
        corners = {i: camera.project(apply(t, scene.marker_set.by_id(i).tag_corners_mm())) + rng.normal(scale=0.3, size=(4, 2))
                   for i, t in scene.camera_from_marker(carm_from_drill).items() if i in seen}
        solve = dict(observations={i: poses[i].observations for i in seen}, corners_px=corners, marker_set=scene.marker_set, camera=camera,
                     carm_from_drill0=carm_from_drill, carm_from_marker0={i: poses[i].carm_from_marker for i in seen}, min_markers=2)
        row_off, row_axis = [], []
        for fluoro_only in (None, {i: (p.observations, p.carm_from_marker) for i, p in poses.items() if i not in seen}):
            sol = joint_solve(**solve, fluoro_only=fluoro_only)
            assert sol.used_ids == tuple(seen) and set(sol.carm_from_marker) == set(seen)  # the others vote on nothing
            assert len(sol.detector_distortion_px) == 2
            row_off.append(np.mean([np.linalg.norm(c - TRUE_SHIFT_PX) for _, c in sol.detector_distortion_px]))
            axis, true_axis = TRUE_DRILL_AXIS_CAMERA.transformed(sol.carm_from_drill), TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
            row_axis.append(float(np.linalg.norm(axis.closest_point(entry) - true_axis.closest_point(entry))))
        off_px.append(row_off)
        axis_mm.append(row_axis)
    off_px, axis_mm = np.array(off_px), np.array(axis_mm)
    assert off_px[:, 1].mean() < 0.7 * off_px[:, 0].mean(), off_px
    assert np.median(axis_mm[:, 1]) <= 1.1 * np.median(axis_mm[:, 0]), axis_mm


def test_a_marker_seen_in_one_view_only_is_left_out_of_the_distortion(scene):
    """In one view a marker's own pose takes up the distortion's shift: it would add unknowns and no information."""
    poses = _two_view_shots(scene, np.random.default_rng(3))
    seen = sorted(scene.carm_from_marker)[:2]
    rng = np.random.default_rng(4)
    carm_from_drill = scene.drill_pose_towards(rng, offset_mm=5.0, tilt_deg=5.0)
    corners = {i: scene.true_camera.project(apply(t, scene.marker_set.by_id(i).tag_corners_mm()))
               for i, t in scene.camera_from_marker(carm_from_drill).items() if i in seen}
    solve = dict(observations={i: poses[i].observations for i in seen}, corners_px=corners, marker_set=scene.marker_set, camera=scene.true_camera,
                 carm_from_drill0=carm_from_drill, carm_from_marker0={i: poses[i].carm_from_marker for i in seen}, min_markers=2)
    plain = joint_solve(**solve)
    one_view = joint_solve(**solve, fluoro_only={i: (p.observations[:1], p.carm_from_marker) for i, p in poses.items() if i not in seen})
    assert np.allclose(one_view.carm_from_drill, plain.carm_from_drill)
    two_views = joint_solve(**solve, fluoro_only={i: (p.observations, p.carm_from_marker) for i, p in poses.items() if i not in seen})
    assert not np.allclose(two_views.carm_from_drill, plain.carm_from_drill)
