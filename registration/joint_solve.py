"""One joint solve of every marker pose and ``carm_from_drill`` over video and fluoroscopy.

The two modalities see complementary things: the camera, close to a 30 mm tag,
fixes each marker's normal and in-plane layout; the C-arm, through a handful of
BBs, fixes each marker's position across the beam but only weakly its depth
along the beam (magnification) and, for a marker nearly face-on to the beam, not
which of its two mirror poses it is in. Solving them together lets each cover
the other's weakness.

Unknowns: ``carm_from_drill`` (6), every marker's ``carm_from_marker`` (6 each)
and the camera's focal scale, principal point and distortion coefficients (8, held
near camera.json by priors of its calibration uncertainty, so that the covariance
carries it).
Residuals, each divided by its noise: every identified BB in every fluoroscopy
view (``fluoro_sigma_px``) and every tag corner in the camera image
(``corner_sigma_px``), each tag's corners and each marker's BBs in a view whitened
together for the shift and scale they share (blur, exposure, an image
intensifier's distortion: :data:`CORNER_COMMON_PER_SIGMA`, :data:`BB_COMMON_SIGMA_PX`). scipy's ``least_squares`` (trust-region reflective); the
Jacobian is block sparse (a BB residual depends on its own marker's 6
parameters only, a corner on its marker's, the drill's and the intrinsics) and
small, so all its forward differences are taken in one batched evaluation. A marker whose normalised residuals stand out is rejected, named,
and the solve repeated without it; one that still misfits, where that rule cannot act, is voted out by the others
when they fit without it, and a misfit that remains widens the covariance by the fit's reduced chi-square.

Rotations are perturbed about the centroid of the markers (drill) or the marker
centre (markers), which keeps rotation and translation nearly uncorrelated and
the covariance readable.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import block_diag
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

from .camera import PinholeCamera
from .camera_uncertainty import DEFAULT_INTRINSICS_UNCERTAINTY, camera_priors
from .carm import intensifier_shift_px
from .cut_corners import across_slides
from .errors import MarkersNotFound
from .markers import MarkerSet
from .transforms import apply, invert, make_transform
from .video_claims import drill_from_marker
from .video_markers import SQUARE_MISFIT_MIN_PX, tag_object_points

__all__ = ["JointSolution", "joint_solve", "perturb_about", "project_distorted", "FOCAL_REL_SIGMA", "PRINCIPAL_SIGMA_PX", "DISTORTION_SIGMA",
           "CORNER_COMMON_PER_SIGMA", "CORNER_SCALE_PER_SIGMA", "BB_COMMON_SIGMA_PX", "BB_SCALE_SIGMA_PX",
           "SQUARE_MISFIT_PER_RMS", "SQUARE_MISFIT_MIN_PX", "square_misfit_noise_px", "CORNER_SIGMA_PX", "FRAME_CORNER_PER_EDGE_SIGMA",
           "frame_corner_sigma_px", "frame_shape_modes", "N_FRAME_MODES"]

N_INTRINSICS = 8  # focal scale (relative), cx, cy (px), distortion k1, k2, p1, p2, k3 (OpenCV's order)
# The camera calibration's uncertainty (1 sigma) held by the priors, at a calibration's stated size: focal
# length (relative, fx and fy together), principal point per axis, and the distortion coefficients. The
# distortion's error is a parameter of its own: it used to act only through a focal / principal prior widened
# to 0.3 % / 1.5 px, a fudge tuned on 4 seeds that, measured again on 32 (benchmarks/bound_coverage.py), put the
# covariance's position term at 1.3-1.5 times the pose's actual error (docs/identity_and_error.md).
# A calibration may state a larger uncertainty (camera.json's intrinsics_sigma): registration/camera_uncertainty.py.
FOCAL_REL_SIGMA = DEFAULT_INTRINSICS_UNCERTAINTY.focal_rel
PRINCIPAL_SIGMA_PX = DEFAULT_INTRINSICS_UNCERTAINTY.principal_px
DISTORTION_SIGMA = DEFAULT_INTRINSICS_UNCERTAINTY.distortion
# Errors shared by a whole group of measurements, which the group's pose absorbs and its residuals therefore
# cannot show, as the operating room makes them (1 sigma, px; benchmarks/noise_decomposition.py measures each
# against the twin's truth, seeds 9100-9103, docs/identity_and_error.md). Each group's errors have covariance
# sigma^2 I + shift^2 (per image axis, the group together) + scale^2 (radially, at the group's mean radius).
# A tag's four corners: blur, defocus, compression and an exposure step move a tag's edges together, sideways
# (shift) and in or out (scale), as they widen its edges and so raise the corners' independent scatter too: stated
# in proportion to that independent noise (as the residuals re-estimate it), so a sharp frame is not charged for a
# blurred one's errors. With every camera degradation on: 0.22 px shift and 0.68 px scale against 0.49 px
# independent (0.45 and 1.4 of it); motion blur alone 0.23 / 0.14 / 0.35 px; a clean frame 0.07 / 0.03 / 0.04 px
# (its independent noise floored at half the stated 0.3 px, so charged 0.07 / 0.21 px).
CORNER_COMMON_PER_SIGMA = 0.45
CORNER_SCALE_PER_SIGMA = 1.4

# A tag corner's independent noise (1 sigma, px) the solve starts from; re-estimated from the corners' residuals.
CORNER_SIGMA_PX = 0.3

# Errors shared by every tag of one frame: a motion blur streaks the whole frame one way, and where it runs across a
# tag's black border into the code's white cells it moves the border's edges by an amount that depends on the edge's
# direction against the streak's. Every tag's corners then err alike, a few tenths of a pixel, in four modes of its
# shape (about its own centre, at its half-diagonal): a scale, a turn, and two stretches. A stretch of a tag's image
# reads as a tilt of its normal (the more, the nearer the tag is to face-on); common to the frame's tags, it tilts
# every tag's normal the same way, which no number of tags averages out. Measured against the twin's truth (every camera
# degradation, seeds 9100-9107, 3 frames each, a frame's mean over its tags; benchmarks/noise_decomposition.py): at
# 640x480 (tags 41 px to the half-diagonal) 0.24 / 0.26 / 0.24 / 0.19 px RMS, at 1280x720 (79 px) 0.10 / 0.06 / 0.10 /
# 0.10 px; at 640x480 motion blur alone makes most of them. The covariance carries them at FRAME_CORNER_PER_EDGE_SIGMA
# times the RMS of the frame's tags' edge-stated noise (``VideoMarker.edge_sigma_px``, which grows with the same blur
# against the same tags): 0.41 px at 640x480 and 0.24 px at 1280x720 there, against which the shared modes were
# 0.46-0.63 and 0.27-0.43 of it. They are not solved for: held as unknowns under a prior of that size (as the
# intrinsics are), they moved the 640x480 axis by more than they held it (seeds 32903-32905: two-view angle RMS 0.195
# -> 0.238 deg).
N_FRAME_MODES = 4
FRAME_CORNER_PER_EDGE_SIGMA = 0.6


def frame_corner_sigma_px(edge_sigma_px) -> float:
    """The size (1 sigma, px at each tag's half-diagonal) of the shape modes every tag of a frame shares
    (:data:`FRAME_CORNER_PER_EDGE_SIGMA`), from its detected tags' edge-stated noises ``edge_sigma_px`` (K,) px (those at
    0, not stated, left out); 0 where none is stated (nothing is then carried)."""
    e = np.asarray([float(v) for v in edge_sigma_px if np.isfinite(v) and v > 0], dtype=np.float64)
    return float(FRAME_CORNER_PER_EDGE_SIGMA * np.sqrt(np.mean(e**2))) if len(e) else 0.0


def frame_shape_modes(groups_px: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The shape modes (N, 2, N_FRAME_MODES) every tag of a frame shares, at each observed corner of ``groups_px`` (each
    tag's kept corners (k, 2) px): scale, turn, and the two stretches about the tag's centre, one unit at its
    half-diagonal (RMS distance of its corners from their centre)."""
    out = []
    for g in groups_px:
        g = np.asarray(g, dtype=np.float64).reshape(-1, 2)
        rel = g - g.mean(axis=0)
        half = float(np.sqrt(np.mean(np.sum(rel * rel, axis=1))))
        q = rel / half if half > 0 else np.zeros_like(rel)
        x, y = q[:, 0], q[:, 1]
        out.append(np.stack([np.stack([x, y], axis=1), np.stack([-y, x], axis=1), np.stack([x, -y], axis=1), np.stack([y, x], axis=1)], axis=2))
    return np.concatenate(out) if out else np.zeros((0, 2, N_FRAME_MODES))

# A tag's four corners fit a view of its square (its size, the calibrated camera) with 2 degrees of freedom to
# spare: an RMS misfit r (px, over the corners) says each corner coordinate is off by about sqrt(2) r. Under every
# camera degradation (twin seeds 5000-5030, 3 poses, 314 detected tags) the tags with a corner over 1.5 px off
# misfit their square by 0.07-2.0 px, half of them over 0.33 px; the others by 0.06 px (median), 0.15 px (p90),
# 0.36 px (p99). A misfit over SQUARE_MISFIT_MIN_PX is charged as extra noise on each of the tag's corners.
# SQUARE_MISFIT_MIN_PX (0.2 px) is defined beside the tag's pose (video_markers.py), whose repair of a displaced corner
# also stops at it.
SQUARE_MISFIT_PER_RMS = float(np.sqrt(2.0))


def square_misfit_noise_px(reprojection_error_px: float) -> float:
    """The extra independent noise (px) charged to each corner of a tag whose corners misfit a view of its square by
    ``reprojection_error_px`` RMS (``VideoMarker.reprojection_error_px``): 0 up to :data:`SQUARE_MISFIT_MIN_PX`."""
    r = float(reprojection_error_px)
    return SQUARE_MISFIT_PER_RMS * r if r > SQUARE_MISFIT_MIN_PX else 0.0


# One marker's BBs in one fluoroscopy view: an image intensifier's distortion (pincushion, S) is smooth over a
# marker's few centimetres, so it shifts and scales its BBs together; with every fluoroscopy degradation on,
# 0.77 px shift and 0.24 px scale (independent rest 0.28 px, and the BBs' 0.05 mm manufacturing error 0.32 px
# per coordinate, which the variance components see); a flat panel's clean shot: 0.02 / 0.02 px, and with
# surgeon_markers, low_dose, hardware and collimator 0.036 / 0.034 px (benchmarks/noise_decomposition.py, seeds
# 9100-9102). Stated at the intensifier's size for every view, also where its distortion is estimated
# (CArmView.distortion_sigma_px: what the r^3 model leaves) and on a flat panel: stated at the flat panel's
# 0.04 / 0.03 px, a single lateral view with an edge-on marker (tests/test_video_claims.py, seed 40) put the axis
# 2.33 mm off at the entry, 0.80 mm with these (the corners' shared terms discount the camera's depth, and a
# marker's BB pattern scale alone then decides it); on the clean twin they cost the two-view angle 0.060 ->
# 0.138 deg RMS (docs/identity_and_error.md).
BB_COMMON_SIGMA_PX = 0.77
BB_SCALE_SIGMA_PX = 0.24
# A BB whose shadow overlaps or nearly touches another's comes out of the blob detector pulled towards it: a
# bias, which the pose partly absorbs. Its extra noise (px) against the crowding ratio (distance to the nearest
# other BB's projection over the sum of their projected radii), from the detected centres' errors against the
# twin's truth (every fluoroscopy degradation but the intensifier's, seeds 6100-6102, every pair: RMS 3.55 px
# under 0.8, 1.23 px at 1.0-1.2, 0.73 px at 1.2-1.5, 0.48-0.56 px beyond, less the 0.5 px of the rest).
CROWDED_BB_PX = (np.array([0.8, 1.1, 1.35, 1.6]), np.array([3.5, 1.1, 0.5, 0.0]))
# An intensifier's radial distortion is pincushion (its curved input screen imaged onto a flat output: outward at the
# edge), never barrel: a barrel coefficient is held by this share of the prior's size (1 px at the field's corner on
# the reference pixel: a slightly over-corrected image). Symmetric about zero, the prior let a single view's
# constellation mirror fit better than the truth by bending the image into a barrel (twin seed 23702, flat markers,
# one view: -7.7 px against the truth's +12.2, chi-square 10.7 against 40.7; the axis 76.7 mm / 36.6 deg off under a
# 6.1 mm / 3.0 deg bound; tests/test_intensifier_mirror.py). The S distortion's sign follows the room's field: either.
BARREL_SHARE = 0.1


@dataclass(frozen=True, kw_only=True)
class JointSolution:
    """Result of :func:`joint_solve`.

    carm_from_drill : (4, 4).
    carm_from_marker : {marker id: (4, 4)} of the markers used.
    covariance_drill : (6, 6) covariance of the drill perturbation (rotation vector rad, translation mm) about
        ``pivot_carm_mm`` (see :func:`perturb_about`), marginal over the markers and intrinsics; the BBs' and
        the corners' noise are each re-estimated from their own residuals (variance components), the
        intrinsics' prior keeps its stated size.
    marker_chi : {marker id: RMS normalised residual} (about 1 for a marker that fits its noise model). When one
        is over the solve's ``outlier_chi`` at the end, ``covariance_drill`` is scaled by ``reduced_chi2``.
    """

    carm_from_drill: NDArray[np.float64]
    carm_from_marker: dict[int, NDArray[np.float64]]
    covariance_drill: NDArray[np.float64]
    pivot_carm_mm: NDArray[np.float64]
    used_ids: tuple[int, ...]
    rejected_ids: tuple[int, ...]
    marker_chi: dict[int, float]
    fluoro_rms_px: float
    corner_rms_px: float
    reduced_chi2: float
    converged: bool
    chi2: float = float("nan")  # sum of the squared normalised residuals
    # ((view, (2,) pincushion and S shift at the field's corner, px), ...) of each intensifier view estimated.
    detector_distortion_px: tuple = ()
    # {marker id: (4, 2) px} where the solution projects each tag corner, those left out too.
    corner_projections_px: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    # {marker id: (k,) indices} of the tag corners left out as outliers (see :func:`joint_solve`).
    dropped_corners: dict[int, tuple[int, ...]] = field(default_factory=dict)


def perturb_about(delta: NDArray[np.float64], target_from_source: NDArray[np.float64], pivot_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Left-perturb a transform (4, 4) by ``delta`` (6,: rotation vector rad, translation mm) rotating about ``pivot_mm``."""
    r = Rotation.from_rotvec(delta[:3]).as_matrix()
    out = np.empty((4, 4))
    out[:3, :3] = r @ target_from_source[:3, :3]
    out[:3, 3] = r @ (target_from_source[:3, 3] - pivot_mm) + pivot_mm + delta[3:]
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _perturb_batch(deltas: NDArray[np.float64], poses: NDArray[np.float64], pivots: NDArray[np.float64]):
    """Rotations (M, 3, 3) and translations (M, 3) of M poses each perturbed about its pivot."""
    r = Rotation.from_rotvec(deltas[:, :3]).as_matrix()
    rot = r @ poses[:, :3, :3]
    t = np.einsum("mij,mj->mi", r, poses[:, :3, 3] - pivots) + pivots + deltas[:, 3:]
    return rot, t


def joint_solve(
    *,
    observations: dict[int, tuple],
    corners_px: dict[int, NDArray[np.float64]],
    marker_set: MarkerSet,
    camera: PinholeCamera,
    carm_from_drill0: NDArray[np.float64],
    carm_from_marker0: dict[int, NDArray[np.float64]],
    fluoro_sigma_px: float = 0.35,
    corner_sigma_px: float = CORNER_SIGMA_PX,
    focal_rel_sigma: float | None = None,
    principal_sigma_px: float | None = None,
    distortion_sigma: tuple[float, ...] | None = None,
    corner_common_per_sigma: float = CORNER_COMMON_PER_SIGMA,
    corner_scale_per_sigma: float = CORNER_SCALE_PER_SIGMA,
    bb_common_sigma_px: float = BB_COMMON_SIGMA_PX,
    bb_scale_sigma_px: float = BB_SCALE_SIGMA_PX,
    outlier_chi: float = 4.0,
    bb_outlier_chi: float = 5.0,
    min_markers: int = 3,
    crowded_bbs: bool = True,
    corner_extra_px: dict[int, float] | None = None,
    corner_slide_px: dict[int, NDArray[np.float64]] | None = None,
    fluoro_only: dict[int, tuple[tuple, NDArray[np.float64]]] | None = None,
    give_up_above_chi2: float | None = None,
    strokes: dict[int, tuple] | None = None,
    rolls: dict[int, tuple] | None = None,
    outlines: dict[int, tuple] | None = None,
    frame_shape_sigma_px: float = 0.0,
    refine: bool = True,
) -> JointSolution:
    """Solve all marker poses and ``carm_from_drill`` together.

    observations : {marker id: ((CArmView, design BB centres (N, 3) mm, detected centres (N, 2) px), ...)}.
    corners_px : {marker id: (4, 2) tag corners in the camera image, OpenCV order}.
    carm_from_marker0, carm_from_drill0 : the starting poses (each marker's on the right mirror side).
    Markers in both ``observations`` and ``corners_px`` are used; a marker whose RMS normalised residual
    exceeds ``outlier_chi`` (and three times the others' median) is rejected while ``min_markers`` remain;
    before that, single BBs farther than ``bb_outlier_chi`` sigmas from their projection are dropped, and a tag
    whose corners fit over ``outlier_chi`` sigmas RMS and 3 times the other tags' median, or whose marker stands
    out, is tried without each of its corners in turn: the one corner whose absence makes the tag fit is left
    out (``dropped_corners``) and the marker kept on the other three. When the worst marker still fits beyond
    ``outlier_chi`` and at least two remain, the one without which every other marker fits within it (when
    exactly one is such) is rejected, even below ``min_markers``; if a marker still fits beyond it at the end, the
    drill covariance is multiplied by ``reduced_chi2``.
    ``focal_rel_sigma``, ``principal_sigma_px``, ``distortion_sigma``: the camera priors; None (the default) takes
    what ``camera.uncertainty`` states, never under the defaults (``registration/camera_uncertainty.py``).
    ``corner_common_per_sigma``, ``corner_scale_per_sigma`` (in units of the corners' independent noise) and
    ``bb_common_sigma_px``, ``bb_scale_sigma_px``: the shift (per axis) and scale shared by a tag's four corners /
    by one marker's BBs in one view (see :data:`CORNER_COMMON_PER_SIGMA`); each group is whitened with them, so
    the estimate weighs the groups right and the covariance carries the shared part, which the residuals cannot
    show. ``crowded_bbs``: a BB whose shadow overlaps or nearly touches another's (:func:`_crowding`, at each
    round's starting poses) is charged its detector's pull as extra noise (:data:`CROWDED_BB_PX`); False charges
    it like any BB. ``corner_extra_px``: {marker id: px} extra independent noise of each of that tag's corners
    (a recovered tag's larger stated noise, what its four corners' misfit to a view of its square shows,
    :func:`square_misfit_noise_px`); absent: none. ``corner_slide_px``: {marker id: (4, 2) px} per corner of that tag, a
    direction in the image along which the corner may lie off, its length the noise (1 sigma) along it (a corner where
    the frame's edge cuts its tag's side lies somewhere on that side, :func:`.cut_corners.cut_corner_slides_px`);
    (0, 0): none.
    ``fluoro_only``: {marker id: (observations as above, starting ``carm_from_marker`` (4, 4))} of markers posed in
    fluoroscopy that the camera does not see. Where a view's intensifier distortion is estimated, their BBs join
    the solve with poses of their own (in no tag corner, no vote, not in ``used_ids``): more of the field shows
    the distortion. Elsewhere they add nothing and are left out.
    ``give_up_above_chi2``: when the first plain fit is not clean and its chi-square exceeds this, that fit is
    returned as it is, with no robust rounds, rejection or vote (a caller that only wants a solution fitting about as
    well as one it has: the mirror start of a single view, :func:`.video_fluoro._settle_constellation_mirror`).
    ``strokes``: {marker id: ((CArmView, anchors (K, 3) mm in the marker frame, normals (K, 2), offsets (K,) px,
    sigmas (K,) px), ...)}: where an edge-on marker's ring stroke lies across its line
    (:func:`.edge_on_ring.measure_ring_stroke`), each anchor's image along its normal, with its own noise; they count
    in no marker's chi, so they reject no marker.
    ``rolls``: {marker id: ((CArmView, near (3,) mm and far (3,) mm in the marker frame, normal (2,), apart px, sigma px), ...)}:
    where an edge-on marker's shadow shows it turned about its own line (:func:`.edge_on_roll.measure_ring_roll`),
    how far apart across the line the two points' images lie, with its own noise; like strokes, they reject no marker.
    ``outlines``: {marker id: ((CArmView, anchors (K, 3) mm in the marker frame, normals (K, 2), offsets (K,) px,
    sigmas (K,) px), ...)}: where an open ring's wire lies across its ellipse (:func:`.ring_outline.measure_ring_outline`),
    each anchor's image along its normal, with its own noise; each view's rows join that marker's BBs in the view (at
    least 3), whose shared shift and scale they share (``bb_common_sigma_px``, ``bb_scale_sigma_px``), and count in
    its chi.
    ``frame_shape_sigma_px``: the size (1 sigma, px at a tag's half-diagonal) of the four shape modes every tag of the
    frame shares (:func:`frame_corner_sigma_px`), which the covariance carries (not solved for); 0: none.
    ``refine`` False: the plain fit's solution at the starting poses as given, no step taken (its chi-square is how
    well those poses fit: a mirror image that the refinement would leave for the best solution).
    """
    ids = sorted(set(observations) & set(corners_px) & set(carm_from_marker0))
    if len(ids) < min_markers:
        raise MarkersNotFound(f"only {len(ids)} marker(s) seen by both the camera and fluoroscopy; at least {min_markers} are needed")
    rejected: list[int] = []
    drill0 = np.asarray(carm_from_drill0, dtype=np.float64)
    markers0 = {i: np.asarray(carm_from_marker0[i], dtype=np.float64) for i in ids}
    given = dict(markers0)  # the starting poses as given (each marker's own fluoroscopy pose), for the vote
    observations = {i: tuple(observations[i]) for i in ids}
    untrimmed = observations
    stated = camera_priors(camera.uncertainty)  # the calibration's statement, never under a typical calibration's error
    focal_rel_sigma = stated.focal_rel if focal_rel_sigma is None else focal_rel_sigma
    principal_sigma_px = stated.principal_px if principal_sigma_px is None else principal_sigma_px
    distortion_sigma = stated.distortion if distortion_sigma is None else distortion_sigma
    prior_sigma = np.array([focal_rel_sigma, principal_sigma_px, principal_sigma_px, *distortion_sigma], dtype=np.float64)
    if prior_sigma.shape != (N_INTRINSICS,) or not np.all(prior_sigma > 0):
        raise ValueError(f"the camera priors need focal, principal and 5 distortion sigmas, all > 0; got {prior_sigma.tolist()}")
    corner_common_sigma_px, corner_scale_sigma_px = corner_common_per_sigma * corner_sigma_px, corner_scale_per_sigma * corner_sigma_px
    if not (corner_common_sigma_px >= 0 and corner_scale_sigma_px >= 0 and bb_common_sigma_px >= 0 and bb_scale_sigma_px >= 0):
        raise ValueError(f"shared sigmas must be >= 0, got corner shift {corner_common_sigma_px}, corner scale {corner_scale_sigma_px}, "
                         f"BB shift {bb_common_sigma_px}, BB scale {bb_scale_sigma_px}")
    corner_extra = {i: float(v) for i, v in (corner_extra_px or {}).items() if v > 0}
    if not all(np.isfinite(v) for v in corner_extra.values()):
        raise ValueError(f"a tag's extra corner noise must be finite, got {corner_extra}")
    corner_slide = {i: np.asarray(v, dtype=np.float64).reshape(4, 2) for i, v in (corner_slide_px or {}).items()}
    if not all(np.all(np.isfinite(v)) for v in corner_slide.values()):
        raise ValueError(f"a tag's corner slides must be finite, got {corner_slide}")
    corner_slide = {i: v for i, v in corner_slide.items() if np.any(v != 0)}
    anchors = _distortion_anchors(fluoro_only or {}, ids, observations)
    frame_sigma = float(frame_shape_sigma_px)
    if not (np.isfinite(frame_sigma) and frame_sigma >= 0):
        raise ValueError(f"the frame's shared corner modes need a finite sigma >= 0 px, got {frame_shape_sigma_px}")
    args = (marker_set, camera, fluoro_sigma_px, corner_sigma_px, prior_sigma, corner_common_sigma_px, corner_scale_sigma_px, bb_common_sigma_px, bb_scale_sigma_px,
            crowded_bbs, corner_extra, corner_slide, anchors, dict(strokes or {}), dict(rolls or {}), dict(outlines or {}), frame_sigma)
    # Most shots are clean: one plain fit, accepted when no marker and no BB stands out.
    corners_px = {i: np.asarray(corners_px[i], dtype=np.float64).reshape(4, 2) for i in ids}
    sol = _solve(ids, observations, corners_px, drill0, markers0, *args, loss="linear", max_nfev=None if refine else 1)
    if not refine:
        return sol
    corner_min_px = outlier_chi * corner_sigma_px
    clean = max(sol.marker_chi.values()) <= outlier_chi and not _corner_suspects(sol, corners_px, ids, corner_min_px, corner_slide) and all(
        len(_trim(observations[i], sol.carm_from_marker[i], bb_outlier_chi * fluoro_sigma_px, sol.detector_distortion_px)[k][1]) == len(o[1])
        for i in ids for k, o in enumerate(observations[i]))
    if clean or (give_up_above_chi2 is not None and sol.chi2 > give_up_above_chi2):
        return sol
    trimmed = consensus_tried = False
    dropped: dict[int, tuple[int, ...]] = {}
    known: JointSolution | None = None  # the robust fit of this round's inputs, when the corner check already made it
    while True:
        # Judged on a robust fit (soft L1 beyond 3 sigma), so that one bad marker cannot drag the others
        # into disagreeing with their own data and hide among them.
        sol = known if known is not None else _solve(ids, observations, corners_px, drill0, markers0, *args, loss="soft_l1")
        known = None
        drill0, markers0 = sol.carm_from_drill, {i: sol.carm_from_marker[i] for i in ids}
        chi = sol.marker_chi
        # A corner a glove or a glare spot displaced spoils its whole tag (6-8 px of one corner move the axis by
        # over 1 mm at the entry while the marker's RMS, diluted by its BBs, still looks ordinary): before the
        # marker itself is judged, a tag whose corners stand out, or a marker that would be rejected, is tried on
        # three corners (once per marker). Nothing stands out where every marker fits badly (a mirror start).
        standing_out = [i for i in ids if _stands_out(chi, i, ids, outlier_chi)]
        suspects = [i for i in _corner_suspects(sol, corners_px, ids, corner_min_px, corner_slide) + sorted(standing_out, key=lambda i: -chi[i]) if i not in dropped]
        if suspects:
            i = suspects[0]
            dropped[i] = ()
            found, without = _corner_outlier(ids, observations, corners_px, drill0, markers0, args, i, min_px=corner_min_px, current=sol, slides=corner_slide)
            if found is not None:
                corners_px = {**corners_px, i: corners_px[i].copy()}
                corners_px[i][found] = np.nan
                dropped[i] = (found,)
            known = without if found is not None else sol  # the next round's inputs are those of the fit in hand
            continue
        worst = max(ids, key=lambda i: chi[i])
        if len(ids) > min_markers and _stands_out(chi, worst, ids, outlier_chi):
            rejected.append(worst)
            ids = [i for i in ids if i != worst]
            continue
        if not trimmed:
            # A BB merged with the K-wire or a neighbour's BB, or matched to the wrong design BB, spoils
            # its marker; drop such single BBs (once).
            trimmed = True
            kept = {i: _trim(observations[i], sol.carm_from_marker[i], bb_outlier_chi * fluoro_sigma_px, sol.detector_distortion_px) for i in ids}
            if sum(len(o[1]) for i in ids for o in kept[i]) < sum(len(o[1]) for i in ids for o in observations[i]):
                observations = kept
                continue
        if not consensus_tried and chi[worst] > outlier_chi and len(ids) >= 2:
            # The worst marker fits beyond its noise but the rule above cannot take it: it would leave fewer than
            # min_markers, or it dragged the others into misfitting with it, so it does not stand out 3 times
            # their median. The markers then vote (once): the one without which all the others fit within their
            # noise, when exactly one is, is rejected. With two markers the vote asks whether each fits alone:
            # one whose own BBs and tag fit no pose (its rings in two views disagree) goes; two that each fit
            # alone but not together stay, since neither can be told from the other.
            consensus_tried = True
            odd = _odd_one_out(ids, observations, corners_px, drill0, markers0, args, outlier_chi, given=given)
            if odd is not None:
                rejected.append(odd[0])
                ids = [i for i in ids if i != odd[0]]
                # The single BBs were trimmed against the fit it dragged: the others get theirs back, and are trimmed
                # anew; the next round starts from their fit without it, not where it dragged them.
                observations, trimmed = {i: untrimmed[i] for i in ids}, False
                known = _solve(ids, observations, corners_px, odd[1].carm_from_drill, odd[1].carm_from_marker, *args, loss="soft_l1")
                continue
        break
    # The final fit is plain least squares: its Jacobian gives the covariance.
    sol = _solve(ids, observations, corners_px, drill0, markers0, *args, loss="linear")
    covariance = sol.covariance_drill
    if max(sol.marker_chi.values()) > outlier_chi:
        # A marker still fits far beyond its noise: one the rejection could not take (no marker may go below
        # ``min_markers``), or one that dragged the others into misfitting with it. The residuals call this
        # solution wrong, so its covariance takes the whole fit's a-posteriori variance factor (its reduced
        # chi-square): the bound says so, and the axis is flagged unreliable rather than confidently off.
        covariance = covariance * max(1.0, sol.reduced_chi2)
    return JointSolution(**{**sol.__dict__, "covariance_drill": covariance, "rejected_ids": tuple(rejected),
                            "dropped_corners": {i: k for i, k in dropped.items() if i in ids and k}})


def _odd_one_out(ids, observations, corners_px, drill0, markers0, args, outlier_chi: float, *,
                 given: dict[int, NDArray[np.float64]]) -> tuple[int, JointSolution] | None:
    """The marker without which every other marker fits within its noise (RMS normalised residual at most
    ``outlier_chi``), when exactly one marker is such, with the others' fit without it; None otherwise. One robust
    fit (soft L1) per marker left out, from ``drill0``, ``markers0``, and also from the markers' given starts
    ``given`` (their fluoroscopy poses) with the drill a tag puts there, since the joint fit may have dragged them far."""
    clean: list[tuple[int, JointSolution]] = []
    for i in ids:
        rest = [j for j in ids if j != i]
        starts = [(drill0, markers0)]
        for j in rest:
            # The markers' given poses with the drill a tag puts there (the first whose corners all stand): the fit
            # in hand may have been dragged far.
            drill = _drill_from_tag(given[j], corners_px[j], marker_set=args[0], camera=args[1], marker_id=j)
            if drill is not None:
                starts.append((drill, {**markers0, **{k: given[k] for k in rest}}))
                break
        for drill, markers in starts:
            try:
                sol = _solve(rest, observations, corners_px, drill, markers, *args, loss="soft_l1")
            except (np.linalg.LinAlgError, ValueError):
                continue
            if max(sol.marker_chi.values()) <= outlier_chi:
                clean.append((i, sol))
                break
    return clean[0] if len(clean) == 1 else None


def _drill_from_tag(carm_from_marker: NDArray[np.float64], corners_px: NDArray[np.float64], *, marker_set: MarkerSet, camera: PinholeCamera,
                    marker_id: int) -> NDArray[np.float64] | None:
    """``carm_from_drill`` (4, 4) that puts the marker's tag, at ``carm_from_marker`` (4, 4), on its corners (4, 2) px
    (planar PnP, the better of its two solutions); None when a corner was left out."""
    corners = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    if not np.all(np.isfinite(corners)):
        return None
    design = marker_set.by_id(marker_id)
    _, rvecs, tvecs, errs = cv2.solvePnPGeneric(tag_object_points(design.tag_size_mm), corners, camera.camera_matrix, camera.distortion,
                                                flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not len(rvecs):
        return None
    best = int(np.argmin(np.asarray(errs).ravel()))
    camera_from_tag = make_transform(cv2.Rodrigues(rvecs[best])[0], tvecs[best].ravel())
    return carm_from_marker @ invert(drill_from_marker(camera_from_tag, design.tag_center_mm))


def _stands_out(chi: dict[int, float], marker_id: int, ids, outlier_chi: float) -> bool:
    """Whether a marker's RMS normalised residual is over ``outlier_chi`` and 3 times the other markers' median."""
    return chi[marker_id] > outlier_chi and chi[marker_id] > 3.0 * float(np.median([chi[j] for j in ids if j != marker_id] or [0.0]))


def _corner_errors_px(sol: JointSolution, corners_px, slides: dict[int, NDArray[np.float64]]) -> dict[int, NDArray[np.float64]]:
    """{marker id: (4,) px} each tag corner's distance from its projection, NaN for a corner left out; across its
    slide (``corner_slide_px``) where it has one (along it the corner is not measured)."""
    return {i: np.linalg.norm(across_slides(p - corners_px[i], slides[i]) if i in slides else p - corners_px[i], axis=1)
            for i, p in sol.corner_projections_px.items()}


def _corner_suspects(sol: JointSolution, corners_px, ids, min_px: float, slides: dict[int, NDArray[np.float64]]) -> list[int]:
    """Markers whose tag corners fit worse than ``min_px`` RMS and 3 times the other tags' median, worst first."""
    rms = {i: float(np.sqrt(np.nanmean(e**2))) for i, e in _corner_errors_px(sol, corners_px, slides).items()}
    out = [i for i in ids if rms[i] > min_px and rms[i] > 3.0 * float(np.median([rms[j] for j in ids if j != i] or [0.0]))]
    return sorted(out, key=lambda i: -rms[i])


def _corner_outlier(ids, observations, corners_px, drill0, markers0, args, marker_id: int, *, min_px: float,
                    current: JointSolution, slides: dict[int, NDArray[np.float64]]) -> tuple[int | None, JointSolution | None]:
    """The index of the one corner of ``marker_id``'s tag that, left out, makes the tag fit, and the robust fit
    without it (from ``drill0``, ``markers0``); (None, None) if none does. ``current``: the robust fit with every corner.

    The two corners farthest from their projection in ``current`` are each left out in turn (robust fit). The
    floor is ``min_px`` or 3 times the other tags' median corner error, whichever is larger (blur and compression
    scatter every corner). A corner is named when, without it, each remaining corner of the tag is within the
    floor, it is itself over 3 floors from where the solution projects it, and the chi-square is under half of
    that without the other corner tried. A corner displaced
    by a glove or a glare spot, then; not one of a blurred tag's corners, nor a tag that is off as a whole (the
    marker's own test).
    """
    chi2: dict[int, float] = {}
    fits: set[int] = set()
    fitted: dict[int, JointSolution] = {}
    # The two corners farthest from where the solution puts them: a displaced corner is the farthest (the tag's
    # pose, held by its marker's BBs, cannot follow it), and the second's fit without it is the contrast the
    # chi-square test needs (any other corner left out keeps the displaced one in). Two solves, not four.
    off = _corner_errors_px(current, corners_px, slides)[marker_id]
    for k in [int(j) for j in np.argsort(-np.where(np.isfinite(off), off, -np.inf))[:2]]:
        if not np.isfinite(corners_px[marker_id][k]).all():
            continue
        trial = {**corners_px, marker_id: corners_px[marker_id].copy()}
        trial[marker_id][k] = np.nan
        try:
            sol = _solve(ids, observations, trial, drill0, markers0, *args, loss="soft_l1")
        except (np.linalg.LinAlgError, ValueError):
            continue
        chi2[k], fitted[k] = sol.chi2, sol
        errors = _corner_errors_px(sol, trial, slides)
        others = [e for i, e in errors.items() if i != marker_id]
        floor = max(min_px, 3.0 * float(np.nanmedian(np.concatenate(others)))) if others else min_px
        left_out = float(_corner_errors_px(sol, corners_px, slides)[marker_id][k])
        if np.nanmax(errors[marker_id]) <= floor and left_out > 3.0 * floor:
            fits.add(k)
    if len(chi2) < 2:
        return None, None
    best, second = sorted(chi2, key=chi2.get)[:2]
    # One corner, not any: without it the fit is far better than without any other corner. A tag off as a whole
    # (its marker's BBs shifted in a single view, where depth is loose) fits about as well without any one.
    return (best, fitted[best]) if best in fits and chi2[best] < 0.5 * chi2[second] else (None, None)


def _noise_scales(jac: NDArray[np.float64], res: NDArray[np.float64], groups: tuple[NDArray[np.int64], ...], *, min_scale: float = 0.5,
                  min_dof: float = 4.0) -> NDArray[np.float64]:
    """Per-row factor (R,) by which each group's assumed noise is off: sqrt(chi-square / redundancy) of the group.

    groups: the row indices of each group. Variance components: a group's redundancy is the sum of its rows' 1 - leverage (its share of the fit's
    degrees of freedom). Rows outside the groups (priors) keep 1; a group with less than ``min_dof`` of
    redundancy keeps 1 (too few to estimate); the factor is at least ``min_scale`` (a few residuals that
    happen to be small must not shrink the bound to nothing).
    """
    scales = np.ones(len(res))
    cov0 = np.linalg.pinv(jac.T @ jac)
    leverage = np.einsum("ij,jk,ik->i", jac, cov0, jac)
    for g in groups:
        dof = float(np.sum(1.0 - leverage[g]))
        if dof >= min_dof:
            scales[g] = max(min_scale, float(np.sqrt(np.sum(res[g] ** 2) / dof)))
    return scales


def _distortion_change(xy: NDArray[np.float64], dk: NDArray[np.float64]) -> NDArray[np.float64]:
    """Change (P, N, 2) of the distorted normalised coordinates of ``xy`` (P, N, 2) when the distortion
    coefficients change by ``dk`` (P, 5: k1, k2, p1, p2, k3); the model is linear in them."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    k1, k2, p1, p2, k3 = (dk[:, j : j + 1] for j in range(5))
    radial = r2 * (k1 + r2 * (k2 + r2 * k3))
    return np.stack([x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y], axis=-1)


def _distorted_views(ids, observations) -> list:
    """The distinct views (in order of first use) whose detector distortion the solve estimates."""
    views: list = []
    for i in ids:
        for view, _, _ in observations[i]:
            if getattr(view, "distortion_sigma_px", 0.0) > 0 and not any(v is view for v in views):
                views.append(view)
    return views


def _distortion_anchors(fluoro_only: dict, ids, observations) -> dict[int, tuple[tuple, NDArray[np.float64]]]:
    """Of ``fluoro_only``, the markers not in ``ids`` seen (by 3 or more BBs) in two or more of the views whose
    distortion the solve estimates, each with only those views' observations. In one view a marker's own pose
    takes up the distortion's shift there; two views' rays must meet, which the shift would stop."""
    dist_views = _distorted_views(ids, observations)
    out = {}
    for i, (obs, pose) in sorted(fluoro_only.items()):
        if i in ids:
            continue
        kept = tuple(o for o in obs if any(o[0] is v for v in dist_views) and len(o[1]) >= 3)
        if len({id(o[0]) for o in kept}) >= 2:
            out[i] = (kept, np.asarray(pose, dtype=np.float64))
    return out


def project_distorted(view, points_carm_mm: NDArray[np.float64], distortion: tuple = ()) -> NDArray[np.float64]:
    """Pixels (N, 2) of points (N, 3) in ``view``, moved by the view's estimated intensifier distortion if any."""
    uv = view.project(points_carm_mm)
    coef = next((c for v, c in distortion if v is view), None)
    return view.distorted_px(uv, coef)


# Points on a marker's ring at which its shadow's distance from the BBs is taken (1.3 deg apart: 0.6 mm on a 24 mm ring).
RING_CROWDING_POINTS = 256


def _crowding(observations: dict, carm_from_marker: dict, marker_set: MarkerSet) -> dict[int, tuple[NDArray[np.float64], ...]]:
    """{marker id: per observation (view), (N,) each observed BB's crowding}: the distance from its projection to
    the nearest other BB's (of any marker solved, observed or not) over the sum of their projected radii, or to its
    own marker's ring over its projected radius plus the wire's, whichever is smaller.

    Under about 1 the two BBs' shadows overlap or touch, and a blob detector returns them merged or each pulled
    towards the other: a biased centre, not noise (a marker seen steeply in a lateral view lays its BBs close). Its
    ring seen near edge-on runs past the BBs a few pixels off and pulls them alike (twin seed 10900, markers flat: a
    lateral BB 1.65 px off its true image, 3.8-11 px from the wire, turned two markers 1 deg).
    """
    ids = list(observations)
    designs = {i: marker_set.by_id(i) for i in ids}
    in_c = {i: apply(carm_from_marker[i], designs[i].bb_centers_mm) for i in ids}
    starts = np.cumsum([0] + [len(in_c[i]) for i in ids])
    every_c = np.concatenate([in_c[i] for i in ids])
    every_r = 0.5 * np.concatenate([designs[i].bb_diameters_mm for i in ids])
    per_view: dict[int, tuple] = {}
    out = {}
    for k, i in enumerate(ids):
        rows = []
        design_pts = designs[i].bb_centers_mm
        for view, obj, _ in observations[i]:
            if id(view) not in per_view:
                intrinsics, source_from_carm = view.decompose()
                depth = every_c @ source_from_carm[2, :3] + source_from_carm[2, 3]
                centres = view.project(every_c)
                radii = every_r * intrinsics[0, 0] / depth
                near = np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=2) / (radii[:, None] + radii[None, :])
                np.fill_diagonal(near, np.inf)
                crowd = near.min(axis=1)
                # The marker's own ring: seen near edge-on its wire's shadow runs past the BBs and pulls them as a BB's does.
                for m, j in enumerate(ids):
                    ring = apply(carm_from_marker[j], designs[j].ring_points_mm(RING_CROWDING_POINTS))
                    ring_px = view.project(ring)
                    wire = 0.5 * designs[j].ring_wire_diameter_mm * intrinsics[0, 0] / (ring @ source_from_carm[2, :3] + source_from_carm[2, 3])
                    rows_j = slice(starts[m], starts[m + 1])
                    d = np.linalg.norm(centres[rows_j, None, :] - ring_px[None, :, :], axis=2) / (radii[rows_j, None] + wire[None, :])
                    crowd[rows_j] = np.minimum(crowd[rows_j], d.min(axis=1))
                per_view[id(view)] = crowd
            # Each observed BB is one of the design's (the rows of ``obj`` are design centres).
            index = np.argmin(np.linalg.norm(np.asarray(obj, dtype=np.float64)[:, None, :] - design_pts[None, :, :], axis=2), axis=1)
            rows.append(per_view[id(view)][starts[k] + index])
        out[i] = tuple(rows)
    return out


def crowded_bb_sigma_px(ratio: NDArray[np.float64]) -> NDArray[np.float64]:
    """The extra noise (px, 1 sigma) of a BB's detected centre at a crowding ``ratio`` (:func:`_crowding`): the
    detector's pull towards a neighbour's shadow, measured on the operating-room twin (``CROWDED_BB_PX``)."""
    r, px = CROWDED_BB_PX
    return np.interp(np.asarray(ratio, dtype=np.float64), r, px, left=px[0], right=0.0)


def _trim(observations, carm_from_marker, max_px: float, distortion: tuple = ()) -> tuple:
    """The observations without BBs farther than ``max_px`` from their projection (at least 3 kept per view)."""
    out = []
    for view, obj, img in observations:
        err = np.linalg.norm(project_distorted(view, apply(carm_from_marker, obj), distortion) - img, axis=1)
        keep = err <= max_px
        if keep.sum() < 3:
            keep = err <= np.sort(err)[min(2, len(err) - 1)]
        out.append((view, np.asarray(obj)[keep], np.asarray(img)[keep]))
    return tuple(out)


def _whitening_with_outlines(groups_px: list[NDArray[np.float64]], extra_px: list[NDArray[np.float64]] | None, outline_px: dict,
                             sigma_px: float, shift_px: float, scale_px: float) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Whitening of the BB groups (:func:`_group_whitening`) with ring outline rows joined to some of them.

    ``groups_px``: each group's BB images (N, 2); ``extra_px``: per group (N,) extra noise or None; ``outline_px``:
    {group index: (anchor images (K, 2) px, normals (K, 2), sigmas (K,) px)}. The vector whitened is every group's BB
    coordinates in group order (x0, y0, x1, ...), then every outline row in group order. An outline row errs by its
    own sigma, by the group's shared shift along its normal, and by the group's shared scale (about the BBs' centre,
    ``scale_px`` at their mean radius) along its normal: a group with outline rows is whitened by the inverse
    Cholesky factor of that covariance (noise 1 per row). Returns ``W`` (R, R), the noise (R,) of each row of
    ``W @ e``, and each row's group (R,); the rows come group by group.
    """
    pts_all = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in groups_px]
    n_bb = 2 * sum(len(p) for p in pts_all)
    size = n_bb + sum(len(v[2]) for v in outline_px.values())
    w = np.zeros((size, size))
    noise: list[float] = []
    row_group: list[int] = []
    r, cb, co = 0, 0, n_bb
    for g, pts in enumerate(pts_all):
        n = len(pts)
        cols = list(range(cb, cb + 2 * n))
        cb += 2 * n
        extra = None if extra_px is None else np.asarray(extra_px[g], dtype=np.float64).reshape(-1)
        if g not in outline_px:
            block, nz, _ = _group_whitening([pts], sigma_px, shift_px, scale_px, None if extra is None else [extra])
        else:
            a_px, nrm, sg = (np.asarray(v, dtype=np.float64) for v in outline_px[g])
            k = len(sg)
            cols += list(range(co, co + k))
            co += k
            centre = pts.mean(axis=0)
            ex = np.zeros(n) if extra is None else extra
            ux = np.concatenate([np.tile([1.0, 0.0], n), nrm[:, 0]])
            uy = np.concatenate([np.tile([0.0, 1.0], n), nrm[:, 1]])
            cov = np.diag(np.concatenate([sigma_px**2 + np.repeat(ex**2, 2), sg**2])) + shift_px**2 * (np.outer(ux, ux) + np.outer(uy, uy))
            radius = float(np.mean(np.linalg.norm(pts - centre, axis=1)))
            if n >= 3 and radius > 0:
                rel = np.concatenate([(pts - centre).ravel(), np.sum(nrm * (a_px - centre), axis=1)])
                cov += (scale_px / radius) ** 2 * np.outer(rel, rel)
            block, nz = np.linalg.inv(np.linalg.cholesky(cov)), np.ones(2 * n + k)
        w[r : r + len(cols), cols] = block
        noise += list(nz)
        row_group += [g] * len(cols)
        r += len(cols)
    return w, np.asarray(noise), np.asarray(row_group, dtype=np.int64)


def _group_whitening(groups_px: list[NDArray[np.float64]], sigma_px: float, shift_px: float, scale_px: float,
                     extra_px: list[NDArray[np.float64]] | None = None,
                     slide_px: list[NDArray[np.float64]] | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Whitening of groups of image points whose errors share a shift and a scale within each group.

    groups_px : each group's image points (N, 2), in row order (rows x0, y0, x1, y1, ...). A group's 2N errors
    have covariance sigma^2 I + shift^2 (per image axis, all N points together) + scale^2 (every point moved
    along its radius from the group's centre, by ``scale_px`` at the mean radius; groups of 3 or more points).
    Returns ``W`` (2N, 2N in all, block diagonal and orthonormal: per group its shared modes first, then an
    orthonormal complement), the noise (2N,) of each row of ``W @ e`` and which rows are shared modes.
    ``(W @ e) / noise`` are independent unit-variance residuals with the same sum of squares as the Cholesky
    whitening of the group's covariance, each group's rows still depending on its own marker alone.
    ``extra_px``: per group, (N,) extra independent noise of each point (0: none); a group with any is whitened by
    the inverse Cholesky factor of its covariance (its rows' noise 1, none of them a shared mode).
    ``slide_px``: per group, (N, 2) a direction of each point's extra noise, its length that noise's sigma (adds
    ``v v^T`` to the point's 2x2 block; (0, 0): none); a group with any is whitened like one with extra noise.
    """
    blocks, noise, shared = [], [], []
    for g, pts in enumerate(groups_px):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        n = len(pts)
        extra = np.zeros(n) if extra_px is None else np.asarray(extra_px[g], dtype=np.float64).reshape(-1)
        slide = np.zeros((n, 2)) if slide_px is None else np.asarray(slide_px[g], dtype=np.float64).reshape(n, 2)
        if np.any(extra > 0) or np.any(slide != 0):
            rel = (pts - pts.mean(axis=0)).ravel()
            radius = float(np.mean(np.linalg.norm(rel.reshape(-1, 2), axis=1)))
            ux, uy = np.tile([1.0, 0.0], n), np.tile([0.0, 1.0], n)
            cov = np.diag(sigma_px**2 + np.repeat(extra**2, 2)) + shift_px**2 * (np.outer(ux, ux) + np.outer(uy, uy))
            cov += block_diag(*[np.outer(v, v) for v in slide])
            if n >= 3 and radius > 0:
                cov += (scale_px / radius) ** 2 * np.outer(rel, rel)
            blocks.append(np.linalg.inv(np.linalg.cholesky(cov)))
            noise += [1.0] * (2 * n)
            shared += [False] * (2 * n)
            continue
        modes = [np.tile([1.0, 0.0], n) / np.sqrt(n), np.tile([0.0, 1.0], n) / np.sqrt(n)]
        var = [sigma_px**2 + n * shift_px**2] * 2
        rel = (pts - pts.mean(axis=0)).ravel()
        radius = float(np.mean(np.linalg.norm(rel.reshape(-1, 2), axis=1)))
        if n >= 3 and radius > 0:
            norm = float(np.linalg.norm(rel))
            modes.append(rel / norm)
            var.append(sigma_px**2 + (scale_px * norm / radius) ** 2)  # scale s at the mean radius: s |rel| / radius on the mode
        m = np.stack(modes, axis=1)
        q = np.linalg.qr(m, mode="complete")[0]
        q[:, : m.shape[1]] = m  # the shared modes themselves (already orthonormal), not QR's signs
        blocks.append(q.T)
        noise += [np.sqrt(v) for v in var] + [sigma_px] * (2 * n - len(var))
        shared += [True] * len(var) + [False] * (2 * n - len(var))
    return block_diag(*blocks), np.asarray(noise), np.asarray(shared)


def _solve(ids, observations, corners_px, drill0, markers0, marker_set, camera,
           fluoro_sigma_px, corner_sigma_px, prior_sigma, corner_common_px, corner_scale_px, bb_common_px, bb_scale_px, crowding: bool,
           corner_extra: dict[int, float], corner_slide: dict[int, NDArray[np.float64]], anchors: dict, strokes: dict, rolls: dict, outlines: dict,
           frame_sigma_px: float = 0.0, *, loss: str, max_nfev: int | None = None) -> JointSolution:
    # The markers the camera sees (``ids``, m of them, first) and the fluoroscopy-only ones (``anchors``): every
    # one has a pose; only the first m have tag corners.
    m = len(ids)
    aids = [i for i in sorted(anchors) if i not in ids]
    every_id = list(ids) + aids
    ma = len(every_id)
    if aids:
        observations = {**{i: anchors[i][0] for i in aids}, **observations}
        markers0 = {**{i: anchors[i][1] for i in aids}, **markers0}
    poses0 = np.stack([markers0[i] for i in every_id])
    pivots = poses0[:, :3, 3].copy()
    pivot_d = pivots[:m].mean(axis=0)  # the seen markers' centroid
    # Fluoroscopy rows: one block per (marker, view), projected with the view's 3x4 matrix.
    f_obj, f_img, f_marker, f_p, f_keys = [], [], [], [], []
    for k, i in enumerate(every_id):
        for view, obj, img in observations[i]:
            f_keys.append((k, view))
            f_obj.append(np.asarray(obj, dtype=np.float64))
            f_img.append(np.asarray(img, dtype=np.float64))
            f_marker.append(np.full(len(obj), k))
            f_p.append(np.repeat(view.projection_matrix[None], len(obj), axis=0))
    f_obj_a, f_img_a, f_mk, f_pa = np.concatenate(f_obj), np.concatenate(f_img), np.concatenate(f_marker), np.concatenate(f_p)
    # An image intensifier's view (distortion_sigma_px > 0) gets its own distortion (pincushion, S: 2 px
    # coefficients at the field's corner) held by a prior of that size: the camera's constellation of markers,
    # known in 3D, shows it (markers at different radii magnified differently), and the covariance carries
    # what it does not show. A flat panel's view adds nothing.
    dist_views = _distorted_views(ids, observations)
    n_dv = len(dist_views)
    f_dv = np.concatenate([np.full(len(obj), next((j for j, v in enumerate(dist_views) if v is view), -1))
                           for i in every_id for view, obj, _ in observations[i]])
    f_center = np.concatenate([np.repeat(view.center_px[None], len(obj), axis=0) for i in every_id for view, obj, _ in observations[i]])
    f_corner_r = np.concatenate([np.full(len(obj), view.corner_radius_px) for i in every_id for view, obj, _ in observations[i]])
    dist_sigma = np.repeat([v.distortion_sigma_px for v in dist_views], 2).astype(np.float64)
    barrel_sigma = dist_sigma * BARREL_SHARE  # (BARREL_SHARE)
    is_pincushion = np.tile([True, False], n_dv)  # of each view's two coefficients, the radial one
    f_has = f_dv >= 0
    # A BB crowded by another's shadow (at the starting poses, which the robust rounds bring to the solution) is
    # charged its detector's pull (CROWDED_BB_PX).
    extra = None
    if crowding:
        ratios = _crowding({i: observations[i] for i in every_id}, markers0, marker_set)
        extra = [crowded_bb_sigma_px(r) for i in every_id for r in ratios[i]]
    # Open rings' outlines (the camera's markers only), each view's rows joined to the marker's BBs there.
    o_rows = {}
    for k, i in enumerate(ids):
        for view, a, nv, o, sg in outlines.get(i, ()):
            g = next((j for j, (kk, v) in enumerate(f_keys) if kk == k and v is view), None)
            if g is not None and len(f_img[g]) >= 3:
                a = np.asarray(a, dtype=np.float64).reshape(-1, 3)
                o_rows[g] = (a, np.asarray(nv, dtype=np.float64).reshape(-1, 2), np.asarray(o, dtype=np.float64).reshape(-1),
                             np.asarray(sg, dtype=np.float64).reshape(-1), view.project(apply(markers0[i], a)))
    n_o = sum(len(r[2]) for r in o_rows.values())
    if n_o:
        o_sigma = np.concatenate([o_rows[g][3] for g in sorted(o_rows)])
        if len(o_sigma) != n_o or not np.all(o_sigma > 0) or not np.all(np.isfinite(o_sigma)):
            raise ValueError(f"each outline row needs one finite sigma > 0 px, got {o_sigma}")
        o_obj = np.concatenate([o_rows[g][0] for g in sorted(o_rows)])
        o_nrm = np.concatenate([o_rows[g][1] for g in sorted(o_rows)])
        o_off = np.concatenate([o_rows[g][2] for g in sorted(o_rows)])
        o_mk = np.concatenate([np.full(len(o_rows[g][2]), f_keys[g][0]) for g in sorted(o_rows)])
        o_views = [f_keys[g][1] for g in sorted(o_rows) for _ in range(len(o_rows[g][2]))]
        o_pa = np.stack([v.projection_matrix for v in o_views])
        o_dv = np.array([next((j for j, dv in enumerate(dist_views) if dv is v), -1) for v in o_views])
        o_center = np.stack([v.center_px for v in o_views])
        o_corner_r = np.array([v.corner_radius_px for v in o_views])
        o_has = o_dv >= 0
        wf, f_noise, f_row_group = _whitening_with_outlines(f_img, extra, {g: (r[4], r[1], r[3]) for g, r in o_rows.items()}, fluoro_sigma_px,
                                                            bb_common_px, bb_scale_px)
        f_row_mk = np.array([f_keys[g][0] for g in f_row_group], dtype=np.int64)
        wf_sparse = csr_matrix(wf)
    else:
        wf, f_noise, _ = _group_whitening(f_img, fluoro_sigma_px, bb_common_px, bb_scale_px, extra)
        f_row_mk = np.repeat(f_mk, 2)
    # A corner left out as an outlier is NaN in ``corners_px``: its tag is whitened over the corners it keeps.
    c_keep = [np.all(np.isfinite(np.asarray(corners_px[i], dtype=np.float64).reshape(4, 2)), axis=1) for i in ids]
    c_sel = np.nonzero(np.concatenate(c_keep))[0]  # of every tag's four corners, those used
    c_obj_all = np.concatenate([marker_set.by_id(i).tag_corners_mm() for i in ids])
    c_mk_all = np.repeat(np.arange(m), 4)
    c_groups = [np.asarray(corners_px[i], dtype=np.float64).reshape(4, 2)[keep] for i, keep in zip(ids, c_keep)]
    c_obj, c_img, c_mk = c_obj_all[c_sel], np.concatenate(c_groups), c_mk_all[c_sel]
    c_extra = [np.full(int(keep.sum()), corner_extra.get(i, 0.0)) for i, keep in zip(ids, c_keep)] if any(i in corner_extra for i in ids) else None
    c_slide = [corner_slide[i][keep] if i in corner_slide else np.zeros((int(keep.sum()), 2)) for i, keep in zip(ids, c_keep)] if any(i in corner_slide for i in ids) else None
    wc, c_noise, _ = _group_whitening(c_groups, corner_sigma_px, corner_common_px, corner_scale_px, c_extra, c_slide)
    # The frame's shared shape modes (FRAME_CORNER_PER_EDGE_SIGMA) at each observed corner, (N, 2, 4).
    c_modes = frame_shape_modes(c_groups)
    # Ring strokes of edge-on markers (the camera's markers only): one row each, an anchor's image along a normal.
    s_rows = [(k, view, np.asarray(a, dtype=np.float64).reshape(-1, 3), np.asarray(nv, dtype=np.float64).reshape(-1, 2), np.asarray(o, dtype=np.float64).reshape(-1),
               np.asarray(sg, dtype=np.float64).reshape(-1))
              for k, i in enumerate(ids) for view, a, nv, o, sg in strokes.get(i, ())]
    n_s = sum(len(r[4]) for r in s_rows)
    if n_s:
        s_sigma = np.concatenate([r[5] for r in s_rows])
        if len(s_sigma) != n_s or not np.all(s_sigma > 0) or not np.all(np.isfinite(s_sigma)):
            raise ValueError(f"each stroke needs one finite sigma > 0 px, got {s_sigma}")
        s_obj = np.concatenate([r[2] for r in s_rows])
        s_nrm = np.concatenate([r[3] for r in s_rows])
        s_off = np.concatenate([r[4] for r in s_rows])
        s_mk = np.concatenate([np.full(len(r[4]), r[0]) for r in s_rows])
        s_pa = np.concatenate([np.repeat(r[1].projection_matrix[None], len(r[4]), axis=0) for r in s_rows])
        s_dv = np.concatenate([np.full(len(r[4]), next((j for j, v in enumerate(dist_views) if v is r[1]), -1)) for r in s_rows])
        s_center = np.concatenate([np.repeat(r[1].center_px[None], len(r[4]), axis=0) for r in s_rows])
        s_corner_r = np.concatenate([np.full(len(r[4]), r[1].corner_radius_px) for r in s_rows])
        s_has = s_dv >= 0
    else:
        s_mk = np.zeros(0, dtype=np.int64)
    # Rolls of edge-on markers (the camera's markers only): one row each, two points' images apart along a normal. The
    # two image a few pixels apart, so an intensifier's distortion, the same at both, is left out.
    r_rows = [(k, view, np.stack([np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)]), np.asarray(nv, dtype=np.float64), float(d), float(sg))
              for k, i in enumerate(ids) for view, a, b, nv, d, sg in rolls.get(i, ())]
    n_r = len(r_rows)
    if n_r:
        if not all(r[5] > 0 and np.isfinite(r[4]) for r in r_rows):
            raise ValueError(f"a roll needs a finite separation and a sigma > 0 px, got {[(r[4], r[5]) for r in r_rows]}")
        r_obj = np.concatenate([r[2] for r in r_rows])  # (2 R, 3): near, far of each
        r_mk = np.array([r[0] for r in r_rows], dtype=np.int64)
        r_pa = np.repeat(np.stack([r[1].projection_matrix for r in r_rows]), 2, axis=0)
        r_nrm = np.stack([r[3] for r in r_rows])
        r_apart = np.array([r[4] for r in r_rows])
        r_sigma = np.array([r[5] for r in r_rows])
    else:
        r_mk = np.zeros(0, dtype=np.int64)
    k0 = camera.camera_matrix
    fx0, fy0, cx0, cy0 = k0[0, 0], k0[1, 1], k0[0, 2], k0[1, 2]
    n_f, n_c = len(f_noise), 2 * len(c_obj)
    n_par = 6 + 6 * ma + N_INTRINSICS + 2 * n_dv
    i_dist = 6 + 6 * ma + N_INTRINSICS

    def residuals(xs, every_corner: bool = False):
        """Normalised residuals (P, R) of P parameter vectors (P, n_par) at once; ``every_corner``: the
        projections (P, 4 m, 2) of every tag corner instead, those left out too."""
        n = xs.shape[0]
        rd = Rotation.from_rotvec(xs[:, :3]).as_matrix()  # (P, 3, 3)
        rot_d = rd @ drill0[:3, :3]
        t_d = np.einsum("pij,j->pi", rd, drill0[:3, 3] - pivot_d) + pivot_d + xs[:, 3:6]
        dm = xs[:, 6 : 6 + 6 * ma].reshape(n, ma, 6)
        rm = Rotation.from_rotvec(dm[..., :3].reshape(-1, 3)).as_matrix().reshape(n, ma, 3, 3)
        rot_m = rm @ poses0[None, :, :3, :3]
        t_m = np.einsum("pmij,mj->pmi", rm, poses0[:, :3, 3] - pivots) + pivots + dm[..., 3:]
        pc = np.einsum("pnij,nj->pni", rot_m[:, f_mk], f_obj_a) + t_m[:, f_mk]
        h = np.einsum("nij,pnj->pni", f_pa[:, :, :3], pc) + f_pa[:, :, 3]
        uv = h[..., :2] / h[..., 2:3]
        if n_dv:
            coef = xs[:, i_dist:].reshape(n, n_dv, 2)[:, f_dv[f_has]]
            uv[:, f_has] += intensifier_shift_px(uv[:, f_has], f_center[f_has], f_corner_r[f_has][:, None], coef)
        raw = (uv - f_img_a).reshape(n, -1)
        if n_o:
            # Block diagonal up to the rows' order: applied as a sparse matrix.
            rf = (wf_sparse @ np.concatenate([raw, outline_rows(xs, rot_m, t_m)], axis=1).T).T / f_noise
        else:
            rf = np.einsum("ij,pj->pi", wf, raw) / f_noise
        obj, mk = (c_obj_all, c_mk_all) if every_corner else (c_obj, c_mk)
        cc = np.einsum("pnij,nj->pni", rot_m[:, mk], obj) + t_m[:, mk]
        cd = np.einsum("pji,pnj->pni", rot_d, cc - t_d[:, None])  # drill_from_carm applied
        xy0 = cd[..., :2] / cd[..., 2:3]
        intr = xs[:, 6 + 6 * ma : i_dist]
        xy = camera.distort_normalized(xy0.reshape(-1, 2)).reshape(n, -1, 2) + _distortion_change(xy0, intr[:, 3:])
        s = 1.0 + intr[:, :1]
        u = fx0 * s * xy[..., 0] + k0[0, 1] * xy[..., 1] + cx0 + intr[:, 1:2]
        v = fy0 * s * xy[..., 1] + cy0 + intr[:, 2:3]
        if every_corner:
            return np.stack([u, v], axis=-1)
        rc = np.einsum("ij,pj->pi", wc, (np.stack([u, v], axis=-1) - c_img).reshape(n, -1)) / c_noise
        if n_dv:
            dk = xs[:, i_dist:]
            prior = np.concatenate([intr / prior_sigma, dk / np.where(is_pincushion & (dk < 0.0), barrel_sigma, dist_sigma)], axis=1)
        else:
            prior = intr / prior_sigma
        rest = [rf.reshape(n, -1), rc.reshape(n, -1)]
        if n_s:
            rest.append(stroke_rows(xs, rot_m, t_m))
        if n_r:
            pr = np.einsum("pnij,nj->pni", rot_m[:, np.repeat(r_mk, 2)], r_obj) + t_m[:, np.repeat(r_mk, 2)]
            hr = np.einsum("nij,pnj->pni", r_pa[:, :, :3], pr) + r_pa[:, :, 3]
            uvr = (hr[..., :2] / hr[..., 2:3]).reshape(n, n_r, 2, 2)
            rest.append((np.sum((uvr[:, :, 0] - uvr[:, :, 1]) * r_nrm, axis=-1) - r_apart) / r_sigma)
        return np.concatenate([*rest, prior], axis=1)

    def along_normals(xs, rot_m, t_m, mk, obj, pa, has, dv, center, corner_r, nrm):
        """Each anchor's image (its view's distortion applied where estimated) along its normal (P, K) px."""
        n = xs.shape[0]
        pts = np.einsum("pnij,nj->pni", rot_m[:, mk], obj) + t_m[:, mk]
        hs = np.einsum("nij,pnj->pni", pa[:, :, :3], pts) + pa[:, :, 3]
        uvs = hs[..., :2] / hs[..., 2:3]
        if n_dv and np.any(has):
            coef = xs[:, i_dist:].reshape(n, n_dv, 2)[:, dv[has]]
            uvs[:, has] += intensifier_shift_px(uvs[:, has], center[has], corner_r[has][:, None], coef)
        return np.sum(uvs * nrm, axis=-1)

    def stroke_rows(xs, rot_m, t_m):
        """Normalised residuals (P, n_s) of the ring strokes."""
        return (along_normals(xs, rot_m, t_m, s_mk, s_obj, s_pa, s_has, s_dv, s_center, s_corner_r, s_nrm) - s_off) / s_sigma

    def outline_rows(xs, rot_m, t_m):
        """Residuals (P, n_o) px of the ring outlines, not normalised (their whitening is their BBs' group's)."""
        return along_normals(xs, rot_m, t_m, o_mk, o_obj, o_pa, o_has, o_dv, o_center, o_corner_r, o_nrm) - o_off

    # The Jacobian is block sparse: a BB depends on its own marker's 6 parameters only, a corner on its
    # marker's, the drill's and the intrinsics. So the k-th parameter of every marker can be stepped at
    # once (the grouping scipy's jac_sparsity would find): 6 + 8 + 6 forward differences, evaluated in one
    # batched call, whatever the number of markers (measured ~2 ms against ~30 ms for scipy's grouped
    # sparse differences, which evaluate the groups one call at a time).
    h = 1e-6
    row_marker = np.concatenate([f_row_mk, np.repeat(c_mk, 2), s_mk, r_mk, np.full(N_INTRINSICS + 2 * n_dv, -1)])
    in_marker = np.nonzero(row_marker >= 0)[0]
    n_glob = N_INTRINSICS + 2 * n_dv  # intrinsics and the views' distortion: one column each
    steps = np.zeros((6 + n_glob + 6, n_par))
    steps[np.arange(6), np.arange(6)] = h
    steps[6 + np.arange(n_glob), 6 + 6 * ma + np.arange(n_glob)] = h
    for k in range(6):
        steps[6 + n_glob + k, 6 + k : 6 + 6 * ma : 6] = h

    def jacobian(x):
        f = residuals(np.vstack([x, x + steps]))
        diff = (f[1:] - f[0]) / h
        jac = np.zeros((f.shape[1], n_par))
        jac[:, :6] = diff[:6].T
        jac[:, 6 + 6 * ma :] = diff[6 : 6 + n_glob].T
        for k in range(6):
            jac[in_marker, 6 + 6 * row_marker[in_marker] + k] = diff[6 + n_glob + k, in_marker]
        return jac

    sol = least_squares(lambda x: residuals(x[None])[0], np.zeros(n_par), jac=jacobian, method="trf", loss=loss, f_scale=3.0, x_scale="jac", xtol=1e-8, ftol=1e-8,
                        max_nfev=100 if max_nfev is None else max_nfev)

    def unpack(x):
        drill = perturb_about(x[:6], drill0, pivot_d)
        rot, t = _perturb_batch(x[6 : 6 + 6 * ma].reshape(ma, 6), poses0, pivots)
        return drill, rot, t, x[6 + 6 * ma :]

    drill, rot, t, _ = unpack(sol.x)
    distortion = tuple((view, sol.x[i_dist + 2 * j : i_dist + 2 * j + 2].copy()) for j, view in enumerate(dist_views))
    res = sol.fun
    projected = residuals(sol.x[None], every_corner=True)[0]  # (4 m, 2)
    corner_proj = {i: projected[4 * k : 4 * k + 4] for k, i in enumerate(ids)}
    rf, rc = res[:n_f], res[n_f : n_f + n_c].reshape(-1, 2)
    chi = {}
    for k, i in enumerate(ids):
        both = np.concatenate([rf[f_row_mk == k], rc[c_mk == k].ravel()])
        chi[i] = float(np.sqrt(np.mean(both**2)))
    dof = max(1, len(res) - n_par)
    red = float(np.sum(res**2) / dof)
    jac = np.asarray(sol.jac).copy()
    if n_dv:
        # A pincushion held at zero from below by the barrel's stiff prior is still free upwards: the covariance takes
        # the prior's own size there, as if it were symmetric (linearised at the stiff side, it would state 1 px).
        rows = len(res) - 2 * n_dv + np.nonzero(is_pincushion)[0]
        jac[rows, i_dist + np.nonzero(is_pincushion)[0]] = 1.0 / dist_sigma[is_pincushion]
    # Each group's noise (BBs, corners) from its own residuals, not one reduced chi-square for all: a global
    # factor would also scale the intrinsics' prior, whose size the residuals say nothing about. Only the
    # contrasts within a group (tag, marker-view) tell its independent noise: a group's shared modes also
    # carry the shared shift and scale, which its pose absorbs. The shared rows keep the stated shared part
    # and take the independent part's factor.
    # A row whose noise is the independent sigma alone (a contrast, or a shared mode stated as 0) estimates it.
    f_est, c_est = np.isclose(f_noise, fluoro_sigma_px), np.isclose(c_noise, corner_sigma_px)
    scales = _noise_scales(jac, res, (np.nonzero(f_est)[0], n_f + np.nonzero(c_est)[0]))
    # The corners' shared part is stated in proportion to their independent noise (the same blur makes both), so
    # it takes the same factor; the BBs' shared part (the intensifier's) is stated in px and keeps its size.
    for est, noise, sigma, start, proportional in ((f_est, f_noise, fluoro_sigma_px, 0, False), (c_est, c_noise, corner_sigma_px, n_f, True)):
        k = scales[start : start + len(est)][est][:1]  # the group's factor (the same on all its estimating rows)
        if len(k) and not np.all(est):
            stated = noise[~est]
            scales[start + np.nonzero(~est)[0]] = k[0] if proportional else np.sqrt(stated**2 + (k[0] ** 2 - 1.0) * sigma**2) / stated
    w = 1.0 / scales
    jw = jac * w[:, None]
    cov = np.linalg.pinv(jw.T @ jw)
    if frame_sigma_px > 0:
        # The frame's shared shape modes are not solved for (solved, they took their share of every tag's own noise and
        # moved the axis more than they held it: docs/identity_and_error.md); the covariance carries what a draw of
        # them at their prior does to this solution, as a considered parameter: its sensitivity to them is
        # -cov J^T J_modes (the corners' rows, whitened as the residuals are).
        j_modes = np.zeros((len(res), N_FRAME_MODES))
        j_modes[n_f : n_f + n_c] = (wc @ c_modes.reshape(-1, N_FRAME_MODES)) / c_noise[:, None]
        sens = cov @ (jw.T @ (j_modes * w[:, None]))
        cov = cov + frame_sigma_px**2 * (sens @ sens.T)
    return JointSolution(
        carm_from_drill=drill,
        carm_from_marker={i: make_transform(rot[k], t[k]) for k, i in enumerate(ids)},
        covariance_drill=cov[:6, :6],
        pivot_carm_mm=pivot_d,
        used_ids=tuple(ids),
        rejected_ids=(),
        marker_chi=chi,
        fluoro_rms_px=float(np.sqrt(2.0 * np.mean((np.linalg.solve(wf, res[:n_f] * f_noise)[: 2 * len(f_obj_a)] if n_o else wf.T @ (res[:n_f] * f_noise)) ** 2))),
        corner_rms_px=float(np.sqrt(2.0 * np.mean((wc.T @ (res[n_f : n_f + n_c] * c_noise)) ** 2))),
        reduced_chi2=red,
        chi2=float(np.sum(res**2)),
        converged=bool(sol.success),
        detector_distortion_px=distortion,
        corner_projections_px=corner_proj,
    )
