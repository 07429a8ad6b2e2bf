"""The twin's scene: determinism, geometry, and what the product is handed vs the truth."""

import numpy as np
import pytest

from drillnav.drivers.sim.scene import SceneError, make_scene, parse_views
from drillnav.registration.transforms import invert, rotation_angle_deg


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=3, views="inlet,outlet")


def test_deterministic_per_seed(scene):
    again = make_scene(seed=3, views="inlet,outlet")
    np.testing.assert_array_equal(scene.camera_image, again.camera_image)
    np.testing.assert_array_equal(scene.fluoro_log["inlet"], again.fluoro_log["inlet"])
    other = make_scene(seed=4, render=False)
    assert not np.allclose(other.carm_from_drill, scene.carm_from_drill)


def test_markers_in_view_about_20cm_and_not_coplanar(scene):
    cam = scene.camera_from_marker()
    depths = [t[2, 3] for t in cam.values()]
    assert 150 < np.median(depths) < 260
    for view in scene.views.values():
        px = view.project(np.array([t[:3, 3] for t in scene.carm_from_marker.values()]))
        assert view.contains(px, margin_px=20).all()
    normals = np.array([t[:3, 2] for t in scene.carm_from_marker.values()])
    assert max(np.degrees(np.arccos(np.clip(normals @ normals[0], -1, 1)))) > 2.0


def test_product_is_handed_imperfect_calibrations(scene):
    assert not np.allclose(scene.calibrated_camera.camera_matrix, scene.true_camera.camera_matrix)
    assert 0 < scene.calibrated_axis_drill.angle_deg(scene.drill_axis_carm.transformed(invert(scene.carm_from_drill))) < 1.0
    for i, design in scene.manufactured.items():
        moved = np.linalg.norm(design.bb_centers_mm - scene.marker_set.by_id(i).bb_centers_mm, axis=1)
        assert 0 < moved.max() < 0.5


def test_truth_axis_point_nearest_corridor_entry(scene):
    axis = scene.drill_axis_carm
    entry = scene.corridor_entry_carm_mm
    assert np.dot(entry - axis.point_mm, axis.direction) == pytest.approx(0.0, abs=1e-6)
    assert axis.distance_to_point(entry) < 10.0
    assert rotation_angle_deg(scene.carm_from_ct) < 10


def test_fluoro_shows_tungsten(scene):
    for name, img in scene.fluoro_log.items():
        assert img.shape == (976, 976)
        bb = scene.views[name].project(scene.carm_from_marker[scene.marker_set.ids[0]][:3, 3])[0]
        assert img[int(round(bb[1])), int(round(bb[0]))] > np.median(img) + 1.0


def test_bad_requests():
    with pytest.raises(SceneError, match="unknown view"):
        parse_views("ap,sideways")
    with pytest.raises(SceneError, match="secondary"):
        parse_views("10:120")
    with pytest.raises(SceneError, match="1..7"):
        make_scene(seed=1, n_markers=12, render=False)


def test_cylinder_line_integrals_match_sampling():
    """The K-wire's exact chords against a brute-force count of samples inside the cylinder."""
    from drillnav.drivers.sim.xray import add_cylinder, pixel_rays
    from drillnav.registration.carm import CArmView

    view = CArmView.from_positioner(primary_deg=20.0, secondary_deg=-10.0, source_to_detector_mm=1164.0, source_to_isocenter_mm=624.0,
                                    pixel_spacing_mm=(2.4, 2.4), rows=64, columns=64)
    p0, p1, r = np.array([-40.0, -60.0, -20.0]), np.array([30.0, 50.0, 25.0]), 1.5
    image = np.zeros((64, 64))
    add_cylinder(image, view, p0, p1, radius_mm=r, mu=1.0)
    src, d = pixel_rays(view)
    t = np.arange(300.0, 950.0, 0.02)
    a = (p1 - p0) / np.linalg.norm(p1 - p0)
    rows, cols = np.nonzero(image > 0)
    assert rows.size > 20  # the wire crosses the detector
    for rr, cc in list(zip(rows, cols))[:: max(1, rows.size // 25)]:
        pts = src + t[:, None] * d[rr, cc]
        s = (pts - p0) @ a
        radial = np.linalg.norm((pts - p0) - s[:, None] * a, axis=1)
        inside = (radial <= r) & (s >= 0) & (s <= np.linalg.norm(p1 - p0))
        assert image[rr, cc] == pytest.approx(inside.sum() * 0.02, abs=0.05)


def test_kwire_in_fluoroscopy_rests_on_the_entry(scene):
    chuck, tip = scene.kwire_carm()
    axis = scene.drill_axis_carm
    np.testing.assert_allclose(tip, axis.point_mm, atol=1e-6)  # its tip at the true axis's point nearest the entry
    assert axis.distance_to_point(chuck) < 1e-6 and np.linalg.norm(tip - chuck) > 150
    bare = make_scene(seed=3, views="inlet,outlet", kwire=False)
    assert bare.kwire_carm() is None
    view = scene.views["outlet"]
    middle = view.project(0.5 * (chuck + tip))[0]
    r, c = int(round(middle[1])), int(round(middle[0]))
    assert view.contains(middle[None], margin_px=10).all()
    extra = scene.fluoro_log["outlet"][r - 1 : r + 2, c - 1 : c + 2].mean() - bare.fluoro_log["outlet"][r - 1 : r + 2, c - 1 : c + 2].mean()
    assert extra > 1.0  # 3 mm of steel, after beam hardening


def test_voxel_anatomy_scene(tmp_path):
    """A voxel CT as the patient: markers on its skin, the DRR of the full CT in the fluoroscopy, a coarser copy handed on."""
    from drillnav.drivers.sim import anatomy
    from drillnav.drivers.sim.ct_anatomy import RENDER_STEP_MM, VoxelAnatomy, handed_copy, render_stride
    from drillnav.registration.drr import render_drr
    from drillnav.drivers.sim.ct_phantom import make_pelvis_ct

    ct = make_pelvis_ct(seed=1, voxel_mm=(2.0, 2.0, 2.0))
    corridor = anatomy.CORRIDORS[0]
    patient = VoxelAnatomy.from_volume(ct, corridor=corridor)
    skin, normal = patient.skin_entry()
    exact, exact_normal = anatomy.skin_entry(corridor)
    assert np.linalg.norm(skin - exact) < 3.0 and normal @ exact_normal > 0.95
    # One view: each is a full-detector DRR of the CT, and only the outlet is looked at (a two-view voxel scene is
    # tests/test_cli_anatomy.py's, through sim scene --anatomy).
    scene = make_scene(seed=8, voxel_anatomy=patient, views="outlet")
    for t in scene.carm_from_marker.values():  # resting on the CT's skin
        p_ct = invert(scene.carm_from_ct) @ t[:, 3]
        assert ct.sample(p_ct[:3] - 3.0 * (invert(scene.carm_from_ct)[:3, :3] @ t[:3, 2]))[0] > -200  # body under it
        assert ct.sample(p_ct[:3] + 3.0 * (invert(scene.carm_from_ct)[:3, :3] @ t[:3, 2]))[0] < -500  # air above it
    # A ray through every 2nd pixel (the CT's 2 mm voxels are wider than 2 pixels at the patient), bilinear in
    # between: against a ray through every pixel of a 160 px square at the detector's centre, well under photon noise
    # (0.01-0.05 in log units).
    view = scene.views["outlet"]
    assert render_stride(patient.truth_mu, view, scene.carm_from_ct) == 2
    line = patient.line_integrals(view, scene.carm_from_ct)
    u, v = view.columns // 2, view.rows // 2
    every_ray = render_drr(patient.truth_mu, view, scene.carm_from_ct, roi=(u - 80, v - 80, u + 80, v + 80), step_mm=RENDER_STEP_MM)
    diff = np.abs(line[v - 80 : v + 80, u - 80 : u + 80] - every_ray)
    assert every_ray.max() > 2.0 and np.sqrt(np.mean(diff**2)) < 0.005 and np.percentile(diff, 99) < 0.02, (np.sqrt(np.mean(diff**2)), diff.max())
    img = scene.fluoro_log["outlet"]
    bb = scene.views["outlet"].project(next(iter(scene.carm_from_marker.values()))[:3, 3])[0]
    assert img[int(round(bb[1])), int(round(bb[0]))] > np.median(img) + 1.0
    handed = handed_copy(ct, seed=1)
    np.testing.assert_allclose(handed.spacing_mm, [2.5, 2.5, 2.0])
    np.testing.assert_allclose(handed.centre_mm(), ct.centre_mm(), atol=2.0)
    assert np.std(handed.data[handed.data > -900].astype(float)) > 0
    with pytest.raises(ValueError, match="outside the CT"):
        VoxelAnatomy.from_volume(ct, corridor=anatomy.Corridor(name="x", entry_mm=(0.0, 0.0, 900.0), target_mm=(0.0, 0.0, 0.0)))
