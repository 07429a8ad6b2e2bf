"""The twin's operating-room degradations: each switch changes the rendered image in the way it is meant to.

Small images (a 400x300 camera, a 240x240 detector of 1.2 mm pixels) keep the file fast; each
degraded render is compared with the clean render from the same generator state.
"""

import dataclasses

import cv2
import numpy as np
import pytest

from drillnav.drivers.sim.camera import render_markers
from drillnav.drivers.sim.degradations import (
    GLOVE_BGR, DegradationError, Degradations, collimator_mask, ii_distortion_maps,
)
from drillnav.drivers.sim.scene import ANTERIOR_V, MIN_MARKER_SPACING_MM, PAPER_CARM, SceneError, make_scene, render_fluoro
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.carm import CArmView
from drillnav.registration.markers import default_marker_set
from drillnav.registration.transforms import apply, invert, make_transform

CAMERA = PinholeCamera.from_fov(width=400, height=300, horizontal_fov_deg=60.0)
MARKER = default_marker_set().markers[0]
# One tag face-on, 130 mm in front of the camera, slightly turned.
POSE = make_transform(cv2.Rodrigues(np.array([0.2, -0.15, 0.3]))[0], [4.0, -3.0, 130.0])


def _render(degradations: Degradations | None, seed: int = 1) -> np.ndarray:
    return render_markers(camera=CAMERA, camera_from_marker={MARKER.marker_id: POSE}, markers={MARKER.marker_id: MARKER},
                          rng=np.random.default_rng(seed), glare=False, degradations=degradations)


def _tag_px() -> np.ndarray:
    return CAMERA.project(apply(POSE, MARKER.tag_corners_mm()))


def _tag_mask(shrink_px: float = 0.0) -> np.ndarray:
    tag = _tag_px()
    c = tag.mean(axis=0)
    tag = c + (tag - c) * (1 - shrink_px / np.linalg.norm(tag - c, axis=1, keepdims=True))
    mask = np.zeros((CAMERA.height, CAMERA.width), np.uint8)
    cv2.fillPoly(mask, [np.round(tag).astype(np.int32)], 1)
    return mask > 0


def _sharpness(img: np.ndarray) -> float:
    gray = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return float(np.abs(cv2.Laplacian(gray.astype(np.float32), cv2.CV_32F))[_tag_mask()].mean())


def test_parse_names_all_none_and_refuses_unknown():
    assert Degradations.parse("none") == Degradations()
    everything = Degradations.parse("all")
    assert everything.enabled == Degradations.names() and everything.label() == "all"
    two = Degradations.parse("glove, low_dose")
    assert two.enabled == ("low_dose", "glove") and two.camera
    assert everything.only("mjpeg").enabled == ("mjpeg",)
    with pytest.raises(DegradationError, match="unknown degradation.*gloves"):
        Degradations.parse("gloves")
    with pytest.raises(DegradationError, match="dose_quanta"):
        Degradations(dose_quanta=(0.0, 100.0))


def test_clean_switches_render_as_before():
    np.testing.assert_array_equal(_render(None), _render(Degradations()))


def test_glove_hides_a_tag_corner():
    clean, gloved = _render(None), _render(Degradations(glove=True))
    tag = _tag_px()
    centre = tag.mean(axis=0)
    # Sample each corner 3 px inside the tag: black border in the clean frame.
    inner = [tuple(np.round(c + 3.0 * (centre - c) / np.linalg.norm(centre - c)).astype(int)) for c in tag]
    clean_vals = [int(clean[r, c]) for c, r in inner]
    gloved_vals = [int(gloved[r, c]) for c, r in inner]
    glove_grey = float(cv2.cvtColor(np.uint8([[GLOVE_BGR]]), cv2.COLOR_BGR2GRAY)[0, 0])
    assert max(clean_vals) < 90, clean_vals
    hidden = [v for v in gloved_vals if abs(v - glove_grey) < 0.2 * glove_grey]
    assert 1 <= len(hidden) <= 2, (gloved_vals, glove_grey)  # part of the tag, not all of it


def test_tag_glare_saturates_inside_the_tag():
    clean, glared = _render(None), _render(Degradations(tag_glare=True))
    inside = _tag_mask(shrink_px=1.0)
    assert (clean[inside] == 255).sum() == 0
    assert (glared[inside] == 255).sum() > 20
    assert (glared[~_tag_mask(shrink_px=-40.0)] == 255).sum() == 0  # a highlight on the tag, not elsewhere


def test_blood_specks_are_red_in_colour_frames():
    plain, bloody = _render(Degradations(colour=True)), _render(Degradations(colour=True, blood=True))
    b, g, r = (c.astype(float) for c in cv2.split(bloody))
    red = (r > 1.8 * g + 10) & (r > 1.8 * b + 10)
    b0, g0, r0 = (c.astype(float) for c in cv2.split(plain))
    assert ((r0 > 1.8 * g0 + 10) & (r0 > 1.8 * b0 + 10)).sum() == 0
    assert red.sum() > 20


def test_colour_frames_are_bgr_under_warm_light():
    img = _render(Degradations(colour=True))
    assert img.shape == (CAMERA.height, CAMERA.width, 3) and img.dtype == np.uint8
    means = img.reshape(-1, 3).mean(axis=0)
    assert means[2] > 1.2 * means[0], means  # red over blue


@pytest.mark.parametrize("name", ["motion_blur", "defocus"])
def test_blur_degradations_soften_the_tag_edges(name):
    clean, blurred = _sharpness(_render(None)), _sharpness(_render(Degradations(**{name: True})))
    assert blurred < 0.7 * clean, (clean, blurred)


def test_mjpeg_leaves_8x8_block_edges():
    def blockiness(img):
        d = np.abs(np.diff(img.astype(float), axis=1))
        at_edges = d[:, 7::8].mean()
        return at_edges / np.delete(d, np.s_[7::8], axis=1).mean()

    clean, jpeg = _render(None), _render(Degradations(mjpeg=True))
    assert blockiness(jpeg) > blockiness(clean) + 0.05, (blockiness(clean), blockiness(jpeg))
    assert 0 < np.abs(jpeg.astype(int) - clean.astype(int)).mean() < 12


def test_auto_exposure_steps_the_gain():
    clean = _render(None).astype(float)
    brighter = _render(Degradations(auto_exposure=True, exposure_gain=(1.4, 1.5))).astype(float)
    unsaturated = brighter < 250
    ratio = brighter[unsaturated].mean() / clean[unsaturated].mean()
    assert 1.3 < ratio < 1.6, ratio


# --- fluoroscopy -----------------------------------------------------------------------------------------------

SMALL = dict(PAPER_CARM, pixel_spacing_mm=(1.2, 1.2), rows=240, columns=240)


def _small_scene(degradations: Degradations, seed: int = 11):
    scene = make_scene(seed=seed, views="ap", render=False, degradations=degradations)
    return dataclasses.replace(scene, views={"ap": CArmView.from_positioner(primary_deg=0.0, secondary_deg=0.0, **SMALL)})


def test_photon_noise_scales_with_dose_as_poisson_predicts():
    scene = _small_scene(Degradations())
    noise = {}
    for dose in (1000.0, 16000.0):
        a = render_fluoro(scene, "ap", np.random.default_rng(1), dose_quanta=dose)
        b = render_fluoro(scene, "ap", np.random.default_rng(2), dose_quanta=dose)
        noise[dose] = float(np.std((a - b)[60:180, 60:180]) / np.sqrt(2))
    # Poisson: the log signal's noise goes as 1/sqrt(quanta); 16x the dose gives 1/4 of the noise.
    assert noise[1000.0] / noise[16000.0] == pytest.approx(4.0, rel=0.12), noise
    low = _small_scene(Degradations(low_dose=True))
    a = render_fluoro(low, "ap", np.random.default_rng(1))
    b = render_fluoro(low, "ap", np.random.default_rng(2))
    # A drawn dose of 2,000-5,000 quanta lies between the two measured doses' noise.
    low_noise = float(np.std((a - b)[60:180, 60:180]) / np.sqrt(2))
    assert noise[16000.0] * 1.5 < low_noise < noise[1000.0], (noise, low_noise)


def test_collimated_area_is_dark():
    rng = np.random.default_rng(4)
    mask = collimator_mask(np.random.default_rng(4), 240, 240)
    assert 0.05 < (mask > 0.99).mean() < 0.5
    scene = _small_scene(Degradations(collimator=True))
    img = render_fluoro(scene, "ap", rng, dose_quanta=5000.0)
    counts = 5000.0 * np.exp(-img.astype(float))
    # Behind lead almost no quanta arrive (scatter from the open field aside); the open field gets hundreds.
    assert np.median(counts[mask > 0.99]) < 0.05 * np.median(counts[mask < 0.01])


def test_hardware_is_dense_metal_where_it_projects():
    scene = _small_scene(Degradations(hardware=True))
    assert {p.name for p in scene.hardware} >= {"retractorL", "retractorR", "second K-wire", "clamp jaw", "clamp hinge"}
    bare = dataclasses.replace(scene, hardware=())
    with_metal = render_fluoro(scene, "ap", np.random.default_rng(3), dose_quanta=1e6)
    without = render_fluoro(bare, "ap", np.random.default_rng(3), dose_quanta=1e6)
    view = scene.views["ap"]
    for part in scene.hardware:
        centre = np.asarray(part.centre_mm) if hasattr(part, "centre_mm") else (np.asarray(part.start_mm) + np.asarray(part.end_mm)) / 2
        c, r = np.round(view.project(centre[None])[0]).astype(int)
        if 2 <= c < 238 and 2 <= r < 238:
            assert (with_metal - without)[r - 1:r + 2, c - 1:c + 2].max() > 0.5, part.name


def test_image_intensifier_distortion_is_pincushion_and_s():
    rows = cols = 201
    map_x, map_y = ii_distortion_maps(rows, cols, pincushion_px=8.0, s_px=3.0)
    assert map_x[100, 100] == pytest.approx(100.0, abs=1e-3) and map_y[100, 100] == pytest.approx(100.0, abs=1e-3)
    # A corner shows what lies 8 px further in (pincushion: the image stretches outwards).
    corner_shift = np.hypot(map_x[0, 0] - 100.0, map_y[0, 0] - 100.0) - np.hypot(100.0, 100.0)
    assert corner_shift == pytest.approx(-8.0, abs=1.0)
    # The edge's midpoint is turned ~3 px (S distortion), not only moved in.
    assert abs(map_x[0, 100] - 100.0) == pytest.approx(3.0, abs=0.5)
    clean = _small_scene(Degradations())
    img = render_fluoro(clean, "ap", np.random.default_rng(5), dose_quanta=1e6)
    warped = render_fluoro(dataclasses.replace(clean, degradations=Degradations(ii_distortion=True)), "ap", np.random.default_rng(5), dose_quanta=1e6)
    assert np.abs(warped - img)[:30].mean() > 3 * np.abs(warped - img)[105:135, 105:135].mean()


def test_surgeon_markers_tilted_spread_and_partly_outside_the_field():
    deg = Degradations(surgeon_markers=True)
    tilts, partly_out = [], 0
    for seed in range(20, 26):
        scene = make_scene(seed=seed, views="inlet,outlet", render=False, degradations=deg)
        centres = []
        for pose in scene.carm_from_marker.values():
            ct_from_marker = invert(scene.carm_from_ct) @ pose
            tilts.append(np.degrees(np.arccos(ct_from_marker[:3, 2] @ ANTERIOR_V)))
            centres.append(ct_from_marker[:3, 3])
            ring = apply(pose, MARKER.ring_points_mm(64))
            for view in scene.views.values():
                inside = view.contains(view.project(ring))
                partly_out += bool(inside.any() and not inside.all())
        gaps = np.linalg.norm(np.array(centres)[:, None] - np.array(centres)[None], axis=-1) + np.eye(len(centres)) * 1e9
        assert gaps.min() > MIN_MARKER_SPACING_MM - 8.0  # spaced on the skin (the curve shortens chords a little)
    assert 10.0 - 1e-6 <= min(tilts) and max(tilts) <= 40.0 + 1e-6
    assert partly_out >= 2, partly_out


def test_ct_anatomy_needs_the_ct():
    with pytest.raises(SceneError, match="ct_anatomy.*voxel_anatomy"):
        make_scene(seed=1, render=False, degradations=Degradations(ct_anatomy=True))
