"""DRR against exact line integrals, gradient correlation, fluoroscopy-to-CT registration on the twin, conformance."""

from pathlib import Path

import numpy as np
import pytest

from drillnav.drivers.sim import anatomy
from drillnav.drivers.sim.ct_phantom import make_pelvis_ct
from drillnav.drivers.sim.xray import add_ellipsoids, pixel_rays
from drillnav.registration.conformance import SurfaceDistance, conformance_along, perturbed_axes
from drillnav.registration.ct_registration import FluoroShot, gradient_correlation, register_ct, rotation_centre_mm
from drillnav.registration.drr import DrrVolume, drr_pyramid, render_drr
from drillnav.registration.errors import DegenerateInput
from drillnav.registration.fluoro_masks import metal_mask
from drillnav.registration.line import Line3D
from drillnav.registration.transforms import apply, from_rotvec, invert, make_transform, rotation_angle_deg
from drillnav.registration.volume import Volume

from twin_scenes import rendered_scene


@pytest.fixture(scope="module")
def ct():
    return make_pelvis_ct(seed=0, voxel_mm=(1.0, 1.0, 1.0))


@pytest.fixture(scope="module")
def scene():
    return rendered_scene(5, "inlet,outlet")  # the one tests/test_ct_tracker.py registers


def test_drr_of_a_uniform_box_is_mu_times_chord():
    a = np.eye(4)
    a[:3, 3] = [-50.0, -50.0, -50.0]  # 101 voxels of 1 mm from -50 to +50
    hu = np.full((101, 101, 101), 0, np.int16)  # water
    mu = DrrVolume.from_ct(Volume(data=hu, patient_from_voxel=a))
    from drillnav.registration.carm import CArmView

    view = CArmView.from_positioner(primary_deg=0, secondary_deg=0, source_to_detector_mm=1000, source_to_isocenter_mm=600,
                                    pixel_spacing_mm=(1.0, 1.0), rows=101, columns=101)
    img = render_drr(mu, view, np.eye(4))
    # The central ray crosses the box (voxel centres -50..50) over 100 mm of water.
    assert img[50, 50] == pytest.approx(100.0 * 0.0206, rel=2e-3)


def test_drr_matches_exact_line_integrals_of_the_twin_anatomy(ct, scene):
    view = scene.views["inlet"].binned(8)
    exact = np.zeros((view.rows, view.columns))
    add_ellipsoids(exact, view, anatomy.pelvis_ellipsoids_carm(scene.carm_from_ct), rays=pixel_rays(view))
    drr = render_drr(DrrVolume.from_ct(ct), view, scene.carm_from_ct)
    assert np.corrcoef(exact.ravel(), drr.ravel())[0, 1] > 0.999
    assert abs(drr.mean() - exact.mean()) / exact.mean() < 0.01


def test_drr_volume_cropped_to_its_attenuation_renders_the_same_image(ct, scene):
    from drillnav.registration.volume import hu_to_mu

    cropped = DrrVolume.from_ct(ct)
    assert cropped.mu.size < 0.7 * np.prod(ct.shape)  # the air about the twin's body is gone
    whole = DrrVolume(mu=np.ascontiguousarray(hu_to_mu(np.asarray(ct.data))), patient_from_voxel=ct.patient_from_voxel)
    view = scene.views["inlet"].binned(8)
    step = 0.5  # the same samples in both grids: the crop moves the clipped ray ends, not the sampled field
    a = render_drr(cropped, view, scene.carm_from_ct, step_mm=step)
    b = render_drr(whole, view, scene.carm_from_ct, step_mm=step)
    assert np.abs(a - b).max() < 2e-3 * b.max()


def test_gradient_correlation_bounds():
    rng = np.random.default_rng(0)
    img = rng.normal(size=(64, 64)).astype(np.float32)
    assert gradient_correlation(img, img) == pytest.approx(1.0, abs=1e-6)
    assert gradient_correlation(img, -img) == pytest.approx(-1.0, abs=1e-6)
    assert gradient_correlation(img, 3 * img + 7) == pytest.approx(1.0, abs=1e-5)  # gain and offset do not matter
    assert abs(gradient_correlation(img, rng.normal(size=(64, 64)).astype(np.float32))) < 0.1


def _offset(shots, carm_from_ct, rng, *, mm, deg):
    centre = rotation_centre_mm([s.view for s in shots])
    d = rng.normal(size=3)
    a = rng.normal(size=3)
    p = from_rotvec(np.radians(deg) * a / np.linalg.norm(a))
    p[:3, 3] = centre - p[:3, :3] @ centre + mm * d / np.linalg.norm(d)
    return p @ carm_from_ct


def test_two_view_registration_recovers_the_pose(ct, scene):
    pyramid = drr_pyramid(ct, (2, 4))
    shots = [FluoroShot(view=scene.views[n], image_log=scene.fluoro_log[n], exclude=metal_mask(scene.fluoro_log[n])) for n in scene.views]
    start = _offset(shots, scene.carm_from_ct, np.random.default_rng(1), mm=18.0, deg=4.0)
    res = register_ct(pyramid, shots, start, seed=1)
    diff = res.carm_from_ct @ invert(scene.carm_from_ct)
    entry = scene.corridor_entry_carm_mm
    assert np.linalg.norm(apply(diff, [entry])[0] - entry) < 0.5
    assert rotation_angle_deg(diff) < 0.3
    assert res.converged and res.similarity > res.initial_similarity


def test_prealignment_captures_a_start_centimetres_away(ct, scene):
    pyramid = drr_pyramid(ct, (2, 4))
    shots = [FluoroShot(view=scene.views[n], image_log=scene.fluoro_log[n], exclude=metal_mask(scene.fluoro_log[n])) for n in scene.views]
    start = make_transform(np.eye(3), -np.asarray(scene.corridor.entry_mm))  # C-arm centred on the planned entry
    entry = scene.corridor_entry_carm_mm
    assert np.linalg.norm(apply(start @ invert(scene.carm_from_ct), [entry])[0] - entry) > 40  # far outside CMA-ES's reach
    res = register_ct(pyramid, shots, start, seed=2, search_mm=120.0)
    diff = res.carm_from_ct @ invert(scene.carm_from_ct)
    assert np.linalg.norm(apply(diff, [entry])[0] - entry) < 0.5


def test_everything_masked_is_refused(ct, scene):
    shot = FluoroShot(view=scene.views["inlet"], image_log=scene.fluoro_log["inlet"], exclude=np.ones((976, 976), bool))
    with pytest.raises(DegenerateInput, match="usable pixels"):
        register_ct(drr_pyramid(ct, (1, 2, 4)), [shot], scene.carm_from_ct)


def test_a_pyramid_without_a_level_s_volume_is_named(ct, scene):
    shot = FluoroShot(view=scene.views["inlet"], image_log=scene.fluoro_log["inlet"])
    with pytest.raises(DegenerateInput, match=r"also need \[1\]"):
        register_ct(drr_pyramid(ct, (2, 4)), [shot], scene.carm_from_ct)  # one view ends on the full-resolution volume


@pytest.fixture(scope="module")
def bone(ct):
    pts = np.array([p for c in anatomy.CORRIDORS for p in (c.entry_mm, c.target_mm)])
    return SurfaceDistance.bone(ct, around_mm=pts)


@pytest.mark.parametrize("corridor", anatomy.CORRIDORS, ids=lambda c: c.name)
def test_planned_corridors_are_breach_free(bone, corridor):
    e, t = np.array(corridor.entry_mm), np.array(corridor.target_mm)
    c = conformance_along(Line3D.through(e, t), bone, planned_entry_mm=e, planned_target_mm=t)
    assert not c.breach and c.min_distance_mm > 1.5 and c.along_mm[-1] > 50


def test_acceptance_maps_shared_by_trajectories_are_each_cropped_about_their_own(ct):
    """One plan, one acceptance definition, three corridors apart: each gets the distance map about itself."""
    from drillnav.schemas.scene_files import plan_to_json
    from drillnav.service.ct_mode import acceptance_surface, plan_entries

    cache: dict = {}
    for entry in plan_entries(plan_to_json(anatomy.CORRIDORS), base=Path.cwd()):
        t = entry.trajectory
        e, tg = t.entry_mm, t.target_mm
        c = conformance_along(Line3D.through(e, tg), acceptance_surface(ct, entry, cache), planned_entry_mm=e, planned_target_mm=tg)
        assert not c.breach and c.min_distance_mm > 1.5, t.name
    assert len(cache) == len(anatomy.CORRIDORS)


def test_superior_ramus_shifted_4mm_is_flagged_in_every_direction(bone):
    sr = next(c for c in anatomy.CORRIDORS if c.name == "superior-ramus")
    e, t = np.array(sr.entry_mm), np.array(sr.target_mm)
    d = (t - e) / np.linalg.norm(t - e)
    u = np.cross(d, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(d, u)
    for ang in np.radians([0, 60, 120, 180, 240, 300]):
        shift = 4.0 * (np.cos(ang) * u + np.sin(ang) * w)
        c = conformance_along(Line3D(point_mm=e + shift, direction=d), bone, planned_entry_mm=e, planned_target_mm=t)
        assert c.breach and c.breach_along_mm.size > 0


def test_axis_that_misses_bone_is_a_breach(bone):
    e = np.array([0.0, -90.0, 0.0])  # in the soft tissue in front of the sacrum
    c = conformance_along(Line3D(point_mm=e, direction=[1.0, 0.0, 0.0]), bone, planned_entry_mm=e, planned_target_mm=e + [30.0, 0, 0])
    assert c.breach and c.entry_mm is None and c.min_distance_mm == float("-inf")


def test_perturbed_cone_stays_within_its_bounds():
    rng = np.random.default_rng(0)
    e, t = np.zeros(3), np.array([0.0, 0.0, 80.0])
    axes = perturbed_axes(rng, e, t, position_mm=2.0, angle_deg=3.0, n=200)
    assert max(float(np.linalg.norm(a.point_mm - e)) for a in axes) <= 2.0 + 1e-9
    assert max(float(np.degrees(np.arccos(a.direction[2]))) for a in axes) <= 3.0 + 1e-9


def test_compiled_distance_lookups_match_scipy_and_a_fixed_step_march():
    """The conformance kernels against scipy's trilinear map_coordinates and the plain every-step march they replace."""
    from scipy import ndimage

    from drillnav.registration.conformance import OUTSIDE_MM, radial_clearance

    rng = np.random.default_rng(3)
    k, j, i = np.mgrid[0:40, 0:50, 0:60]
    blob = ((i - 30) / 22.0) ** 2 + ((j - 25) / 15.0) ** 2 + ((k - 20) / 12.0) ** 2 < 1.0
    affine = make_transform(from_rotvec([0.1, -0.2, 0.3])[:3, :3], [-40.0, 15.0, 7.0]) @ np.diag([0.8, 0.9, 1.3, 1.0])
    surface = SurfaceDistance.from_mask(blob, affine)
    pts = apply(affine, rng.uniform([-3, -3, -3], [62, 52, 42], size=(2000, 3)))  # (x, y, z) in voxels, some beyond the grid
    ijk = apply(np.linalg.inv(affine), pts)
    expect = ndimage.map_coordinates(surface.distance_mm.astype(np.float64), ijk[:, ::-1].T, order=1, mode="constant", cval=OUTSIDE_MM)
    np.testing.assert_allclose(surface.at(pts), expect, atol=1e-4)
    assert np.sum(surface.at(pts) == OUTSIDE_MM) > 50
    # Radial clearance: the first crossing on each of 24 rays, every 0.25 mm, nearest over rays.
    axis = Line3D(point_mm=apply(affine, [30.0, 25.0, 20.0]), direction=affine[:3, :3] @ np.array([1.0, 0.2, 0.1]))
    s = np.linspace(-12.0, 12.0, 25)
    on_axis = surface.at(axis.at(s))
    got = radial_clearance(axis, s, surface, on_axis_mm=on_axis)
    d = axis.direction
    u = np.cross(d, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(d, u)
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    r = np.arange(0.0, 20.0 + 1e-9, 0.25)
    vals = surface.at((axis.at(s)[:, None, None, :] + (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w)[None, :, None, :] * r[None, None, :, None]).reshape(-1, 3))
    vals = vals.reshape(len(s), 24, len(r))
    crossing = np.full((len(s), 24), 20.0)
    for n in range(len(s)):
        for q in range(24):
            m = np.flatnonzero(vals[n, q] <= 0)
            if m.size:
                m = m[0]
                crossing[n, q] = 0.0 if m == 0 else r[m - 1] + np.clip(vals[n, q, m - 1] / (vals[n, q, m - 1] - vals[n, q, m]), 0, 1) * 0.25
    expect = np.where(on_axis > 0, crossing.min(axis=1), on_axis)
    np.testing.assert_allclose(got, expect, atol=1e-6)
    assert np.ptp(got) > 2.0  # the clearance really varies along the axis
