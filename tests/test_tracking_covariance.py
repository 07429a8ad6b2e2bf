"""A tracked frame's own corner noise on the drill pose (registration/tracking_covariance.py), against Monte Carlo."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.joint_solve import frame_shape_modes
from drillnav.registration.tracking_covariance import corner_pnp_covariance
from drillnav.registration.transforms import apply, invert, make_transform

CAMERA = PinholeCamera(width=1280, height=720, camera_matrix=np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]]))
# The drill in frame C (the C-arm's).
CARM_FROM_DRILL = make_transform(Rotation.from_euler("xyz", [160, 10, 30], degrees=True).as_matrix(), [12.0, -8.0, 170.0])
PIVOT = np.array([5.0, 0.0, 20.0])


def _tags(centres) -> np.ndarray:
    """Tag corners in the drill camera's frame D (mm): 20 mm squares tilted 20 deg, ~150 mm in front of it."""
    square = np.array([[-10.0, 10, 0], [10, 10, 0], [10, -10, 0], [-10, -10, 0]]) @ Rotation.from_euler("x", 20, degrees=True).as_matrix().T
    return np.concatenate([square + c + [0.0, 0.0, 150.0] for c in centres])


ONE = _tags([[0.0, 0, 0]])
THREE = _tags([[0.0, 0, 0], [45, 10, 3], [-20, 40, -2]])


def _monte_carlo(points: np.ndarray, sigma: float, n: int = 400, frame_px: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(7)
    drill_from_carm = invert(CARM_FROM_DRILL)
    rvec0, _ = cv2.Rodrigues(drill_from_carm[:3, :3])
    tvec0 = drill_from_carm[:3, 3].reshape(3, 1)
    clean, _ = cv2.projectPoints(points, rvec0, tvec0, CAMERA.camera_matrix, CAMERA.distortion)
    deltas = []
    for _ in range(n):
        noisy = clean.reshape(-1, 2) + rng.normal(scale=sigma, size=(len(points), 2))
        if frame_px:  # every tag scaled, turned and stretched about its centre alike (the frame's shared shape)
            noisy += (frame_shape_modes(list(clean.reshape(-1, 4, 2))) @ rng.normal(scale=frame_px, size=4)).reshape(-1, 2)
        rvec, tvec = cv2.solvePnPRefineLM(points, noisy, CAMERA.camera_matrix, CAMERA.distortion, rvec0.copy(), tvec0.copy())
        est = invert(make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel()))
        r = est[:3, :3] @ CARM_FROM_DRILL[:3, :3].T  # the rotation applied in C
        d = est[:3, 3] - r @ (CARM_FROM_DRILL[:3, 3] - PIVOT) - PIVOT
        deltas.append(np.concatenate([Rotation.from_matrix(r).as_rotvec(), d]))
    return np.cov(np.array(deltas).T)


@pytest.mark.parametrize("points", [ONE, THREE], ids=["one tag", "three tags"])
def test_the_covariance_is_what_the_corner_noise_does_to_the_pnp(points):
    sigma = 0.5
    predicted = corner_pnp_covariance(CARM_FROM_DRILL, points_carm_mm=apply(CARM_FROM_DRILL, points), sigma_px=np.full(len(points), sigma),
                                      camera=CAMERA, pivot_carm_mm=PIVOT)
    drawn = _monte_carlo(apply(CARM_FROM_DRILL, points), sigma)
    # Each parameter's spread within 15 % (400 draws: about 7 % sampling error on a standard deviation).
    np.testing.assert_allclose(np.sqrt(np.diag(predicted)), np.sqrt(np.diag(drawn)), rtol=0.15)


def test_one_tag_leaves_the_tilt_far_less_sure_than_three_and_the_noise_scales_it():
    kw = dict(camera=CAMERA, pivot_carm_mm=PIVOT)
    one = corner_pnp_covariance(CARM_FROM_DRILL, points_carm_mm=apply(CARM_FROM_DRILL, ONE), sigma_px=np.full(4, 0.5), **kw)
    three = corner_pnp_covariance(CARM_FROM_DRILL, points_carm_mm=apply(CARM_FROM_DRILL, THREE), sigma_px=np.full(12, 0.5), **kw)
    assert np.trace(one[:3, :3]) > 5 * np.trace(three[:3, :3])
    doubled = corner_pnp_covariance(CARM_FROM_DRILL, points_carm_mm=apply(CARM_FROM_DRILL, ONE), sigma_px=np.full(4, 1.0), **kw)
    np.testing.assert_allclose(doubled, 4 * one, rtol=1e-6, atol=1e-12)


def test_a_sigma_per_corner_that_does_not_match_the_points_is_refused():
    with pytest.raises(ValueError, match="4 points but 3 corner sigmas"):
        corner_pnp_covariance(CARM_FROM_DRILL, points_carm_mm=ONE, sigma_px=np.ones(3), camera=CAMERA, pivot_carm_mm=PIVOT)
    with pytest.raises(ValueError, match="four corners in turn, got 3 points"):
        corner_pnp_covariance(CARM_FROM_DRILL, points_carm_mm=ONE[:3], sigma_px=np.ones(3), camera=CAMERA, pivot_carm_mm=PIVOT, frame_shape_sigma_px=0.3)


def test_the_shape_every_tag_of_the_frame_shares_is_carried():
    """A motion blur scales, turns and stretches every tag of the frame alike (0.4 px at each tag's half-diagonal on
    top of 0.2 px independent noise): with it stated, the covariance follows the PnP's scatter; without it, the tilt's
    spread is understated."""
    points = apply(CARM_FROM_DRILL, THREE)
    kw = dict(points_carm_mm=points, sigma_px=np.full(len(points), 0.2), camera=CAMERA, pivot_carm_mm=PIVOT)
    drawn = _monte_carlo(points, 0.2, frame_px=0.4)
    stated = corner_pnp_covariance(CARM_FROM_DRILL, frame_shape_sigma_px=0.4, **kw)
    np.testing.assert_allclose(np.sqrt(np.diag(stated)), np.sqrt(np.diag(drawn)), rtol=0.15)
    blind = corner_pnp_covariance(CARM_FROM_DRILL, **kw)
    assert np.trace(drawn[:3, :3]) > 2 * np.trace(blind[:3, :3])
