"""Twin calibration images shared by the tests: checkerboard views and the drill-axis jig turning about an axis.

Both render through :func:`drillnav.drivers.sim.camera.render_plane` (the true lens), for any camera; a frame of
field markers where the jig should be, through the twin's marker renderer; and an operating-room twin frame with a
gloved tag (:func:`gloved_frame`); the accuracy study's operating-room scene of a seed and view pair
(:func:`operating_room_scene`).

A full-frame render costs about a second of CPU, and several tests (in one pytest process) ask for the same views: each
set is rendered once per process and handed out read-only, so a test that drew on a shared frame would fail loudly.
"""

from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from drillnav.drivers.sim.camera import checkerboard_texture, render_plane
from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.drill_axis import jig_board, jig_size_mm
from drillnav.registration.line import Line3D
from drillnav.registration.transforms import make_transform
from drillnav.registration.video_markers import VideoMarkerLocator

BOARD_SIZE_MM = (12 * 25.0, 9 * 25.0)  # 9x6 inner corners of 25 mm + 1 + a white square each side

_RENDERED: dict[tuple, list[np.ndarray]] = {}


def _once(kind: str, camera: PinholeCamera, args: tuple, render) -> list[np.ndarray]:
    """``render()``'s frames for (kind, camera, args), rendered on first use; a new list of read-only frames."""
    k = (kind, camera.width, camera.height, camera.camera_matrix.tobytes(), camera.distortion.tobytes(), args)
    if k not in _RENDERED:
        frames = render()
        for f in frames:
            f.setflags(write=False)
        _RENDERED[k] = frames
    return list(_RENDERED[k])


def board_views(camera: PinholeCamera, n: int, *, tilt_deg: float = 30.0, spin_deg: float = 20.0, offset_mm=(40.0, 25.0),
                distance_mm=(380.0, 480.0), seed: int = 0) -> list[np.ndarray]:
    """``n`` views of the 9x6 checkerboard, tilted up to ``tilt_deg``, spun up to ``spin_deg``, centred within
    ``offset_mm`` of the optical axis at ``distance_mm``."""
    args = (n, tilt_deg, spin_deg, tuple(offset_mm), tuple(distance_mm), seed)
    return _once("board", camera, args, lambda: _board_views(camera, n, tilt_deg, spin_deg, offset_mm, distance_mm, seed))


def _board_views(camera, n, tilt_deg, spin_deg, offset_mm, distance_mm, seed) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    tex = checkerboard_texture(9, 6)
    views = []
    for _ in range(n):
        r = Rotation.from_euler("xyz", [rng.uniform(-tilt_deg, tilt_deg), rng.uniform(-tilt_deg, tilt_deg), rng.uniform(-spin_deg, spin_deg)], degrees=True).as_matrix()
        centre = np.array([rng.uniform(-offset_mm[0], offset_mm[0]), rng.uniform(-offset_mm[1], offset_mm[1]), rng.uniform(*distance_mm)])
        t = centre - r @ np.array([BOARD_SIZE_MM[0] / 2, BOARD_SIZE_MM[1] / 2, 0])
        views.append(render_plane(camera=camera, camera_from_plane=make_transform(r, t), texture=tex, size_mm=BOARD_SIZE_MM, rng=rng))
    return views


def jig_frames(camera: PinholeCamera, axis: Line3D, n: int = 8, span_deg: float = 120.0, seed: int = 0) -> list[np.ndarray]:
    """The ArUco jig turning about ``axis`` (camera frame), 150 mm along it from its point, over ``span_deg``."""
    args = (axis.point_mm.tobytes(), axis.direction.tobytes(), n, span_deg, seed)
    return _once("jig", camera, args, lambda: _jig_frames(camera, axis, n, span_deg, seed))


def _jig_frames(camera, axis, n, span_deg, seed) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    s = jig_size_mm()
    px, pad = 800, 80  # the printed jig keeps a white quiet zone about the board
    tex = cv2.copyMakeBorder(jig_board().generateImage((px, px), marginSize=0), pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    pad_mm = pad * s / px
    board_from_print = make_transform(np.eye(3), [-pad_mm, -pad_mm, 0.0])
    c = axis.at([150.0])[0]
    z = axis.direction
    x = np.cross([0, 1, 0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    base = make_transform(np.stack([x, y, z], 1) @ Rotation.from_euler("x", 20, degrees=True).as_matrix(), c - s / 2 * x - s / 2 * y + 30 * x)
    frames = []
    for th in np.linspace(-span_deg / 2, span_deg / 2, n):
        r = Rotation.from_rotvec(np.radians(th) * z).as_matrix()
        frames.append(render_plane(camera=camera, camera_from_plane=make_transform(r, c - r @ c) @ base @ board_from_print, texture=tex,
                                   size_mm=(s + 2 * pad_mm, s + 2 * pad_mm), rng=rng))
    return frames


def field_marker_frame(camera: PinholeCamera, ids=(3, 7, 12, 20), *, distance_mm: float = 300.0, seed: int = 0) -> np.ndarray:
    """The field markers ``ids`` (not the jig) lying side by side ``distance_mm`` in front of the camera, seen a little
    obliquely, through the twin's own marker renderer."""
    from drillnav.drivers.sim.camera import render_markers
    from drillnav.registration.markers import default_marker_set

    markers = {i: default_marker_set().by_id(i) for i in ids}
    tilt = Rotation.from_euler("x", 160, degrees=True).as_matrix()  # facing the camera, 20 deg off
    spacing = 60.0
    poses = {i: make_transform(tilt, [(k - (len(ids) - 1) / 2) * spacing, 0.0, distance_mm]) for k, i in enumerate(ids)}
    return render_markers(camera=camera, camera_from_marker=poses, markers=markers, rng=np.random.default_rng(seed), glare=False)


GLOVED_SEED, GLOVED_MARKER = 5000, 2


def gloved_frame():
    """Twin seed 5000 (inlet+outlet, the glove on), its first freehand frame, in which a gloved finger hides a corner
    of marker 2's tag and ArUco loses it: (scene, true carm_from_drill, frame (read-only), locator)."""
    scene = make_scene(seed=GLOVED_SEED, views="inlet,outlet", render=False, degradations=Degradations(glove=True))
    rng = np.random.default_rng(GLOVED_SEED)
    pose = scene.drill_pose_towards(rng, offset_mm=5.0, tilt_deg=5.0)
    image = scene.render_camera(rng, carm_from_drill=pose)
    image.setflags(write=False)
    locator = VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)
    return scene, pose, image, locator


CT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ct" / "cxr.nii.gz"


@lru_cache(maxsize=1)
def _patient():
    """The real CT as the twin's patient (``accuracy.load_patient``), loaded once per process: reading and converting it
    costs about 3 s of CPU, and most tests of the operating-room twin ask for it. Its CT is handed out read-only (a
    test that wrote into the shared patient would fail loudly; the attenuation volume stays writable, as numba's DRR
    kernel was compiled for it); its DRR cache is shared, so a view another test rendered is rendered once."""
    import accuracy

    patient = accuracy.load_patient(CT)
    patient.volume.data.setflags(write=False)
    return patient


def operating_room_scene(seed: int, pair: str, *, marker_tilt_deg: tuple[float, float] | None = None, **scene_args):
    """The accuracy study's scene of ``seed`` and view ``pair`` (every degradation, the real CT as anatomy): (scene, k),
    k the pair's index, which seeds its images (``accuracy.camera_shots``). Skips the test where the CT is absent.
    ``marker_tilt_deg``: the markers' tilt from the AP beam as ``accuracy.py --marker-tilt`` sets it (None: the twin's)."""
    import pytest

    if not CT.exists():
        pytest.skip("../shared/data/ct is not present on this machine (the twin's scene needs the real CT as its anatomy)")
    import accuracy

    patient = _patient()
    pairs = list(accuracy._pairs(np.random.default_rng(seed)).items())
    k = [p for p, _ in pairs].index(pair)
    degradations = Degradations.parse("all")
    if marker_tilt_deg is not None:
        degradations = replace(degradations, marker_tilt_deg=marker_tilt_deg)
    return accuracy.make_scene(seed=seed, views=pairs[k][1], render=False, degradations=degradations, voxel_anatomy=patient,
                               **scene_args), k


def study_shot(seed: int, pair: str, pose_index: int, *, marker_tilt_deg: tuple[float, float] | None = None):
    """The accuracy study's fluoroscopy marker poses and camera shot of ``seed``, view ``pair`` and drill pose
    ``pose_index``: (scene, marker poses, carm_from_drill of the shot, video detections, camera image), as
    ``accuracy.py`` makes them (:func:`operating_room_scene`; skips where the CT is absent)."""
    import accuracy

    from drillnav.drivers.sim.scene import render_fluoro
    from drillnav.registration.fluoro_markers import detect_in_view
    from drillnav.registration.marker_pose import register_markers

    scene, k = operating_room_scene(seed, pair, marker_tilt_deg=marker_tilt_deg)
    image_rng = np.random.default_rng([seed, k, 1])
    names = list(scene.views)
    dets = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in names}
    poses = tuple(register_markers([dets[n] for n in names], [scene.views[n] for n in names], scene.marker_set))
    pose, video, image = accuracy.camera_shots(scene, seed=seed, k=k, poses=pose_index + 1)[pose_index]
    return scene, poses, pose, video, image


def one_view_registration(seed: int, pair: str, pose_index: int, view: str | None = None, *, marker_tilt_deg: tuple[float, float] | None = None):
    """The study's registration of one view of ``pair`` alone (``view``; None: the pair's first) on the twin's ``seed``,
    drill pose ``pose_index``: (scene, the view's name, registration, its predicted error at the corridor's entry, the
    axis's error there in mm, its angle error in deg)."""
    import accuracy

    from drillnav.drivers.sim.scene import render_fluoro
    from drillnav.registration.fluoro_markers import detect_in_view
    from drillnav.registration.marker_pose import register_markers
    from drillnav.registration.video_fluoro import predicted_axis_error

    scene, k = operating_room_scene(seed, pair, marker_tilt_deg=marker_tilt_deg)
    image_rng = np.random.default_rng([seed, k, 1])
    dets = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in scene.views}
    view = next(iter(scene.views)) if view is None else view
    poses = tuple(register_markers([dets[view]], [scene.views[view]], scene.marker_set))
    pose, video, image = accuracy.camera_shots(scene, seed=seed, k=k, poses=pose_index + 1)[pose_index]
    video, reg = accuracy._register(scene, image, video, poses, joint=True)
    off_mm, off_deg = axis_error_at_entry(scene, pose, reg)
    pe = predicted_axis_error(video, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=scene.corridor_entry_carm_mm)
    return scene, view, reg, pe, off_mm, off_deg


def axis_error_at_entry(scene, carm_from_drill: np.ndarray, reg) -> tuple[float, float]:
    """The registered axis's error against the true one of the shot taken at ``carm_from_drill``, as the study scores
    it: (mm at the corridor's entry, deg)."""
    from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA

    entry = scene.corridor_entry_carm_mm
    axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
    true_axis = TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
    return float(np.linalg.norm(axis.closest_point(entry) - true_axis.closest_point(entry))), axis.angle_deg(true_axis)


def flat_marker_scene(seed: int):
    """The twin with the markers stuck flat on the skin (0-10 deg from the AP beam), AP + lateral, and its rendered
    log images {view name: (H, W)}: every marker face-on in the AP view and near edge-on in the lateral one."""
    from drillnav.drivers.sim.scene import render_fluoro

    scene = make_scene(seed=seed, views="ap,lateral", render=False, degradations=Degradations(surgeon_markers=True, marker_tilt_deg=(0.0, 10.0)))
    images = {n: render_fluoro(scene, n, np.random.default_rng([seed, 1])) for n in scene.views}
    return scene, images


def edge_on_rows_as_first_taken(monkeypatch) -> None:
    """Edge-on rings' rows as they were first taken, when the scenes of some tests were found: strokes as two
    agreeing halves only (no half alone, no centre of two that disagree, none along a line turned from the predicted
    one), no marker that a view shows by nothing looked for turned, no ambiguous roll settled by the stroke's profile,
    and no open ring measured around its ellipse (seed 11702's pair: 0.45 mm without its rolls). There, the later rows
    alone place the markers well enough that the scene no longer shows what the test checks."""
    from drillnav.registration import edge_on_ring, ring_outline, video_fluoro

    monkeypatch.setattr(ring_outline, "OPEN_RING_RATIO", float("inf"))  # no ring open enough

    monkeypatch.setattr(edge_on_ring, "LONE_MIN_CORRELATION", 2.0)  # no correlation reaches it
    monkeypatch.setattr(edge_on_ring, "CENTRE_AGREEMENT_PX", edge_on_ring.HALF_AGREEMENT_PX)
    monkeypatch.setattr(edge_on_ring, "TURN_SEARCH_DEG", ())
    monkeypatch.setattr(video_fluoro, "TURNED_STROKE_CORRELATION", 2.0)  # neither found turned nor settled by the stroke
