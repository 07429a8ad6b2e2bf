"""A complete twin scene: patient on the table, markers on the skin, the drill camera, C-arm shots, truth.

What is TRUE (used to render) and what the product is HANDED differ on purpose:
the camera renders through the true lens but camera.json carries calibration
error; the drill axis in drill.json is perturbed; BBs sit where manufacturing
put them while markers.json holds the design; fluoroscopy images the exact
analytic anatomy with beam hardening, scatter, quantum noise and blur, plus
what the CT lacks: the table, the markers and the K-wire in the drill, whose
tip rests on the bone at the entry when the shot is taken.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from drillnav.registration.axis_uncertainty import AxisUncertainty
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.camera_uncertainty import DEFAULT_INTRINSICS_UNCERTAINTY
from drillnav.registration.carm import CArmView, intensifier_distortion_sigma_px
from drillnav.registration.line import Line3D
from drillnav.registration.horn import absolute_orientation
from drillnav.registration.markers import BB, MarkerDesign, MarkerSet, default_marker_set
from drillnav.registration.transforms import apply, from_rotvec, invert, make_transform

from . import anatomy
from .ct_anatomy import VoxelAnatomy
from .blur import gaussian_blur_fft
from .camera import render_markers
from .degradations import LEAD_LINE_INTEGRAL, Box, Degradations, Hardware, collimator_mask, ii_distortion_maps, make_hardware
from .xray import MU_PER_MM, add_box, add_cylinder, add_ellipsoids, add_ring, add_slab, add_spheres, pixel_rays

__all__ = ["Scene", "make_scene", "parse_views", "NAMED_VIEWS", "CAMERA_FOV_DEG", "PAPER_CARM", "TRUE_DRILL_AXIS_CAMERA"]

# The drill camera's horizontal field of view (deg): a small USB camera's wide lens.
CAMERA_FOV_DEG = 76.0
PAPER_CARM = dict(source_to_detector_mm=1164.0, source_to_isocenter_mm=624.0, pixel_spacing_mm=(0.304, 0.304), rows=976, columns=976)
# Named positioner angles (primary LAO+, secondary CRA+). Inlet: beam tilted caudally; outlet: cranially.
NAMED_VIEWS: dict[str, tuple[float, float]] = {
    "ap": (0.0, 0.0),
    "lateral": (90.0, 0.0),
    "inlet": (0.0, -25.0),
    "outlet": (0.0, 30.0),
    "lao30": (30.0, 0.0),
    "rao30": (-30.0, 0.0),
}
# The drill axis in the camera frame: 45 mm below the optical centre, converging on the optical axis at ~225 mm.
TRUE_DRILL_AXIS_CAMERA = Line3D(point_mm=[0.0, 45.0, 0.0], direction=[0.0, -0.2, 1.0])
TABLE_Y_MM = (135.0, 160.0)
# The K-wire in the drill: it leaves the chuck 60 mm along the axis from the camera's axis point; 3 mm steel.
KWIRE_CHUCK_MM = 60.0
KWIRE_RADIUS_MM = 1.5


class SceneError(ValueError):
    """A scene request that cannot be simulated (bad view, marker id, count)."""


def parse_views(text: str) -> dict[str, tuple[float, float]]:
    """'ap,outlet,20:-10' -> {name: (primary_deg, secondary_deg)}."""
    views: dict[str, tuple[float, float]] = {}
    for item in (t.strip() for t in text.split(",") if t.strip()):
        if item in NAMED_VIEWS:
            views[item] = NAMED_VIEWS[item]
            continue
        try:
            a, b = (float(v) for v in item.split(":"))
        except ValueError:
            raise SceneError(f"unknown view '{item}': use one of {', '.join(NAMED_VIEWS)} or PRIMARY:SECONDARY in degrees") from None
        if not (-180 <= a <= 180 and -90 <= b <= 90):
            raise SceneError(f"view '{item}': primary must be -180..180 and secondary -90..90 degrees")
        views[f"p{a:+.0f}s{b:+.0f}"] = (a, b)
    if not views:
        raise SceneError("no views given")
    return views


@dataclass(frozen=True, kw_only=True)
class Scene:
    seed: int
    marker_set: MarkerSet                      # the design, handed to the product
    manufactured: dict[int, MarkerDesign]      # as built: BBs with manufacturing error
    carm_from_ct: NDArray[np.float64]
    carm_from_marker: dict[int, NDArray[np.float64]]
    carm_from_drill: NDArray[np.float64]
    true_camera: PinholeCamera
    calibrated_camera: PinholeCamera           # handed to the product (with calibration error)
    calibrated_axis_drill: Line3D              # handed to the product (with calibration error)
    corridor: anatomy.Corridor
    views: dict[str, CArmView]
    view_angles: dict[str, tuple[float, float]]
    fluoro_log: dict[str, NDArray[np.float32]] = field(default_factory=dict)
    camera_image: NDArray[np.uint8] | None = None
    kwire: bool = True                         # the K-wire is in the drill (and in the fluoroscopy)
    voxel_anatomy: VoxelAnatomy | None = None  # a real CT as the patient (None: the analytic pelvis)
    table_y_mm: tuple[float, float] = TABLE_Y_MM
    degradations: Degradations = field(default_factory=Degradations)  # what the operating room adds (default: none)
    hardware: Hardware = ()                    # surgical metal in the field (frame C), with ``degradations.hardware``
    carm: Mapping[str, object] = field(default_factory=lambda: dict(PAPER_CARM))  # the C-arm's geometry and detector (PAPER_CARM's keys)

    def measured_marker_set(self) -> MarkerSet:
        """The marker set a site writes with ``drillnav markers measure``, taken as perfectly measured: each marker as
        built, its BBs in the frame that best fits the design (X-ray does not show their common rigid displacement
        against the paper tag, which stays at the design's place)."""
        measured = []
        for design in self.marker_set.markers:
            built = self.manufactured[design.marker_id]
            fit = absolute_orientation(built.bb_centers_mm, design.bb_centers_mm).target_from_source
            measured.append(replace(built, bbs=tuple(BB(center_mm=fit[:3, :3] @ b.center_mm + fit[:3, 3], diameter_mm=b.diameter_mm) for b in built.bbs)))
        return MarkerSet(markers=tuple(measured))

    def kwire_carm(self, carm_from_drill: NDArray[np.float64] | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """The K-wire as (chuck end, tip) in C (mm), its tip at the true axis's point nearest the corridor entry."""
        if not self.kwire:
            return None
        axis = TRUE_DRILL_AXIS_CAMERA.transformed(self.carm_from_drill if carm_from_drill is None else carm_from_drill)
        tip = axis.closest_point(self.corridor_entry_carm_mm)
        s_tip = float((tip - axis.point_mm) @ axis.direction)
        if s_tip <= KWIRE_CHUCK_MM + 10.0:
            return None  # the drill is too close for a wire to fit: none in the image
        return np.asarray(axis.at(KWIRE_CHUCK_MM), dtype=np.float64).reshape(3), np.asarray(tip, dtype=np.float64).reshape(3)

    @property
    def drill_axis_carm(self) -> Line3D:
        axis = TRUE_DRILL_AXIS_CAMERA.transformed(self.carm_from_drill)
        return Line3D(point_mm=axis.closest_point(self.corridor_entry_carm_mm), direction=axis.direction)

    @property
    def corridor_entry_carm_mm(self) -> NDArray[np.float64]:
        return apply(self.carm_from_ct, np.asarray(self.corridor.entry_mm))

    def camera_from_marker(self, carm_from_drill: NDArray[np.float64] | None = None) -> dict[int, NDArray[np.float64]]:
        drill_from_carm = invert(self.carm_from_drill if carm_from_drill is None else carm_from_drill)
        return {i: drill_from_carm @ t for i, t in self.carm_from_marker.items()}

    def render_camera(self, rng: np.random.Generator, *, carm_from_drill: NDArray[np.float64] | None = None, **kwargs) -> NDArray[np.uint8]:
        if self.degradations.camera:
            kwargs.setdefault("degradations", self.degradations)
        return render_markers(camera=self.true_camera, camera_from_marker=self.camera_from_marker(carm_from_drill), markers=self.manufactured, rng=rng, **kwargs)

    def drill_pose_towards(self, rng: np.random.Generator, *, offset_mm: float = 3.0, tilt_deg: float = 3.0, standoff_mm: float = 290.0) -> NDArray[np.float64]:
        """A freehand drill pose aiming near the corridor entry (``carm_from_drill``)."""
        return _drill_pose(rng, self.corridor, self.carm_from_ct, offset_mm=offset_mm, tilt_deg=tilt_deg, standoff_mm=standoff_mm)


def _drill_pose(rng, corridor, carm_from_ct, *, offset_mm, tilt_deg, standoff_mm) -> NDArray[np.float64]:
    entry = apply(carm_from_ct, np.asarray(corridor.entry_mm)) + rng.normal(scale=offset_mm / np.sqrt(3), size=3)
    d = carm_from_ct[:3, :3] @ anatomy.corridor_direction(corridor)
    d = Rotation.from_rotvec(np.radians(tilt_deg) * _unit(rng.normal(size=3))).apply(d)
    d_cam = TRUE_DRILL_AXIS_CAMERA.direction
    # Rotation taking the camera-frame axis direction onto d, then a random roll about d.
    align, _ = Rotation.align_vectors([d], [d_cam])
    roll = Rotation.from_rotvec(d * rng.uniform(-np.pi / 6, np.pi / 6))
    r = (roll * align).as_matrix()
    t = entry - standoff_mm * d - r @ TRUE_DRILL_AXIS_CAMERA.point_mm
    return make_transform(r, t)


def _unit(v):
    return v / np.linalg.norm(v)


# The patient's anterior direction in V (LPS): the AP beam's axis, from which a surgeon's marker tilts.
ANTERIOR_V = np.array([0.0, -1.0, 0.0])
MIN_MARKER_SPACING_MM = 58.0  # a surgeon keeps the 48 mm rings apart on the skin


def _on_front(skin_at, r: float, a: float) -> bool:
    """Whether (r, a) lands on the body's front (not off the outline, not on the flank)."""
    try:
        _, normal = skin_at(r, a)
    except ValueError:
        return False
    return bool(normal @ ANTERIOR_V > np.cos(np.radians(60.0)))


def _surgeon_sites(rng, n: int, degradations: Degradations, skin_at) -> list[tuple[float, float]]:
    """(radius_mm, angle_rad) about the incision, spread unevenly as a surgeon sticks them, one by one, rings not touching."""
    sites: list[tuple[float, float]] = []
    for _ in range(2000):
        r, a = float(rng.uniform(*degradations.marker_radius_mm)), float(rng.uniform(0, 2 * np.pi))
        xy = np.array([r * np.cos(a), r * np.sin(a)])
        if all(np.hypot(*(xy - [ri * np.cos(ai), ri * np.sin(ai)])) >= MIN_MARKER_SPACING_MM for ri, ai in sites) and _on_front(skin_at, r, a):
            sites.append((r, a))
            if len(sites) == n:
                return sites
    raise SceneError(f"{n} markers do not fit {MIN_MARKER_SPACING_MM:.0f} mm apart within {degradations.marker_radius_mm[1]:.0f} mm of the incision")


def _surgeon_normal(rng, skin_normal, degradations: Degradations) -> NDArray[np.float64]:
    """The marker's normal tilted 10-40 deg from the AP axis, towards where the skin itself tilts."""
    tangential = skin_normal - (skin_normal @ ANTERIOR_V) * ANTERIOR_V
    toward = _unit(tangential) if np.linalg.norm(tangential) > 0.05 else _unit(np.cross(ANTERIOR_V, rng.normal(size=3)))
    tilt = np.radians(rng.uniform(*degradations.marker_tilt_deg))
    return Rotation.from_rotvec(tilt * _unit(np.cross(ANTERIOR_V, toward))).apply(ANTERIOR_V)


def _place_on_skin(rng, ids, carm_from_ct, skin_at, degradations: Degradations | None = None) -> dict[int, NDArray[np.float64]]:
    """Markers round a 50 mm circle, each resting on the skin: ``skin_at(radius_mm, angle_rad) -> (point, normal)`` in V.

    With ``degradations.surgeon_markers``: where a surgeon sticks them instead (uneven, 40-95 mm out, tilted 10-40 deg).
    """
    n = len(ids)
    surgeon = degradations is not None and degradations.surgeon_markers
    radius = 50.0 if n > 1 else 0.0
    phase = rng.uniform(0, 2 * np.pi)
    sites = _surgeon_sites(rng, n, degradations, skin_at) if surgeon else None
    poses = {}
    for k, marker_id in enumerate(ids):
        if surgeon:
            r, a = sites[k]
        else:
            a = phase + 2 * np.pi * k / n + rng.normal(scale=0.08)
            r = radius + rng.normal(scale=2.0)
        try:
            p, normal = skin_at(r, a)
        except ValueError as exc:
            raise SceneError(f"marker {marker_id} cannot be placed on the skin {r:.0f} mm from the entry: {exc}") from None
        if surgeon:
            normal = _surgeon_normal(rng, normal, degradations)
        else:
            normal = Rotation.from_rotvec(np.radians(5.0) * _unit(rng.normal(size=3))).apply(normal)
        z = _unit(normal)
        x = _unit(np.cross([0.0, 0.0, 1.0], z))
        y = np.cross(z, x)
        spin = Rotation.from_rotvec(z * rng.uniform(0, 2 * np.pi)).as_matrix()
        ct_from_marker = make_transform(spin @ np.stack([x, y, z], axis=1), p + 1.0 * z)  # resting on the drape
        poses[marker_id] = carm_from_ct @ ct_from_marker
    return poses


def _place_markers(rng, ids, carm_from_ct, corridor, degradations=None) -> dict[int, NDArray[np.float64]]:
    """On the analytic body's anterior skin, about the corridor's skin entry."""
    centre_v, _ = anatomy.skin_entry(corridor)
    return _place_on_skin(rng, ids, carm_from_ct, lambda r, a: anatomy.skin_point(centre_v[0] + r * np.cos(a), centre_v[2] + r * np.sin(a)), degradations)


def _place_markers_ct(rng, ids, carm_from_ct, patient: VoxelAnatomy, degradations=None) -> dict[int, NDArray[np.float64]]:
    """On a real CT's skin about the trajectory's skin entry, each cast onto the skin along the trajectory."""
    centre, _ = patient.skin_entry()
    d = anatomy.corridor_direction(patient.corridor)
    u = _unit(np.cross(d, [0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.cross(d, [1.0, 0.0, 0.0]))
    v = np.cross(d, u)
    return _place_on_skin(rng, ids, carm_from_ct, lambda r, a: patient.skin_along(centre + r * (np.cos(a) * u + np.sin(a) * v) + 40.0 * d, -d), degradations)


def _perturbed_camera(rng, camera: PinholeCamera) -> PinholeCamera:
    k = camera.camera_matrix.copy()
    u = DEFAULT_INTRINSICS_UNCERTAINTY
    k[0, 0] *= 1 + rng.normal(scale=u.focal_rel)
    k[1, 1] = k[0, 0] * (1 + rng.normal(scale=0.0005))
    k[0, 2] += rng.normal(scale=u.principal_px)
    k[1, 2] += rng.normal(scale=u.principal_px)
    d = camera.distortion + rng.normal(scale=list(u.distortion))
    # Drawn at exactly a typical calibration's error, which its camera.json states.
    return PinholeCamera(width=camera.width, height=camera.height, camera_matrix=k, distortion=d, uncertainty=DEFAULT_INTRINSICS_UNCERTAINTY)


# The drill axis's calibration error as drill.json states it (residual_mm per axis of its point, residual_deg the
# RMS tilt) and as the predicted error assumes it: Gaussian. Drawn at exactly 0.12 deg about a random axis (as
# before), the tilt across the drill axis was 0.098 deg RMS and never over 0.12 deg, against the stated 2-D
# Gaussian's 0.12 deg RMS and 0.18 deg 90th percentile, so the predicted bounds over-covered on the twin.
AXIS_CALIBRATION_SIGMA_MM = 0.1
AXIS_CALIBRATION_RMS_TILT_DEG = 0.12
AXIS_CALIBRATION_UNCERTAINTY = AxisUncertainty(sigma_mm=AXIS_CALIBRATION_SIGMA_MM, rms_tilt_deg=AXIS_CALIBRATION_RMS_TILT_DEG)  # drill.json's residuals


def _perturbed_axis(rng, axis: Line3D) -> Line3D:
    # Three normals, as before, so every later draw of the scene is unchanged; their part along the axis does
    # not tilt it, the two across it are each sigma = RMS / sqrt(2).
    g = rng.normal(size=3)
    g -= (g @ axis.direction) * axis.direction
    d = Rotation.from_rotvec(np.radians(AXIS_CALIBRATION_RMS_TILT_DEG / np.sqrt(2.0)) * g).apply(axis.direction)
    return Line3D(point_mm=axis.point_mm + rng.normal(scale=AXIS_CALIBRATION_SIGMA_MM, size=3), direction=d)


def render_fluoro(scene: Scene, view_name: str, rng: np.random.Generator, *, dose_quanta: float | None = None,
                  carm_from_drill: NDArray[np.float64] | None = None) -> NDArray[np.float32]:
    """Measured log attenuation (rows, columns) of one shot, with the twin's physics (the K-wire where the drill is).

    ``dose_quanta``: quanta per pixel unattenuated; None: 12,000, or drawn from
    ``scene.degradations.dose_quanta`` with ``low_dose``. The scene's other
    fluoroscopy degradations (hardware, collimator, image-intensifier
    distortion) apply here too.
    """
    deg = scene.degradations
    if dose_quanta is None:
        dose_quanta = float(rng.uniform(*deg.dose_quanta)) if deg.low_dose else 12000.0
    if not dose_quanta > 0:
        raise SceneError(f"dose must be > 0 quanta per pixel, got {dose_quanta}")
    view = scene.views[view_name]
    rays = pixel_rays(view)
    if scene.voxel_anatomy is not None:
        line = scene.voxel_anatomy.line_integrals(view, scene.carm_from_ct)
    else:
        line = np.zeros((view.rows, view.columns))
        add_ellipsoids(line, view, anatomy.pelvis_ellipsoids_carm(scene.carm_from_ct), rays=rays)
    add_slab(line, view, y_min_mm=scene.table_y_mm[0], y_max_mm=scene.table_y_mm[1], mu=MU_PER_MM["table"], rays=rays)
    for marker_id, pose in scene.carm_from_marker.items():
        design = scene.manufactured[marker_id]
        centres = apply(pose, design.bb_centers_mm)
        add_spheres(line, view, centres, design.bb_diameters_mm / 2, MU_PER_MM["tungsten"])
        add_ring(line, view, pose, radius_mm=design.ring_radius_mm, wire_diameter_mm=design.ring_wire_diameter_mm, mu=MU_PER_MM["tungsten"])
    wire = scene.kwire_carm(carm_from_drill)
    if wire is not None:
        add_cylinder(line, view, wire[0], wire[1], radius_mm=KWIRE_RADIUS_MM, mu=MU_PER_MM["steel"], rays=rays)
    for part in scene.hardware:
        if isinstance(part, Box):
            add_box(line, view, centre_mm=np.asarray(part.centre_mm), carm_from_box_rotation=np.asarray(part.axes), half_size_mm=np.asarray(part.half_size_mm),
                    mu=MU_PER_MM["steel"], rays=rays)
        else:
            add_cylinder(line, view, np.asarray(part.start_mm), np.asarray(part.end_mm), radius_mm=part.radius_mm, mu=MU_PER_MM["steel"], rays=rays)
    # Beam hardening: a polyenergetic beam attenuates less per mm the more it has crossed.
    hardened = 6.0 * np.log1p(line / 6.0)
    primary = dose_quanta * np.exp(-hardened)
    if deg.collimator:
        # Lead at the source stops the primary (no hardening model needed for it), so the shadow also scatters less.
        primary *= np.exp(-LEAD_LINE_INTEGRAL * collimator_mask(rng, view.rows, view.columns))
    # Sizes in the detector plane are stated in the reference detector's pixels (PAPER_CARM): a coarser detector
    # sees the same millimetres in fewer of its pixels.
    per_px = PAPER_CARM["pixel_spacing_mm"][1] / view.pixel_spacing_mm[1]
    scatter = 0.12 * gaussian_blur_fft(primary, 35.0 * per_px)
    counts = rng.poisson(primary + scatter).astype(np.float64)
    if deg.ii_distortion:
        # The intensifier's electron optics bend the image after the input phosphor caught the quanta.
        map_x, map_y = ii_distortion_maps(view.rows, view.columns, pincushion_px=deg.ii_pincushion_px * per_px, s_px=deg.ii_s_px * per_px)
        counts = cv2.remap(counts, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    counts = cv2.GaussianBlur(counts, (0, 0), 0.6)
    return (-np.log(np.maximum(counts, 0.5) / dose_quanta)).astype(np.float32)


def make_scene(
    *,
    seed: int,
    n_markers: int = 5,
    marker_ids: list[int] | None = None,
    views: str | dict[str, tuple[float, float]] = "inlet,outlet",
    corridor: str = "AIIS-PSIS",
    image_size: tuple[int, int] = (1280, 720),
    camera_fov_deg: float = CAMERA_FOV_DEG,
    render: bool = True,
    bb_manufacturing_sigma_mm: float = 0.05,
    kwire: bool = True,
    voxel_anatomy: VoxelAnatomy | None = None,
    degradations: Degradations | None = None,
    carm: Mapping[str, object] | None = None,
) -> Scene:
    """A deterministic scene for ``seed``; ``render=False`` skips the images (geometry and truth only).

    ``image_size``: the drill camera's frame (width, height) px, ``camera_fov_deg`` its horizontal field of view.
    ``carm``: the C-arm's geometry and detector as :data:`PAPER_CARM`'s keys (None: :data:`PAPER_CARM`, the
    reference's C-arm).

    ``voxel_anatomy``: a real CT as the patient, with its planned trajectory (``corridor`` is then unused).
    ``degradations``: what an operating room adds (``drivers/sim/degradations.py``); None: none.
    ``ct_anatomy`` among them needs ``voxel_anatomy`` (the caller loads the CT).
    """
    degradations = degradations if degradations is not None else Degradations()
    if degradations.ct_anatomy and voxel_anatomy is None:
        raise SceneError("the ct_anatomy degradation needs voxel_anatomy= (a real CT loaded by the caller, e.g. ../shared/data/ct/cxr.nii.gz)")
    rng = np.random.default_rng(seed)
    design_set = default_marker_set()
    if marker_ids is None:
        if not 1 <= n_markers <= 7:
            raise SceneError(f"--markers must be 1..7 (markers must fit the fluoroscopy field), got {n_markers}")
        marker_ids = sorted(rng.choice(len(design_set.markers), size=n_markers, replace=False).tolist())
    used = design_set.subset(marker_ids)
    if voxel_anatomy is not None:
        target = voxel_anatomy.corridor
    else:
        corridors = {c.name: c for c in anatomy.CORRIDORS}
        if corridor not in corridors:
            raise SceneError(f"unknown corridor '{corridor}': one of {', '.join(corridors)}")
        target = corridors[corridor]
    view_angles = parse_views(views) if isinstance(views, str) else dict(views)

    # Patient on the table: the entry site near the isocentre, a few degrees and mm off.
    try:
        skin, skin_normal = voxel_anatomy.skin_entry() if voxel_anatomy is not None else anatomy.skin_entry(target)
    except ValueError as exc:
        raise SceneError(f"the trajectory {target.name} does not reach the skin: {exc}") from None
    centre_v = 0.8 * skin + 0.2 * np.asarray(target.entry_mm)
    carm_from_ct = from_rotvec(np.radians(2.0) * rng.normal(size=3))
    carm_from_ct[:3, 3] = -carm_from_ct[:3, :3] @ centre_v + rng.normal(scale=3.0, size=3)

    if voxel_anatomy is not None:
        poses = _place_markers_ct(rng, marker_ids, carm_from_ct, voxel_anatomy, degradations)
        back = voxel_anatomy.posterior_extent_mm(carm_from_ct)
        table_y = (back + 2.0, back + 27.0)  # the table top just under the patient's back
    else:
        poses = _place_markers(rng, marker_ids, carm_from_ct, target, degradations)
        table_y = TABLE_Y_MM
    manufactured = {m.marker_id: m.with_bb_errors(rng, bb_manufacturing_sigma_mm) for m in used.markers}
    true_camera = PinholeCamera.from_fov(width=image_size[0], height=image_size[1], horizontal_fov_deg=camera_fov_deg, distortion=[-0.12, 0.09, 0.0006, -0.0004, -0.02])
    carm_from_drill = _drill_pose(rng, target, carm_from_ct, offset_mm=3.0, tilt_deg=3.0, standoff_mm=290.0)
    # The twin's C-arm with ii_distortion is an image intensifier without a dewarp calibration: its views say so
    # (as its DICOM does, X-Ray Receptor Type), and the product estimates their distortion.
    carm = dict(PAPER_CARM if carm is None else carm)
    ii_sigma = intensifier_distortion_sigma_px(float(carm["pixel_spacing_mm"][1])) if degradations.ii_distortion else 0.0
    scene_views = {name: CArmView.from_positioner(primary_deg=a, secondary_deg=b, distortion_sigma_px=ii_sigma, **carm)
                   for name, (a, b) in view_angles.items()}
    scene = Scene(
        seed=seed,
        marker_set=used,
        manufactured=manufactured,
        carm_from_ct=carm_from_ct,
        carm_from_marker=poses,
        carm_from_drill=carm_from_drill,
        true_camera=true_camera,
        calibrated_camera=_perturbed_camera(rng, true_camera),
        calibrated_axis_drill=_perturbed_axis(rng, TRUE_DRILL_AXIS_CAMERA),
        corridor=target,
        views=scene_views,
        view_angles=view_angles,
        kwire=kwire,
        voxel_anatomy=voxel_anatomy,
        table_y_mm=table_y,
        degradations=degradations,
        hardware=make_hardware(np.random.default_rng([seed, 5]), site_carm_mm=apply(carm_from_ct, skin), anterior_carm=carm_from_ct[:3, :3] @ skin_normal)
        if degradations.hardware else (),
        carm=carm,
    )
    if not render:
        return scene
    image_rng = np.random.default_rng([seed, 1])
    fluoro = {name: render_fluoro(scene, name, image_rng) for name in scene_views}
    camera_image = scene.render_camera(image_rng)
    return Scene(**{**scene.__dict__, "fluoro_log": fluoro, "camera_image": camera_image})
