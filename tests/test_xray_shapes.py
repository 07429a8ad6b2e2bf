"""The twin's analytic X-ray shapes: each adds its whole line integral (the detector windows they are computed in
cut nothing off), and the scatter's FFT blur is OpenCV's Gaussian blur."""

import cv2
import numpy as np
import pytest

from drillnav.drivers.sim.blur import gaussian_blur_fft
from drillnav.drivers.sim.xray import add_box, add_cylinder, add_ellipsoids, add_ring, add_spheres, pixel_rays
from drillnav.registration.carm import CArmView
from drillnav.registration.transforms import from_rotvec

VIEW = CArmView.from_positioner(primary_deg=20.0, secondary_deg=-10.0, source_to_detector_mm=1000.0, source_to_isocenter_mm=600.0,
                                rows=120, columns=160, pixel_spacing_mm=(1.6, 1.6))


def integral_mm3(image: np.ndarray, at_mm: np.ndarray) -> float:
    """Sum of chord lengths times each pixel's area at the body's depth: the body's volume (mm^3)."""
    pixel_at_body = VIEW.pixel_spacing_mm[0] / float(VIEW.magnification(at_mm[None, :])[0])
    return float(image.sum()) * pixel_at_body**2


def test_each_shape_adds_its_whole_volume():
    rot = from_rotvec(np.array([0.4, -0.7, 0.2]))[:3, :3]
    centre = np.array([5.0, -3.0, 8.0])
    cases = []
    img = np.zeros((VIEW.rows, VIEW.columns))
    add_ellipsoids(img, VIEW, [(centre, np.array([30.0, 12.0, 20.0]), rot, 1.0)])
    cases.append(("ellipsoid", img, 4 / 3 * np.pi * 30 * 12 * 20))
    img = np.zeros((VIEW.rows, VIEW.columns))
    add_box(img, VIEW, centre_mm=centre, carm_from_box_rotation=rot, half_size_mm=np.array([25.0, 4.0, 10.0]), mu=1.0)
    cases.append(("box", img, 8 * 25 * 4 * 10))
    img = np.zeros((VIEW.rows, VIEW.columns))
    add_cylinder(img, VIEW, centre - 40 * rot[:, 0], centre + 40 * rot[:, 0], radius_mm=2.0, mu=1.0)
    cases.append(("cylinder", img, np.pi * 4 * 80))
    img = np.zeros((VIEW.rows, VIEW.columns))
    add_spheres(img, VIEW, centre + np.array([[0, 0, 0], [6, 0, 0], [3, 5, 2]]), np.array([1.0, 1.5, 2.0]), 1.0)
    cases.append(("spheres", img, 4 / 3 * np.pi * (1 + 1.5**3 + 8)))
    for name, image, volume in cases:
        # Depth varies over the body: magnification at the centre is good to about 1 %.
        assert integral_mm3(image, centre) == pytest.approx(volume, rel=0.03), name


def marched_chords_mm(inside, centre: np.ndarray, reach_mm: float, step_mm: float = 0.2) -> np.ndarray:
    """Chord (rows, columns) of every pixel's central ray through the body ``inside`` (points (N, 3) -> bool (N,)), by
    counting steps of ``step_mm`` within ``reach_mm`` of ``centre``'s depth: the shapes' reference, no formula shared."""
    src, d = pixel_rays(VIEW)
    depth = float(np.linalg.norm(centre - src))
    t = np.arange(depth - reach_mm, depth + reach_mm, step_mm) + step_mm / 2
    out = np.zeros((VIEW.rows, VIEW.columns))
    for r in range(VIEW.rows):
        pts = src + d[r, :, None, :] * t[None, :, None]
        out[r] = inside(pts.reshape(-1, 3)).reshape(VIEW.columns, t.size).sum(axis=1) * step_mm
    return out


def test_no_ray_through_a_shape_is_left_out():
    """Every pixel whose ray crosses the body gets its chord, to the marching step, wherever it lies on the detector."""
    rot = from_rotvec(np.array([0.4, -0.7, 0.2]))[:3, :3]
    centre = np.array([5.0, -3.0, 8.0])
    semi, half = np.array([30.0, 12.0, 20.0]), np.array([25.0, 4.0, 10.0])
    a, b = centre - 40 * rot[:, 0], centre + 40 * rot[:, 0]

    def in_cylinder(p):
        s = (p - a) @ rot[:, 0]
        return (s >= 0) & (s <= 80) & (np.linalg.norm(p - a - s[:, None] * rot[:, 0], axis=1) <= 2.0)

    shapes = [
        (lambda img: add_ellipsoids(img, VIEW, [(centre, semi, rot, 1.0)]), lambda p: np.sum((((p - centre) @ rot) / semi) ** 2, axis=1) <= 1),
        (lambda img: add_box(img, VIEW, centre_mm=centre, carm_from_box_rotation=rot, half_size_mm=half, mu=1.0),
         lambda p: np.all(np.abs((p - centre) @ rot) <= half, axis=1)),
        (lambda img: add_cylinder(img, VIEW, a, b, radius_mm=2.0, mu=1.0), in_cylinder),
    ]
    for add, inside in shapes:
        image = np.zeros((VIEW.rows, VIEW.columns))
        add(image)
        marched = marched_chords_mm(inside, centre, reach_mm=50.0)
        assert marched.max() > 3.5
        np.testing.assert_allclose(image, marched, atol=0.45)


def test_spheres_at_once_and_one_by_one_and_over_the_edge_agree():
    """A ring's spheres computed together equal each computed alone; a sphere the detector's edge cuts keeps the part
    inside, as every ray through the whole detector sees it."""
    pose = from_rotvec(np.array([0.3, 0.2, -0.1]))
    pose[:3, 3] = [10.0, 5.0, 0.0]
    together = np.zeros((VIEW.rows, VIEW.columns))
    add_ring(together, VIEW, pose, radius_mm=20.0, wire_diameter_mm=0.5, mu=7.0)
    t = np.linspace(0, 2 * np.pi, 3, endpoint=False)
    centres = (np.stack([20 * np.cos(t), 20 * np.sin(t), 0 * t, 1 + 0 * t], axis=1) @ pose.T)[:, :3]
    alone, at_once = np.zeros_like(together), np.zeros_like(together)
    for c in centres:
        add_spheres(alone, VIEW, c[None, :], np.array([1.2]), 7.0)
    add_spheres(at_once, VIEW, centres, np.full(3, 1.2), 7.0)
    np.testing.assert_allclose(at_once, alone, rtol=1e-12, atol=1e-12)
    src, d = pixel_rays(VIEW, supersample=3)
    reference = np.zeros_like(together)
    for c in centres:
        w = c - src
        t = d @ w
        reference += 7.0 * (2.0 * np.sqrt(np.maximum(1.2**2 - (w @ w - t * t), 0.0))).reshape(VIEW.rows, 3, VIEW.columns, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(at_once, reference, rtol=1e-9, atol=1e-12)
    assert together.max() > 0.5
    # A sphere on the detector's left edge: every sub-pixel ray of the whole detector, binned, is the reference.
    edge_px = np.array([0.3, 60.0])
    s, dirs = VIEW.backproject(edge_px[None, :])
    c = s + 600.0 * dirs[0]
    cut = np.zeros_like(together)
    add_spheres(cut, VIEW, c[None, :], np.array([2.0]), 1.0)
    w = c - src
    t = d @ w
    chord = 2.0 * np.sqrt(np.maximum(4.0 - (w @ w - t * t), 0.0))
    reference = chord.reshape(VIEW.rows, 3, VIEW.columns, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(cut, reference, rtol=1e-9, atol=1e-12)
    assert 0 < cut.sum() < reference.sum() * 1.0000001


@pytest.mark.parametrize("shape, sigma", [((976, 976), 35.0), ((100, 60), 35.0), ((300, 500), 9.3), ((7, 9), 0.6)])
def test_the_scatter_blur_is_opencvs_gaussian(shape, sigma):
    image = np.random.default_rng(1).uniform(1.0, 12000.0, size=shape)
    expected = cv2.GaussianBlur(image, (0, 0), sigma)
    assert np.abs(gaussian_blur_fft(image, sigma) - expected).max() <= 1e-13 * np.abs(expected).max()


def test_the_scatter_blur_refuses_a_width_not_above_zero():
    with pytest.raises(ValueError, match="sigma must be > 0"):
        gaussian_blur_fft(np.ones((4, 4)), 0.0)
