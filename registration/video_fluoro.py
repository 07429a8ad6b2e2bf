"""Video-to-fluoroscopy registration: ``carm_from_drill`` from markers seen by both the camera and the C-arm.

1. Horn (weighted by the video covariances) between X_D(m) and X_C(m), the reference's method.
   An outlier marker (e.g. one bumped since the shot) is rejected by its
   point-based residual (leave-one-out), and per-marker FRE is reported.
2. Each marker's mirror ambiguity in fluoroscopy is settled by the tag normal
   the camera sees (carried into C by the Horn rotation).
3. PnP on every tag corner: the corners' 3D positions in C (from each
   registered marker pose and the design) against their sub-pixel image
   positions, so all markers constrain the camera pose together.
4. With the joint solve, markers the camera sees claim their BBs in views where fluoroscopy did not identify
   them (:mod:`.video_claims`: the camera's marker constellation fitted to the identified ones predicts them).
   When the marker poses carry their BB observations (``register_markers``
   keeps them), one joint solve of all marker poses and ``carm_from_drill``
   over every BB and every tag corner (:mod:`.joint_solve`), with its
   covariance; ``joint=False`` stops after step 3 (the former pipeline).
5. A predicted error for the drill axis: the joint solve's covariance (which
   carries the camera's calibration uncertainty) propagated to the axis with
   the drill axis's calibration uncertainty; Monte-Carlo over the inputs when
   there is no covariance. Its 90 % bound decides ``reliable``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2 as chi2_dist

from .camera import PinholeCamera
from .carm import CArmView
from .cut_corners import cut_corner_slides_px
from .errors import DegenerateInput, DrillnavError, MarkersNotFound
from .horn import absolute_orientation, absolute_orientation_batch
from .edge_on_ring import RingStroke, measure_ring_stroke
from .edge_on_roll import RingRoll, measure_ring_roll, rolled_about
from .ring_outline import measure_ring_outline
from .joint_solve import CORNER_SIGMA_PX, FOCAL_REL_SIGMA, JointSolution, frame_corner_sigma_px, joint_solve, project_distorted, square_misfit_noise_px
from .line import Line3D
from .marker_pose import MarkerPose, planar_candidates
from .markers import MarkerDesign, MarkerSet
from .transforms import apply, invert, make_transform
from .video_claims import claim_from_solution, claim_from_video, corroborate_loose, drill_from_marker, fit_constellation, paired_anchors, with_claims
from .video_markers import VideoDetections, VideoMarker

__all__ = ["DrillRegistration", "PredictedError", "register_video_to_fluoro", "predicted_axis_error", "RELIABLE_POSITION_MM", "RELIABLE_ANGLE_DEG"]


# Limits on the 90 % bound above which an axis is flagged unreliable (displays grey it out).
RELIABLE_POSITION_MM = 3.0
RELIABLE_ANGLE_DEG = 3.0


@dataclass(frozen=True, kw_only=True)
class PredictedError:
    """Bounds on the drill axis's error: position at the working point (mm) and angle (deg).

    position_mm, angle_deg : 95 % bounds; position90_mm, angle90_deg : 90 % bounds.
    reliable : both 90 % bounds within the limits given to :func:`predicted_axis_error`.
    """

    position_mm: float
    angle_deg: float
    cone_half_angle_deg: float
    position90_mm: float = float("nan")
    angle90_deg: float = float("nan")
    reliable: bool = True


@dataclass(frozen=True, kw_only=True)
class DrillRegistration:
    """carm_from_drill (4, 4); fre_mm: per-marker distance between X_C and the registered X_D."""

    carm_from_drill: NDArray[np.float64]
    carm_from_drill_horn: NDArray[np.float64]
    fre_mm: dict[int, float]
    used_ids: tuple[int, ...]
    rejected_ids: tuple[int, ...]
    corner_rms_px: float
    # From the joint solve (None / empty without it): covariance (6, 6) of a perturbation of carm_from_drill
    # (rotation vector rad, translation mm) rotating about pivot_carm_mm, and the refined marker poses.
    covariance_drill: NDArray[np.float64] | None = None
    pivot_carm_mm: NDArray[np.float64] | None = None
    carm_from_marker: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    method: str = "horn+pnp"
    # One view only: the constellation's mirror solution (4, 4) when it fits nearly as well (None: ruled out).
    # predicted_axis_error's bounds then reach it, and the axis is flagged unreliable past the limits.
    mirror_carm_from_drill: NDArray[np.float64] | None = None
    # The mirror is the solution's mirror image, no minimum of its own (the refinement slid from it to the best, though
    # it fits within the margin): it widens the bound, but the tags the frame missed are looked for where the best
    # solution puts them alone, and named by their place as with no mirror (:func:`.pipeline.register_with_recovery`).
    mirror_unrefined: bool = False
    # Two markers that fit only alone (:func:`_two_markers_alone`): each one's own solution (4, 4). The covariance is
    # widened towards them, and predicted_axis_error's bounds reach their axes, as the mirror's: a covariance spanning
    # a turn of tens of degrees, linearised, can fall short of it.
    alone_carm_from_drill: tuple[NDArray[np.float64], ...] = ()
    # A lone marker whose unrefined mirror image fits about as well as the best is registered half-way to it
    # (:func:`_half_way`): the best fit's ``carm_from_drill`` (4, 4) and {id: (4, 4)} marker poses, where the missing
    # tags are looked for as before. None: the registration is the best fit itself.
    fit_carm_from_drill: NDArray[np.float64] | None = None
    fit_carm_from_marker: dict[int, NDArray[np.float64]] | None = None
    # The marker poses registered: those given, with the BBs claimed through the video's identities
    # (:mod:`.video_claims`) and the markers found that way; empty without the joint solve.
    marker_poses: tuple = ()
    # ((view, (2,) pincushion and S shift at the field's corner, px), ...): each image intensifier view's
    # distortion as the joint solve estimated it (:func:`.joint_solve.project_distorted` draws with it).
    detector_distortion_px: tuple = ()


def _corner_extra_px(marker: VideoMarker, *, solve_sigma_px: float = CORNER_SIGMA_PX) -> float:
    """The extra noise (px) the joint solve charges each corner of ``marker``'s tag over its own ``solve_sigma_px``:
    its corners' misfit to a view of its square (:func:`.joint_solve.square_misfit_noise_px`) and what its stated
    corner noise exceeds that by (a recovered tag's ``RECOVERED_CORNER_SIGMA_PX``, a detected tag's edges'
    ``VideoMarker.edge_sigma_px``), added in quadrature."""
    stated = float(np.sqrt(max(max(marker.corner_sigma_px, marker.edge_sigma_px) ** 2 - solve_sigma_px**2, 0.0)))
    return float(np.hypot(square_misfit_noise_px(marker.reprojection_error_px), stated))


def register_video_to_fluoro(
    video: VideoDetections,
    marker_poses: tuple[MarkerPose, ...],
    marker_set: MarkerSet,
    camera: PinholeCamera,
    *,
    outlier_mm: float = 2.5,
    min_markers: int = 1,
    joint: bool = True,
) -> DrillRegistration:
    """``carm_from_drill`` from the markers seen by the camera and localised in fluoroscopy.

    ``joint``: finish with the joint solve of every marker pose and the drill pose when the marker poses carry
    their BB observations (the default); False keeps the former Horn + corner PnP pipeline. With the joint
    solve, markers the camera sees claim their BBs where fluoroscopy did not identify them
    (:func:`.video_claims.claim_from_video`), so an edge-on marker in a single view still counts.

    One or two markers in common register too (a tag's four corners give the marker's full pose in D, its BBs
    its pose in C): the joint solve's covariance carries the weaker geometry into the predicted error, which
    flags the axis unreliable when its bound is over the limits. Refused (``MarkersNotFound``) below
    ``min_markers`` markers in common or below 4 BBs in all. Markers are rejected as outliers only while
    3 or more remain: with two, neither can be told from the other.

    A marker posed from a ring identified only at the looser cost (``MarkerPose.needs_camera``) counts only when the
    camera sees its tag; otherwise it is left out here.
    """
    seen = {m.marker_id for m in video.markers}
    loose = tuple(p for p in marker_poses if p.loose and p.marker_id in seen)
    marker_poses = tuple(p for p in marker_poses if not p.loose and (not p.needs_camera or p.marker_id in seen))
    if joint:
        # With no marker the camera sees posed in fluoroscopy, a ring's loose match to one of them may anchor the
        # constellation, when the other markers' BBs are where it then predicts them.
        if loose and not any(p.observations and p.marker_id in seen for p in marker_poses):
            marker_poses = corroborate_loose(video, marker_poses, loose, marker_set)
        marker_poses = claim_from_video(video, tuple(marker_poses), marker_set)
    every = {p.marker_id: p for p in marker_poses}
    poses = {i: p for i, p in every.items() if p.converged}
    vids = video.by_id()
    common = sorted(set(poses) & set(vids))
    # The joint solve also takes markers whose fluoroscopy-only pose did not converge (edge-on, few BBs, one
    # view): the camera fixes their orientation, so their BBs still count.
    joinable = sorted(i for i in set(every) & set(vids) if every[i].observations or every[i].solution_observations) if joint else []
    available = joinable if joinable and len(joinable) >= len(common) else common
    bbs = sum(_bb_count(every[i]) for i in available)
    # One marker seen by the camera (its tag: a full pose in D) and posed in fluoroscopy fixes carm_from_drill;
    # below four BBs in all its pose in C is not determined (three give up to four P3P solutions).
    if len(available) < max(min_markers, 1) or bbs < 4:
        raise MarkersNotFound(
            f"only {len(available)} marker(s) seen by both the camera and fluoroscopy "
            f"(camera: {sorted(vids)}, fluoroscopy: {sorted(poses)}, {bbs} BBs); at least {max(min_markers, 1)} "
            "with 4 or more BBs in all are needed"
        )
    used = list(common if len(common) >= HORN_MIN_MARKERS else available)
    rejected: list[int] = []
    if len(used) >= HORN_MIN_MARKERS:
        while True:
            fit = _horn(used, vids, every)
            worst = int(np.argmax(fit.residuals_mm))
            if fit.residuals_mm[worst] <= outlier_mm or len(used) <= max(min_markers, HORN_MIN_MARKERS):
                break
            # Leave-one-out: does the fit without the worst marker explain the others well?
            rest = [i for k, i in enumerate(used) if k != worst]
            if _horn(rest, vids, every).fre_mm < fit.fre_mm:
                rejected.append(used.pop(worst))
            else:
                break
        carm_from_drill_horn = fit.target_from_source
    else:
        # One or two markers: no point-based fit; each marker's pose in C composed with its pose in D.
        carm_from_drill_horn = _from_few_markers(used, vids, every, marker_set)
    carm_from_marker = {}
    for i in set(used) | set(common) | set(joinable):
        carm_from_marker[i], observations = _camera_side(every[i], carm_from_drill_horn @ vids[i].camera_from_tag)
        every[i] = replace(every[i], observations=observations)
    # Joint PnP on all tag corners of the markers kept.
    obj, img = [], []
    for i in used:
        design = marker_set.by_id(i)
        obj.append(apply(carm_from_marker[i], design.tag_corners_mm()))
        img.append(vids[i].corners_px)
    obj_a, img_a = np.concatenate(obj), np.concatenate(img)
    drill_from_carm0 = invert(carm_from_drill_horn)
    rvec0, _ = cv2.Rodrigues(drill_from_carm0[:3, :3])
    rvec, tvec = cv2.solvePnPRefineLM(obj_a, img_a, camera.camera_matrix, camera.distortion, rvec0.copy(), drill_from_carm0[:3, 3].reshape(3, 1).copy())
    rot, _ = cv2.Rodrigues(rvec)
    carm_from_drill = invert(make_transform(rot, tvec.ravel()))
    proj, _ = cv2.projectPoints(obj_a, rvec, tvec, camera.camera_matrix, camera.distortion)
    corner_rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_a) ** 2, axis=1))))
    extra: dict = {}
    if available is joinable:
        for i in joinable:
            if not every[i].converged:  # orientation from the camera, position from fluoroscopy
                start = carm_from_drill @ vids[i].camera_from_tag
                start[:3, 3] = every[i].position_carm_mm
                carm_from_marker[i] = start
        solve = dict(observations={i: every[i].observations for i in joinable}, corners_px={i: vids[i].corners_px for i in joinable},
                     marker_set=marker_set, camera=camera, min_markers=min(HORN_MIN_MARKERS, len(joinable)),
                     corner_extra_px={i: _corner_extra_px(vids[i]) for i in joinable},
                     corner_slide_px={i: cut_corner_slides_px(vids[i].corners_px, width=camera.width, height=camera.height) for i in joinable},
                     frame_shape_sigma_px=frame_corner_sigma_px([v.edge_sigma_px for v in video.markers]),
                     fluoro_only={i: (p.observations, p.carm_from_marker) for i, p in every.items()
                                  if i not in joinable and p.converged and p.mirror_carm_from_marker is None and not p.needs_camera})
        sol = joint_solve(carm_from_drill0=carm_from_drill, carm_from_marker0=carm_from_marker, **solve)
        # The claims predicted each marker through its tag's pose in the camera; the solve's poses, refined by every
        # BB and corner, may find the BBs of a marker in a view where those missed them (edge-on): solved again with them.
        # A marker the camera sees that no view observed (its BBs edge-on, or only a tilted prediction would find
        # them) is predicted through the solve's drill and its tag, and claimed too.
        camera_only = {i: sol.carm_from_drill @ drill_from_marker(vids[i].camera_from_tag, marker_set.by_id(i).tag_center_mm)
                       for i in vids if i in marker_set.ids and i not in joinable}
        again = claim_from_solution(tuple(every.values()), {i: sol.carm_from_marker[i] for i in sol.used_ids}, marker_set, camera_only=camera_only,
                                    distortion=sol.detector_distortion_px)
        first, before_claims = sol, (dict(every), marker_poses, joinable, dict(carm_from_marker), dict(solve))

        def with_claims_solved(claims: dict) -> tuple:
            # The solve again from before the claims, with ``claims``: (sol, every, marker_poses, joinable, carm_from_marker, solve).
            every_, poses_, joinable_, starts_, solve_ = (dict(before_claims[0]), before_claims[1], before_claims[2], dict(before_claims[3]),
                                                          dict(before_claims[4]))
            blobs_from = next(iter(every_.values()))
            for i in sorted(set(claims) - set(every_)):
                every_[i] = MarkerPose(marker_id=i, carm_from_marker=camera_only[i], residual_px=float("nan"), n_views=0, n_points=0, converged=False,
                                       observations=(), view_blobs=blobs_from.view_blobs, non_disc_blobs=blobs_from.non_disc_blobs)
                poses_ = (*poses_, every_[i])
            gained = sorted(i for i in claims if i in camera_only)
            every_.update({i: with_claims(every_[i], claims[i]) for i in claims})
            poses_ = tuple(with_claims(p, claims[p.marker_id]) if p.marker_id in claims else p for p in poses_)
            if gained:
                joinable_ = sorted({*joinable_, *gained})
                starts_.update({i: camera_only[i] for i in gained})
                solve_.update(corners_px={i: vids[i].corners_px for i in joinable_}, corner_extra_px={i: _corner_extra_px(vids[i]) for i in joinable_},
                              corner_slide_px={i: cut_corner_slides_px(vids[i].corners_px, width=camera.width, height=camera.height) for i in joinable_},
                              min_markers=min(HORN_MIN_MARKERS, len(joinable_)))
            solve_["observations"] = {i: every_[i].observations for i in joinable_}
            sol_ = joint_solve(carm_from_drill0=first.carm_from_drill, carm_from_marker0={**starts_, **first.carm_from_marker}, **solve_)
            return sol_, every_, poses_, joinable_, starts_, solve_

        if again:
            state = with_claims_solved(again)
            while True:
                misfit = _misfit_claims(state[0], again) or _dragging_claim(first, state[0], again, with_claims_solved)
                if not misfit:
                    sol, every, marker_poses, joinable, carm_from_marker, solve = state
                    break
                # A claim the solve cannot fit, or that drags the rest, is a wrong one: solved again from before the claims, without it.
                again = {i: kept for i, per in again.items() if (kept := tuple(o for k, o in enumerate(per) if (i, k) not in misfit))}
                if not again:
                    break
                state = with_claims_solved(again)
        # An edge-on marker (a lateral view, markers on the anterior skin) shows few BBs or none, but its ring's stroke
        # across its line fixes its depth along the other views' beams: measured at the solve's poses, solved again.
        sol = _with_strokes(sol, every, solve, carm_from_marker, marker_set)
        alternative, unrefined, fit = None, False, None
        views = {id(o[0]): o[0] for i in sol.used_ids for o in every[i].observations}
        before_mirror = sol
        if len(views) == 1:
            sol, alternative, unrefined = _settle_constellation_mirror(sol, next(iter(views.values())), solve)
            if unrefined and len(sol.used_ids) == 1:
                fit, sol = sol, _half_way(sol, alternative, solve)
        elif len(sol.used_ids) == 1 and sol.marker_chi[sol.used_ids[0]] > LONE_MARKER_MISFIT_CHI:
            i = sol.used_ids[0]
            sol, alternative = _settle_lone_marker_views(sol, solve, drill_from_marker(vids[i].camera_from_tag, marker_set.by_id(i).tag_center_mm))
        elif len(sol.used_ids) == 1 and len(every[sol.used_ids[0]].solutions) > 1:
            sol, alternative = _settle_lone_marker_mirror(sol, every[sol.used_ids[0]], solve)
        if alternative is None and fit is None:
            # An open ring's wire, all around it, measures its marker's scale in the view (its depth along the beam) where
            # the BBs, within 15 mm of the centre, fix it least: measured at the solve's poses, solved again. Only where no
            # mirror image is left open: measured around one solution's ellipse, the rows would judge the other on anchors
            # it does not place there (twin seed 29102, flat markers, the AP view alone, second pose: a lone marker's
            # open mirror closed, the axis 45.6 mm off under a 7.9 mm bound, flagged).
            settled = sol
            sol = _with_outlines(sol, every, solve, carm_from_marker, marker_set)
            before_mirror = sol if before_mirror is settled else before_mirror
        alone = _markers_alone(sol, solve)
        kept = _seen_in_more_views(alone, every) if alternative is None and fit is None else None
        if kept is not None:
            # Two markers that fit only alone, one posed over two views, the other in one: the first alone.
            sol = replace(kept, rejected_ids=(*sol.rejected_ids, *(i for i in sol.used_ids if i not in kept.used_ids)))
            alone = {}
        carm_from_drill, corner_rms = sol.carm_from_drill, sol.corner_rms_px
        used, rejected = list(sol.used_ids), list(sol.rejected_ids)
        carm_from_marker.update(sol.carm_from_marker)
        covariance = sol.covariance_drill if alternative is None else _spanning(sol.covariance_drill, sol.carm_from_drill, alternative, sol.pivot_carm_mm)
        alone_solutions = tuple(a.carm_from_drill for a in alone.values())
        if alone_solutions and before_mirror.used_ids == sol.used_ids and not _same_drill(before_mirror, sol):
            # Two markers that fit only alone, the constellation's mirror taken: the better of two misfits says little.
            # The bounds reach the solution it left, and each marker's own solved from there too (one view: a marker
            # alone keeps the side of its start). Twin seed 11901 (random pair, one view, first pose, recovered tags'
            # cells read beside covers): the mirror (chi-square 151 against 1722) lay 47.6 deg off, and each marker's
            # own from it as far; the bound reached 15 deg.
            alone_solutions += (before_mirror.carm_from_drill, *_two_markers_alone(before_mirror, solve))
        for alone in alone_solutions:
            covariance = _spanning(covariance, sol.carm_from_drill, alone, sol.pivot_carm_mm)
        extra = dict(covariance_drill=covariance, pivot_carm_mm=sol.pivot_carm_mm, method="joint", marker_poses=tuple(marker_poses),
                     mirror_carm_from_drill=alternative, alone_carm_from_drill=alone_solutions, mirror_unrefined=unrefined, detector_distortion_px=sol.detector_distortion_px,
                     fit_carm_from_drill=None if fit is None else fit.carm_from_drill, fit_carm_from_marker=None if fit is None else fit.carm_from_marker)
    common = sorted(set(common) | set(joinable))
    drill_from_carm = invert(carm_from_drill)
    fre = {i: float(np.linalg.norm(apply(drill_from_carm, carm_from_marker[i][:3, 3]) - vids[i].position_camera_mm)) for i in common}
    return DrillRegistration(
        carm_from_drill=carm_from_drill,
        carm_from_drill_horn=carm_from_drill_horn,
        fre_mm=fre,
        used_ids=tuple(used),
        rejected_ids=tuple(rejected),
        corner_rms_px=corner_rms,
        carm_from_marker=carm_from_marker,
        **extra,
    )


# A claimed view's BBs whose RMS distance from where the solve that took them projects them exceeds this (px) were
# not that marker's: the claim's other evidence (its tilt, its slide along the beam) fitted blobs the solve's other
# BBs and tags cannot place there. Right claims fit within their noise (about 1 px, crowded BBs a few).
CLAIM_MISFIT_PX = 10.0


def _misfit_claims(sol: JointSolution, claims: dict[int, tuple]) -> set[tuple[int, int]]:
    """{(marker id, index in its claims)}: the claimed observations ((view, design (N, 3) mm, blobs (N, 2) px), ...) per
    marker of ``claims`` that ``sol`` (solved with them) fits at over ``CLAIM_MISFIT_PX`` RMS; a marker the solve left
    out is not judged.

    Twin seed 31300 (random pair, both views, first pose, markers stuck flat): marker 27, observed in the first view
    only, slid along its beam and tilted, claimed four blobs in the second, two of them discs, 90 and 100 px from its
    BBs' true places; the solve's chi-square went 25.6 -> 857 and the axis lay 4.9 mm / 2.1 deg off under a 1.6 mm /
    0.5 deg bound, unflagged.
    """
    out = set()
    for i, per in claims.items():
        if i not in sol.carm_from_marker:
            continue
        for k, (view, design_mm, blobs_px) in enumerate(per):
            predicted = project_distorted(view, apply(sol.carm_from_marker[i], np.asarray(design_mm, dtype=np.float64)), sol.detector_distortion_px)
            if np.sqrt(np.mean(np.sum((predicted - np.asarray(blobs_px, dtype=np.float64)) ** 2, axis=1))) > CLAIM_MISFIT_PX:
                out.add((i, k))
    return out


# A solve with the claims whose chi-square exceeds the one before them by more than this quantile of chi-square with as
# many degrees of freedom as the claims add rows (each BB two) has a claim that does not fit.
CLAIM_JUMP_QUANTILE = 0.999
# ... and only where it drags another marker of the solve past its stated noise (RMS normalised residual) and to over
# twice its fit before the claims.
DRAGGED_CHI = 1.0


def _dragging_claim(before: JointSolution, after: JointSolution, claims: dict[int, tuple], solve_with) -> set[tuple[int, int]]:
    """{(marker id, index in its claims)} of the one claimed observation whose removal takes the most chi-square off
    ``after`` (solved with ``claims`` by ``solve_with(claims)``), when ``after`` costs more than ``before`` beyond what
    its claimed BBs' rows allow (:data:`CLAIM_JUMP_QUANTILE`), that removal gives back more than the claim's own rows
    allow, and another marker of ``before`` fits ``after`` past :data:`DRAGGED_CHI` and twice its fit in ``before``;
    empty otherwise.

    A claimed view's BBs that the solve fits under :data:`CLAIM_MISFIT_PX` may still not be the marker's: the solve
    spreads one wrong BB over every marker. Twin seed 32001 (AP+lateral, markers stuck flat, second pose): marker 9,
    posed in the AP view only, claimed two BBs in the lateral view, one of them 13.6 px from its own; the two markers'
    solve went from chi-square 6.1 to 126 on four more rows, both markers' RMS from 0.4 to 1.7, and they no longer fitted
    together (8.5 mm, flagged).
    """
    rows = 2 * sum(len(o[2]) for per in claims.values() for o in per)
    if not np.isfinite(after.chi2) or after.chi2 - before.chi2 <= chi2_dist.ppf(CLAIM_JUMP_QUANTILE, max(rows, 1)):
        return set()
    best, best_chi2 = None, after.chi2
    for i, per in claims.items():
        for k in range(len(per)):
            rest = {j: kept for j, q in claims.items() if (kept := tuple(o for m, o in enumerate(q) if (j, m) != (i, k)))}
            try:
                trial = solve_with(rest)[0] if rest else before
            except DrillnavError:
                continue
            if trial.chi2 < best_chi2:
                best, best_chi2 = (i, k), trial.chi2
    if best is None:
        return set()
    own_rows = 2 * len(claims[best[0]][best[1]][2])
    # Only a claim that the other markers' own fit contradicts: a lone marker's claim may instead contradict its pose
    # from one view and a tag, on the wrong side of its mirror (seed 10901, tests/test_lone_marker_mirror.py: two right
    # BBs, 1.0 and 2.1 px from their places, chi-square 4.2 -> 37.6).
    dragged = any(after.marker_chi.get(j, 0.0) > max(DRAGGED_CHI, 2.0 * before.marker_chi[j]) for j in before.used_ids if j != best[0])
    return {best} if dragged and after.chi2 - best_chi2 > chi2_dist.ppf(CLAIM_JUMP_QUANTILE, own_rows) else set()


def _bb_count(pose: MarkerPose) -> int:
    """The BBs ``pose`` was solved on: its observations, or the most any of its pairings makes where its BBs pair
    two ways (:attr:`.MarkerPose.solution_observations`); 4 for a converged pose handed in without observations."""
    sets = [pose.observations, *pose.solution_observations]
    return max(sum(len(o[1]) for o in obs) for obs in sets) if any(sets) else 4


# Below this many markers in common, no point-based (Horn) fit and no outlier rejection: two cannot outvote each other.
HORN_MIN_MARKERS = 3
# A view where a used marker shows fewer BBs than this measures its ring's stroke when it is edge-on there; the
# strokes are measured again at each round's poses (the predicted profile closer to the image's), this many rounds.
STROKE_BELOW_BBS = 4
STROKE_ROUNDS = 2
# A stroke farther than this (in its sigmas) from where the solve with it puts its anchor is left out, and the
# round solved again without it (a neighbour's stroke or a K-wire matched instead).
STROKE_OUTLIER_CHI = 4.0
# A roll whose runner-up angle matches the image within this share of its best is settled by the fit
# (:func:`_settle_rolls`): taken at the angle whose fit is better by ROLL_DELTA_CHI2 (in units of the fit's reduced
# chi-square, at least 1), else left out.
ROLL_AMBIGUOUS_RATIO = 0.8
ROLL_DELTA_CHI2 = 9.0
# A used marker that a view shows by neither its BBs nor its stroke, edge-on there: its stroke's profile, predicted
# from a pose turned a few degrees about the ring's line, can miss the image (the ring opened into a thin ellipse).
# Its shadow's best turn is taken down to this correlation, and, with it, the two halves of its stroke found agreeing
# at the turned pose, each to TURNED_STROKE_CORRELATION; the one bears the other out.
TURNED_MIN_CORRELATION = 0.3
TURNED_STROKE_CORRELATION = 0.85
TURNED_STROKE_MARGIN = 0.05


def _with_strokes(sol: JointSolution, every: dict[int, MarkerPose], solve: dict, starts: dict[int, NDArray[np.float64]],
                  marker_set: MarkerSet) -> JointSolution:
    """``sol`` solved again with the ring strokes (:func:`.edge_on_ring.measure_ring_stroke`) of its markers in the views
    where they show fewer than ``STROKE_BELOW_BBS`` BBs, and with their rolls (:func:`.edge_on_roll.measure_ring_roll`)
    in every view where they are edge-on (:func:`_settle_rolls`); ``solve`` (joint_solve's other arguments) takes
    both, so later solves keep them. ``sol`` as it is where the poses carry no images or nothing is measured."""
    images = next((p.view_images for p in every.values() if p.view_images), ())
    if len(images) < 2:
        return sol
    for _ in range(STROKE_ROUNDS):
        strokes: dict[int, list] = {}
        measured: dict[int, list] = {}
        for i in sol.used_ids:
            shown = {id(o[0]): len(o[1]) for o in solve["observations"].get(i, ())}
            design = marker_set.by_id(i)
            for view, image in images:
                # A half-stroke alone has nothing in it to check it, so it is taken only where another marker can:
                # on one marker, seed 10802's marker 43 (flat, AP+lateral, second pose) took a half 20 px off.
                found = (measure_ring_stroke(image, view, sol.carm_from_marker[i], design, lone_half=len(sol.used_ids) >= 2)
                         if shown.get(id(view), 0) < STROKE_BELOW_BBS else ())
                # Shown by nothing in this view, the marker is looked for turned as its shadow says: the pose's turn
                # about the ring's line can leave the stroke's predicted profile off the image's (fresh seed 13300).
                turned = None
                if not found and not shown.get(id(view), 0) and len(sol.used_ids) >= 2:
                    turned, found = _turned_stroke(image, view, sol.carm_from_marker[i], design)
                if found:
                    strokes.setdefault(i, []).append((view, np.stack([st.anchor_mm for st in found]), np.stack([st.normal for st in found]),
                                                      np.array([st.offset_px for st in found]), np.array([st.sigma_px for st in found])))
                # A roll is measured where the view shows the marker (its BBs, or its stroke), on two markers or more. Where
                # the view showed neither, its shadow was matched wherever the solve put it: seed 14000's random pair
                # (default twin), marker 12 turned 8 deg, the axis 0.25 -> 9.0 mm off. On one marker nothing checks a roll:
                # a weak match turned seed 11901's lone marker 12 deg (flat, AP+lateral).
                if turned is not None:
                    measured.setdefault(i, []).append((view, turned))
                elif len(sol.used_ids) >= 2 and (shown.get(id(view), 0) or found):
                    roll = measure_ring_roll(image, view, sol.carm_from_marker[i], design)
                    if roll is not None:
                        roll = _settled_by_stroke(image, view, sol.carm_from_marker[i], design, roll)
                        measured.setdefault(i, []).append((view, roll))
        if not strokes and not measured:
            return sol
        start = dict(carm_from_drill0=sol.carm_from_drill, carm_from_marker0={**starts, **sol.carm_from_marker})
        rolls = _settle_rolls(measured, {**solve, **start, "strokes": strokes})
        while True:
            again = joint_solve(**start, **{**solve, "strokes": strokes, "rolls": rolls})
            far, far_rolls = _far_strokes(again, strokes), _far_rolls(again, rolls)
            if not far and not far_rolls:
                break
            strokes = {i: per for i, per in ((i, [s for k, s in enumerate(per) if (i, k) not in far]) for i, per in strokes.items()) if per}
            rolls = {i: per for i, per in ((i, [r for k, r in enumerate(per) if (i, k) not in far_rolls]) for i, per in rolls.items()) if per}
            if not strokes and not rolls:
                return sol
        solve["strokes"], solve["rolls"] = strokes, rolls
        sol = again
    return sol


# How near another used marker's BB or wire an outline's anchor may lie (px beyond the BB's radius; from the wire).
OUTLINE_CLEARANCE_PX = 6.0
# An outline row farther than this (in its sigmas) from where the solve with the outlines puts its anchor is left out,
# and the solve run again without it (a K-wire, a clamp's edge or a neighbour's shadow across the wire).
OUTLINE_OUTLIER_CHI = 4.0


def _with_outlines(sol: JointSolution, every: dict[int, MarkerPose], solve: dict, starts: dict[int, NDArray[np.float64]],
                   marker_set: MarkerSet) -> JointSolution:
    """``sol`` solved again with the outlines of its markers' open rings (:func:`.ring_outline.measure_ring_outline`) in
    every view where the marker shows 3 BBs or more; ``solve`` takes them, so later solves keep them. Rows that the
    solve leaves over ``OUTLINE_OUTLIER_CHI`` sigmas off are dropped and it is solved again. ``sol`` as it is where the
    poses carry no images, nothing is measured, or the solve with the outlines fails."""
    images = next((p.view_images for p in every.values() if p.view_images), ())
    if not images:
        return sol
    outlines: dict[int, list] = {}
    for view, image in images:
        coef = next((c for v, c in sol.detector_distortion_px if v is view), None)
        shown = {i: len(o[1]) for i in sol.used_ids for o in solve["observations"].get(i, ()) if o[0] is view}
        for i in sol.used_ids:
            if shown.get(i, 0) < 3:
                continue
            avoid, radius = [], []
            for j, pose in sol.carm_from_marker.items():
                if j == i:
                    continue
                other = marker_set.by_id(j)
                bbs = project_distorted(view, apply(pose, other.bb_centers_mm), sol.detector_distortion_px)
                scale = float(view.magnification(pose[:3, 3][None])[0]) / float(view.pixel_spacing_mm[1])
                ring = project_distorted(view, apply(pose, other.ring_points_mm(180)), sol.detector_distortion_px)
                avoid += [bbs, ring]
                radius += [0.5 * other.bb_diameters_mm * scale + OUTLINE_CLEARANCE_PX, np.full(len(ring), 0.5 * other.ring_wire_diameter_mm * scale + OUTLINE_CLEARANCE_PX)]
            found = measure_ring_outline(image, view, sol.carm_from_marker[i], marker_set.by_id(i), distortion_px=coef,
                                         avoid_px=np.concatenate(avoid) if avoid else None, avoid_radius_px=np.concatenate(radius) if radius else 0.0)
            if found is not None:
                outlines.setdefault(i, []).append((view, found.anchors_mm, found.normals, found.offsets_px, found.sigmas_px))
    if not outlines:
        return sol
    start = dict(carm_from_drill0=sol.carm_from_drill, carm_from_marker0={**starts, **sol.carm_from_marker})
    while True:
        try:
            again = joint_solve(**start, **{**solve, "outlines": outlines})
        except DrillnavError:
            return sol
        far = _far_rows(again, outlines, OUTLINE_OUTLIER_CHI)
        if not far:
            break
        outlines = _without_rows(outlines, far)
        if not outlines:
            return sol
    solve["outlines"] = outlines
    return again


def _without_rows(outlines: dict[int, list], far: set[tuple[int, int, int]]) -> dict[int, list]:
    """``outlines`` without the rows ``far`` names ((marker id, index in its list, row)), and without what is left empty."""
    kept: dict[int, list] = {}
    for i, per in outlines.items():
        for k, (view, anchors, normals, offsets, sigmas) in enumerate(per):
            keep = np.array([(i, k, r) not in far for r in range(len(offsets))])
            if keep.any():
                kept.setdefault(i, []).append((view, anchors[keep], normals[keep], offsets[keep], sigmas[keep]))
    return kept


def _far_rows(sol: JointSolution, outlines: dict[int, list], chi: float) -> set[tuple[int, int, int]]:
    """(marker id, index in its list, row) of the outline rows over ``chi`` sigmas from where ``sol`` puts their
    anchors (a marker the solve rejected: all of its rows)."""
    far = set()
    for i, per in outlines.items():
        for k, (view, anchors, normals, offsets, sigmas) in enumerate(per):
            if i not in sol.carm_from_marker:
                far |= {(i, k, r) for r in range(len(offsets))}
                continue
            uv = project_distorted(view, apply(sol.carm_from_marker[i], anchors), sol.detector_distortion_px)
            far |= {(i, k, int(r)) for r in np.nonzero(np.abs(np.sum(uv * normals, axis=1) - offsets) > chi * sigmas)[0]}
    return far


def _ambiguous(roll: RingRoll) -> bool:
    """Whether ``roll``'s runner-up turn matched the image within ``ROLL_AMBIGUOUS_RATIO`` of its best."""
    return bool(np.isfinite(roll.runner_up_deg) and roll.runner_up >= ROLL_AMBIGUOUS_RATIO * roll.correlation)


def _halves_at(image: NDArray[np.floating], view: CArmView, carm_from_marker: NDArray[np.float64], design: MarkerDesign,
               roll: RingRoll, deg: float) -> tuple[tuple[RingStroke, ...], float]:
    """The two halves of ``design``'s stroke found agreeing at ``carm_from_marker`` (4, 4) turned ``deg`` about
    ``roll``'s axis through the ring's centre, and the weaker half's correlation (-1 where there are not two)."""
    turned = rolled_about(carm_from_marker, roll.axis_mm, np.asarray(design.ring_center_mm, dtype=np.float64), deg)
    found = measure_ring_stroke(image, view, turned, design, lone_half=False)
    return found, (min(h.correlation for h in found) if len(found) == 2 else -1.0)


def _settled_by_stroke(image: NDArray[np.floating], view: CArmView, carm_from_marker: NDArray[np.float64], design: MarkerDesign,
                       roll: RingRoll, *, best: float | None = None) -> RingRoll:
    """``roll`` measured at ``carm_from_marker`` (4, 4), settled where its runner-up turn matched about as well
    (``ROLL_AMBIGUOUS_RATIO``) and the ring's stroke tells them apart: the two turns open the ring differently, and the
    stroke's profile at the best turn matches (both halves, to ``TURNED_STROKE_CORRELATION``) better by
    ``TURNED_STROKE_MARGIN`` than at the runner-up's; then it has no runner-up. ``roll`` as it is otherwise.
    ``best``: the weaker half's correlation at the best turn where the caller has it (:func:`_halves_at`)."""
    if not _ambiguous(roll):
        return roll
    if best is None:
        _, best = _halves_at(image, view, carm_from_marker, design, roll, roll.roll_deg)
    _, other = _halves_at(image, view, carm_from_marker, design, roll, roll.runner_up_deg)
    if best >= TURNED_STROKE_CORRELATION and best > other + TURNED_STROKE_MARGIN:
        return replace(roll, runner_up=0.0, runner_up_apart_px=float("nan"), runner_up_deg=float("nan"))
    return roll


def _turned_stroke(image: NDArray[np.floating], view: CArmView, carm_from_marker: NDArray[np.float64],
                   design: MarkerDesign) -> tuple[RingRoll | None, tuple[RingStroke, ...]]:
    """The roll and the stroke of an edge-on marker that ``view`` shows by neither its BBs nor its stroke at
    ``carm_from_marker`` (4, 4): the shadow's best turn (matched down to ``TURNED_MIN_CORRELATION``, settled where
    ambiguous by :func:`_settled_by_stroke`), and the ring's two halves found agreeing at that turned pose, each to
    ``TURNED_STROKE_CORRELATION``; (None, ()) unless both."""
    roll = measure_ring_roll(image, view, carm_from_marker, design, min_correlation=TURNED_MIN_CORRELATION)
    if roll is None:
        return None, ()
    halves, score = _halves_at(image, view, carm_from_marker, design, roll, roll.roll_deg)
    if score < TURNED_STROKE_CORRELATION:
        return None, ()
    roll = _settled_by_stroke(image, view, carm_from_marker, design, roll, best=score)
    return (None, ()) if _ambiguous(roll) else (roll, halves)


def _roll_rows(measured: dict[int, list], choice: dict[tuple[int, int], bool | None]) -> dict[int, list]:
    """joint_solve's ``rolls`` from the measured rolls {marker id: [(view, RingRoll), ...]}: each at its best angle, or
    at its runner-up where ``choice`` says True for (marker id, index); those ``choice`` maps to None are left out."""
    out: dict[int, list] = {}
    for i, per in measured.items():
        for k, (view, r) in enumerate(per):
            pick = choice.get((i, k), False)
            if pick is None:
                continue
            out.setdefault(i, []).append((view, r.near_mm, r.far_mm, r.normal, r.runner_up_apart_px if pick else r.apart_px, r.sigma_px))
    return out


def _settle_rolls(measured: dict[int, list], solve: dict) -> dict[int, list]:
    """The rolls the joint solve takes: nearly edge-on, a marker's shadow turned the other way can match about as well
    (its runner-up within ``ROLL_AMBIGUOUS_RATIO`` of its best), and the image alone cannot tell which; each such roll
    is then solved at either angle with the others as settled so far (at their best at first), and taken at the one
    whose fit is better by ``ROLL_DELTA_CHI2`` (the camera's constellation and the other markers' rolls tell), else
    left out."""
    choice: dict[tuple[int, int], bool | None] = {}
    ambiguous = [(i, k) for i, per in measured.items() for k, (_, r) in enumerate(per) if _ambiguous(r)]
    if not ambiguous:
        return _roll_rows(measured, choice)
    base = joint_solve(**{**solve, "rolls": _roll_rows(measured, choice)})
    for key in ambiguous:
        other = joint_solve(**{**solve, "rolls": _roll_rows(measured, {**choice, key: True})})
        margin = ROLL_DELTA_CHI2 * max(1.0, min(base.reduced_chi2, other.reduced_chi2))
        if other.chi2 < base.chi2 - margin:
            choice[key] = True
            base = other
        elif other.chi2 <= base.chi2 + margin:
            choice[key] = None
            base = joint_solve(**{**solve, "rolls": _roll_rows(measured, choice)})
    return _roll_rows(measured, choice)


def _far_strokes(sol: JointSolution, strokes: dict[int, list]) -> set[tuple[int, int]]:
    """(marker id, index in its list) of the strokes whose anchors lie over ``STROKE_OUTLIER_CHI`` sigmas from where
    ``sol`` puts them (a marker the solve rejected: all of its strokes)."""
    far = set()
    for i, per in strokes.items():
        for k, (view, anchors, normals, offsets, sigmas) in enumerate(per):
            if i not in sol.carm_from_marker:
                far.add((i, k))
                continue
            uv = project_distorted(view, apply(sol.carm_from_marker[i], anchors), sol.detector_distortion_px)
            if np.any(np.abs(np.sum(uv * normals, axis=1) - offsets) > STROKE_OUTLIER_CHI * sigmas):
                far.add((i, k))
    return far


def _far_rolls(sol: JointSolution, rolls: dict[int, list]) -> set[tuple[int, int]]:
    """(marker id, index in its list) of the rolls that ``sol`` leaves over ``STROKE_OUTLIER_CHI`` sigmas from their
    measure (a marker the solve rejected: all of its rolls): the shadow matched with a neighbour's over it."""
    far = set()
    for i, per in rolls.items():
        for k, (view, near, far_mm, normal, apart, sigma) in enumerate(per):
            if i not in sol.carm_from_marker:
                far.add((i, k))
                continue
            uv = view.project(apply(sol.carm_from_marker[i], np.stack([near, far_mm])))
            if abs(float(normal @ (uv[0] - uv[1])) - apart) > STROKE_OUTLIER_CHI * sigma:
                far.add((i, k))
    return far


def _from_few_markers(ids, vids, every, marker_set: MarkerSet) -> NDArray[np.float64]:
    """``carm_from_drill`` (4, 4) from one or two markers: each marker's pose in C composed with its pose in D.

    With BB observations, the camera's constellation fitted to every BB (both planar solutions of each marker
    as starts, :func:`.video_claims.fit_constellation`); without, the first marker's pose alone (the corner PnP
    that follows uses every marker).
    """
    d_from_m = {i: drill_from_marker(vids[i].camera_from_tag, marker_set.by_id(i).tag_center_mm) for i in ids}
    starts = [t @ invert(d_from_m[i]) for i in ids for t in every[i].solutions]
    anchors = {i: every[i].observations for i in ids if every[i].observations or every[i].solution_observations}
    if not anchors:
        return starts[0]
    fits = [fit_constellation(a, {i: d_from_m[i] for i in a}, starts) for a in paired_anchors(anchors, every)]
    return min(fits, key=lambda f: f[1])[0]


# A marker whose RMS normalised residual at the end exceeds this (joint_solve's outlier_chi) fits no pose with the
# rest: a lone marker observed in several views is solved on each view alone (:func:`_settle_lone_marker_views`); of
# two markers, each is solved alone and the bound reaches both (:func:`_two_markers_alone`).
LONE_MARKER_MISFIT_CHI = 4.0
# Two markers fit together when one drill pose for both costs at most this much chi-square over their fits alone: the
# 99.9th percentile of chi-square with 6 degrees of freedom (the shared pose's six constraints). On the twin, pairs
# that fit together cost -12 to 7 (the stated noise is conservative), two that did not 62 and 948.
TWO_MARKERS_DISAGREE_CHI2 = 22.46
# A mirror solution whose chi-square exceeds the best by less than this (in units of the best fit's reduced
# chi-square) is not ruled out by the data: about a 4-sigma difference in one direction.
MIRROR_DELTA_CHI2 = 16.0
# The mirror start's first plain fit, beyond the best by this many times that margin, ends its solve there.
MIRROR_GIVE_UP = 100.0


def _settle_constellation_mirror(sol: JointSolution, view, solve: dict) -> tuple[JointSolution, NDArray[np.float64] | None, bool]:
    """One view: the better of the joint solution and its mirror image, the other one's ``carm_from_drill`` if it fits
    nearly as well, and whether that is the best's mirror image unrefined (both starts reached one solution).

    The markers lie on the skin, nearly in one plane, and the camera ties the drill rigidly to them: in one
    view the whole constellation has the planar ambiguity of a single marker (depth along the beam poorly
    fixed), and its mirror pose tilts the drill by about twice the plane's tilt to the beam. The mirror start
    reflects the constellation across the plane through its centroid perpendicular to the beam, then across
    its own plane (together a proper rotation about their intersection).
    """
    flip = _mirror_across_beam(sol, view)
    # A mirror whose first plain fit is far beyond the best (MIRROR_GIVE_UP times the margin that keeps it open) is not
    # worth the robust rounds, rejection and vote: on the twin they took 0.6-1.4 s of a single view's registration, and
    # only dropped BBs or markers from a fit already ruled out.
    give_up = sol.chi2 + MIRROR_GIVE_UP * MIRROR_DELTA_CHI2 * max(sol.reduced_chi2, 1.0)
    try:
        alt = joint_solve(carm_from_drill0=flip @ sol.carm_from_drill, carm_from_marker0={i: flip @ t for i, t in sol.carm_from_marker.items()},
                          give_up_above_chi2=give_up, **solve)
    except DrillnavError:
        return sol, None, False
    if set(alt.used_ids) != set(sol.used_ids):
        return sol, None, False
    best, other = (sol, alt) if sol.chi2 <= alt.chi2 else (alt, sol)
    if not _same_drill(best, other):
        return best, _left_open(best, other), False
    # Both starts reached one solution: the mirror is no minimum of its own, the refinement slides from it to the best.
    # Nearly face-on to the beam a marker's tilt shows only through its pattern's foreshortening (1 - cos), and a
    # pixel's bias (the intensifier's distortion across it, a BB's pull) turns it over; the mirror image itself may
    # still fit within the margin. Twin seed 11100 (flat markers, AP view alone, second drill pose): marker 10 alone,
    # 5.8 deg from face-on, both planar starts refined to a pose 12.7 deg off, its mirror image (unrefined) fitting
    # within the margin (chi-square 8.1 against 2.6 + 16); the axis lay 30 mm / 12.4 deg off under a 7.5 mm / 3.4 deg bound.
    # Both are judged on the same measurements (the best's own fit may have left BBs or corners out).
    flip = _mirror_across_beam(best, view)
    mirror = flip @ best.carm_from_drill
    inputs = {**solve, "observations": {i: solve["observations"][i] for i in best.used_ids}, "min_markers": len(best.used_ids)}
    try:
        here = joint_solve(carm_from_drill0=best.carm_from_drill, carm_from_marker0=best.carm_from_marker, refine=False, **inputs)
        there = joint_solve(carm_from_drill0=mirror, carm_from_marker0={i: flip @ t for i, t in best.carm_from_marker.items()}, refine=False, **inputs)
    except DrillnavError:
        return best, None, False
    if there.chi2 - here.chi2 < MIRROR_DELTA_CHI2 * max(here.reduced_chi2, 1.0):
        return best, mirror, True
    return best, None, False


def _half_way(best: JointSolution, mirror: NDArray[np.float64], solve: dict) -> JointSolution:
    """``best``, one marker's joint solution whose unrefined mirror image ``mirror`` (its ``carm_from_drill`` (4, 4)) fits
    about as well, taken half-way along the turn to it: the solution there, unrefined; ``best`` where it cannot be had.

    The mirror image of one marker is its own plane turned across the beam, face-on half-way. Nearly face-on, its tilt
    shows only through its pattern's foreshortening (1 - cos), so the noise on that tilts the fit away from face-on,
    and the data fit the whole turn about equally: half-way, the error is at most half the turn whichever end is true,
    and the bound spans to the mirror image as before. Twin seed 13000 (flat markers, AP+lateral, first pose): marker
    38 alone in the AP view, the axis 27.5 mm / 10.6 deg off at the best fit, 16.1 mm / 6.8 deg half-way (turn 11.1
    deg); seed 11100 (the AP view alone, second pose) 30.3 -> 14.6 mm; seed 18202 (a flat panel, the AP view alone),
    whose best fit was the nearer end, 7.3 -> 14.2 mm. With two markers or more the plane's tilt also
    shows through their magnifications: taken half-way too, 16 such registrations moved on 66 seeds with the markers flat
    and 69 with the surgeon's, 12 of them farther.
    """
    half = _turn_part(mirror @ invert(best.carm_from_drill), 0.5)
    inputs = {**solve, "observations": {i: solve["observations"][i] for i in best.used_ids}, "min_markers": len(best.used_ids)}
    try:
        return joint_solve(carm_from_drill0=half @ best.carm_from_drill, carm_from_marker0={i: half @ t for i, t in best.carm_from_marker.items()},
                           refine=False, **inputs)
    except DrillnavError:
        return best


def _turn_part(turn: NDArray[np.float64], share: float) -> NDArray[np.float64]:
    """``share`` of a rotation (4, 4) about a fixed axis (``turn``, no slide along its axis): the same axis, ``share`` of
    its angle."""
    point = np.linalg.lstsq(np.eye(3) - turn[:3, :3], turn[:3, 3], rcond=None)[0]  # a point on the axis
    part = Rotation.from_rotvec(share * Rotation.from_matrix(turn[:3, :3]).as_rotvec()).as_matrix()
    return make_transform(part, point - part @ point)


def _mirror_across_beam(sol: JointSolution, view) -> NDArray[np.float64]:
    """The proper rotation (4, 4) that takes ``sol``'s constellation to its mirror image in ``view``: across the plane
    through its centroid perpendicular to the beam, then across its own plane (one marker: the marker's plane)."""
    centres = np.array([sol.carm_from_marker[i][:3, 3] for i in sol.used_ids])
    centroid = centres.mean(axis=0)
    normal = np.linalg.svd(centres - centroid)[2][2] if len(centres) >= 3 else sol.carm_from_marker[sol.used_ids[0]][:3, 2]
    beam = centroid - view.source_position_mm
    beam /= np.linalg.norm(beam)
    rot = (np.eye(3) - 2.0 * np.outer(beam, beam)) @ (np.eye(3) - 2.0 * np.outer(normal, normal))
    return make_transform(rot, centroid - rot @ centroid)


def _same_drill(a: JointSolution, b: JointSolution) -> bool:
    """Whether two solutions turn the drill alike (within 0.5 deg): both starts reached the same solution."""
    return Rotation.from_matrix(a.carm_from_drill[:3, :3].T @ b.carm_from_drill[:3, :3]).magnitude() < np.radians(0.5)


def _left_open(best: JointSolution, other: JointSolution | None) -> NDArray[np.float64] | None:
    """``other``'s ``carm_from_drill`` when the data do not rule it out against ``best`` (within ``MIRROR_DELTA_CHI2``),
    None when they do, when there is none, or when both starts reached the same solution."""
    if other is None or _same_drill(best, other):
        return None
    return other.carm_from_drill if other.chi2 - best.chi2 < MIRROR_DELTA_CHI2 * max(best.reduced_chi2, 1.0) else None


def _settle_lone_marker_mirror(sol: JointSolution, pose: MarkerPose, solve: dict) -> tuple[JointSolution, NDArray[np.float64] | None]:
    """One marker, posed over several views, whose fluoroscopy pose leaves other solutions open (``pose.solutions``): the
    better of the joint solution and the solve from each other solution, and the other one's ``carm_from_drill`` if it
    fits nearly as well (as :func:`_settle_constellation_mirror`).

    The camera ties the drill rigidly to the marker: with one marker it cannot tell the marker's orientation in frame C,
    so a mirror the views leave open turns the drill with it. Twin seed 11702 (AP+lateral, second frame): marker 15
    alone, its pose 27 deg off in fluoroscopy with the mirror open, gave an axis 75 mm and 31 deg off under a 6.7 mm
    bound.
    """
    i = sol.used_ids[0]
    here = sol.carm_from_marker[i]
    give_up = sol.chi2 + MIRROR_GIVE_UP * MIRROR_DELTA_CHI2 * max(sol.reduced_chi2, 1.0)
    fits = [sol]
    for k, start in enumerate(pose.solutions):
        start = np.asarray(start)
        if Rotation.from_matrix(here[:3, :3].T @ start[:3, :3]).magnitude() < np.radians(2.0):
            continue  # the solution the joint solve started from (or reached)
        move = start @ invert(here)
        observations = pose.solution_observations[k] if pose.solution_observations else pose.observations
        try:
            alt = joint_solve(carm_from_drill0=move @ sol.carm_from_drill, carm_from_marker0={**sol.carm_from_marker, i: start}, give_up_above_chi2=give_up,
                              **{**solve, "observations": {**solve["observations"], i: observations}})
        except DrillnavError:
            continue
        if set(alt.used_ids) != {i}:
            continue
        fits.append(alt)
    # The other solution is the best of those that turn the drill otherwise: a start a few degrees from the joint
    # solve's (its fluoroscopy pose, 3.4 deg away) may reach that same solution again, and must not hide the mirror.
    # Twin seed 10901 (AP+lateral, second frame, a C-arm of 1000 / 600 mm source distances): marker 14 alone, posed in
    # the AP view with two BBs claimed in the lateral one, reached a pose 19.6 deg off from one start (chi-square 37.6)
    # and one 1.5 deg off from the other (38.8); the first start's copy stood in for the mirror, which was closed, and
    # the axis lay 46 mm off under a 6.5 mm bound.
    best = min(fits, key=lambda f: f.chi2)
    distinct = [f for f in fits if not _same_drill(best, f)]
    return best, _left_open(best, min(distinct, key=lambda f: f.chi2) if distinct else None)


def _settle_lone_marker_views(sol: JointSolution, solve: dict, drill_from_marker_: NDArray[np.float64]) -> tuple[JointSolution, NDArray[np.float64] | None]:
    """One marker left, fitting far beyond its noise (over ``LONE_MARKER_MISFIT_CHI``) over several views: the marker
    solved on each view's BBs alone with its tag (``drill_from_marker_`` (4, 4), from the camera), the best of those
    that fit, and the next one's ``carm_from_drill`` (None where only one fits); ``sol`` as it is where none does.

    Its views place it apart: one of them took another marker's ring for it (a pattern partly hidden matching the
    wrong design). With no other marker, nothing tells which view is right, so the bound reaches both. Twin seed
    11000 (random pair, second drill pose): view p-28s-23 identified marker 0's ring, five of its BBs seen, as marker
    22, 78 mm from where view p+16s-14 placed 22; solved together, the axis lay 74 mm and 56 deg off under a 28.5 mm bound.
    """
    i = sol.used_ids[0]
    observations = solve["observations"][i]
    fits = []
    for view in {id(o[0]): o[0] for o in observations}.values():
        own = tuple(o for o in observations if o[0] is view)
        try:
            starts = [t @ invert(drill_from_marker_) for o in own for t in planar_candidates(o[0], o[1], o[2])]
        except (ValueError, cv2.error):  # its BBs nearly collinear (edge-on in that view)
            continue
        if not starts:
            continue
        carm_from_drill0, _ = fit_constellation({i: own}, {i: drill_from_marker_}, starts)
        try:
            alt = joint_solve(carm_from_drill0=carm_from_drill0, carm_from_marker0={i: carm_from_drill0 @ drill_from_marker_},
                              **{**solve, "observations": {i: own}, "strokes": None})
        except DrillnavError:
            continue
        if alt.used_ids == (i,) and alt.marker_chi[i] <= LONE_MARKER_MISFIT_CHI:
            fits.append(alt)
    if not fits:
        return sol, None
    fits.sort(key=lambda f: f.marker_chi[i])
    return fits[0], _distinct_drill(fits[0], fits[1]) if len(fits) > 1 else None


def _two_markers_alone(sol: JointSolution, solve: dict) -> list[NDArray[np.float64]]:
    """:func:`_markers_alone`'s ``carm_from_drill`` (4, 4) each."""
    return [a.carm_from_drill for a in _markers_alone(sol, solve).values()]


def _seen_in_more_views(alone: dict[int, JointSolution], every: dict[int, MarkerPose]) -> JointSolution | None:
    """Of two markers that fit only alone (:func:`_markers_alone`), the one whose BBs two views or more observed, when
    it fits its own solution and the other's BBs one view alone: that marker's solution; None otherwise.

    One view leaves a marker's pose open along the beam and to its mirror image: posed there from a ring matched to
    the wrong marker, or on its mirror, it still fits alone (four BBs and a tag give its pose and the drill's with room
    to spare), while a marker posed over two views is pinned by both. Twin seed 29600 (random pair, both views, second
    pose): marker 38, posed on 4 BBs of the second view 93 mm off with its normal turned 161 deg, fitted alone at
    chi-square 0.0, marker 30 (5 and 3 BBs in the two views) at 13.6 (its RMS 0.36); together 2494, and the axis lay
    48.9 mm / 19.2 deg off (flagged).
    """
    if len(alone) != 2:
        return None
    views = {i: len({id(o[0]) for o in every[i].observations}) for i in alone}
    pinned = [i for i in alone if views[i] >= 2]
    if len(pinned) != 1 or min(views.values()) != 1:
        return None
    own = alone[pinned[0]]
    return own if own.marker_chi[pinned[0]] <= LONE_MARKER_MISFIT_CHI else None


def _markers_alone(sol: JointSolution, solve: dict) -> dict[int, JointSolution]:
    """Two markers that do not fit together: each marker solved alone on its BBs, strokes and tag, {marker id: its
    solution}; {} when they fit together, without a marker that gives no solution.

    Two markers that each fit alone but not together stay in the joint solve (its vote cannot tell which is wrong), and
    their fit's covariance, scaled by its reduced chi-square, need not reach either one's own solution. They do not fit
    together when one is over ``LONE_MARKER_MISFIT_CHI`` in the joint solve, or when sharing one drill pose costs the
    pair more chi-square than ``TWO_MARKERS_DISAGREE_CHI2`` over their two fits alone (the six constraints the shared
    pose adds). Twin seed 11901 (random pair, one view, first pose): marker 27, its tag at the frame's edge, posed on the
    two BBs its pairings agree on, dragged marker 19 to 17.8 mm off; the axis lay 16.8 deg off under an 8.8 deg bound.
    Seed 15102 (AP+lateral, the lateral view alone, first pose): marker 41 posed on four BBs 76 mm off, both markers
    under the misfit limit together (chi 1.8 and 4.0) but chi-square 953 against 1.6 + 3.7 alone; the axis lay 31.7 mm
    off under a 7.8 mm bound.
    """
    # Alone each fits at a chi-square of 0 or more: a pair within the limit together is within it over them too.
    if len(sol.used_ids) != 2 or (max(sol.marker_chi.values()) <= LONE_MARKER_MISFIT_CHI and sol.chi2 <= TWO_MARKERS_DISAGREE_CHI2):
        return {}
    alone: dict[int, JointSolution] = {}
    for i in sol.used_ids:
        own = {key: {i: solve[key][i]} if solve.get(key) and i in solve[key] else None for key in ("strokes", "rolls", "outlines")}
        try:
            alone[i] = joint_solve(carm_from_drill0=sol.carm_from_drill, carm_from_marker0={i: sol.carm_from_marker[i]},
                                   **{**solve, "observations": {i: solve["observations"][i]}, "min_markers": 1, **own})
        except DrillnavError:
            continue
    disagree = len(alone) == 2 and sol.chi2 - sum(a.chi2 for a in alone.values()) > TWO_MARKERS_DISAGREE_CHI2
    if max(sol.marker_chi.values()) <= LONE_MARKER_MISFIT_CHI and not disagree:
        return {}
    return alone


def _distinct_drill(best: JointSolution, other: JointSolution) -> NDArray[np.float64] | None:
    """``other``'s ``carm_from_drill`` unless both solutions turn the drill alike (within 0.5 deg) and place it alike (within 0.5 mm)."""
    if _same_drill(best, other) and np.linalg.norm(best.carm_from_drill[:3, 3] - other.carm_from_drill[:3, 3]) < 0.5:
        return None
    return other.carm_from_drill


def _spanning(covariance: NDArray[np.float64], carm_from_drill: NDArray[np.float64], mirror: NDArray[np.float64],
              pivot_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """``covariance`` (6, 6) widened to reach the mirror solution: plus the outer product of the perturbation (about ``pivot_mm``) to it.

    The frames after a joint solve keep its covariance but not its mirror (``pipeline.joint_refinement``): a
    covariance that spans the open mirror keeps them flagged. With the mirror at one sigma along its own
    direction, the 90 % bound lies past the mirror's axis.
    """
    r = mirror[:3, :3] @ carm_from_drill[:3, :3].T
    delta = np.concatenate([Rotation.from_matrix(r).as_rotvec(), mirror[:3, 3] - r @ (carm_from_drill[:3, 3] - pivot_mm) - pivot_mm])
    return covariance + np.outer(delta, delta)


def _camera_side(pose: MarkerPose, carm_from_tag_video: NDArray[np.float64]) -> tuple[NDArray[np.float64], tuple]:
    """(carm_from_marker (4, 4), observations): the marker's fluoroscopy pose, or the other solution it leaves open
    (:attr:`.MarkerPose.solutions`) whose normal is nearest the camera's; with the BBs that solution pairs where
    the solutions pair them differently (:attr:`.MarkerPose.solution_observations`)."""
    if pose.mirror_carm_from_marker is None:
        return pose.carm_from_marker, pose.observations
    normal = carm_from_tag_video[:3, 2]
    k = int(np.argmax([float(t[:3, 2] @ normal) for t in pose.solutions]))
    return np.asarray(pose.solutions[k]), pose.solution_observations[k] if pose.solution_observations else pose.observations


def _horn(ids, vids, poses):
    src = np.array([vids[i].position_camera_mm for i in ids])
    dst = np.array([poses[i].position_carm_mm for i in ids])
    w = np.array([1.0 / max(np.trace(vids[i].covariance_mm2), 1e-4) for i in ids])
    try:
        return absolute_orientation(src, dst, w / w.max())
    except DegenerateInput as exc:
        raise MarkersNotFound(f"markers usable for registration are degenerate: {exc}") from None


def _psd_root(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """A matrix ``L`` with ``L @ L.T == cov`` for a symmetric positive semi-definite ``cov`` (n, n).

    From its eigen-decomposition, negative round-off eigenvalues taken as 0: a covariance that is singular or
    nearly so (a direction the data do not fix, priors near zero) is sampled along the directions it has, where a
    Cholesky factorisation raised ``LinAlgError`` and the frame had no axis.
    """
    sym = 0.5 * (cov + cov.T)
    w, v = np.linalg.eigh(sym)
    return v * np.sqrt(np.clip(w, 0.0, None))


def predicted_axis_error(
    video: VideoDetections,
    marker_poses: tuple[MarkerPose, ...],
    registration: DrillRegistration,
    axis_drill: Line3D,
    *,
    working_point_carm_mm: NDArray[np.float64],
    fluoro_sigma_mm: float = 0.15,
    axis_sigma_mm: float = 0.1,
    axis_sigma_deg: float = 0.085,
    focal_rel_sigma: float = FOCAL_REL_SIGMA,
    samples: int = 64,
    seed: int = 0,
    position_limit_mm: float = RELIABLE_POSITION_MM,
    angle_limit_deg: float = RELIABLE_ANGLE_DEG,
    fluoro_poses: tuple[MarkerPose, ...] | None = None,
) -> PredictedError:
    """Error bounds of the axis from every input's uncertainty.

    With a joint solve (``registration.covariance_drill``): draws of the drill
    pose from its covariance (which already carries the camera's calibration
    uncertainty and the BBs' and corners' noise as their residuals show it), with the
    calibrated drill axis drawn from its own uncertainty (drill.json).
    Without: draws of the video X_D from their covariances with a common
    focal-length scale error, the fluoroscopy X_C with ``fluoro_sigma_mm``,
    each registered by Horn. The 90th and 95th percentiles of the axis's
    displacement at the working point and of its angle are the bounds;
    ``reliable`` is False when a 90 % bound exceeds its limit, when the registration rests on one marker whose tag was
    named by a code read in part (:func:`lone_name_unchecked`, judged on ``video``), and when it rests on one marker whose
    fluoroscopy pose does not stand alone (:func:`stands_alone`, judged on ``fluoro_poses``, the poses fluoroscopy
    gave before any joint solve refined them; default ``marker_poses``): nothing then checks that marker's BB
    correspondences, and a wrong one fits as well as the truth (on fresh seeds, a registration 128 mm and 59 deg
    off under a 2.2 mm bound, on a marker whose own pose missed its BBs by 15 px).

    ``axis_sigma_mm`` (per axis) and ``axis_sigma_deg`` (per tilt component) are the drill axis's
    calibration uncertainty: drill.json's ``residual_mm`` and ``residual_deg`` / sqrt(2) (an RMS tilt of
    ``residual_deg`` spread over the two directions that tilt the axis); the defaults are those of a
    0.1 mm / 0.12 deg calibration.
    """
    rng = np.random.default_rng(seed)
    axis_c = axis_drill.transformed(registration.carm_from_drill)
    s0 = float(np.dot(working_point_carm_mm - axis_c.point_mm, axis_c.direction))
    ref = axis_c.at(s0)[0]
    if registration.covariance_drill is not None:
        # A covariance is cheap to sample: enough draws for steady 90th/95th percentiles.
        n = max(samples, 512)
        delta = rng.normal(size=(n, 6)) @ _psd_root(registration.covariance_drill).T
        r = Rotation.from_rotvec(delta[:, :3]).as_matrix()
        pivot = registration.pivot_carm_mm
        carm_from_drill = np.repeat(registration.carm_from_drill[None], n, axis=0)
        carm_from_drill[:, :3, :3] = r @ registration.carm_from_drill[:3, :3]
        carm_from_drill[:, :3, 3] = np.einsum("bij,j->bi", r, registration.carm_from_drill[:3, 3] - pivot) + pivot + delta[:, 3:]
    elif len(registration.used_ids) < HORN_MIN_MARKERS:
        # Without the joint solve's covariance, one or two markers give no point-based draws: no bound to state.
        inf = float("inf")
        return PredictedError(position_mm=inf, angle_deg=inf, cone_half_angle_deg=inf, position90_mm=inf, angle90_deg=inf, reliable=False)
    else:
        n = samples
        vids = video.by_id()
        poses = {p.marker_id: p for p in marker_poses}
        ids = list(registration.used_ids)
        src = np.array([vids[i].position_camera_mm for i in ids])  # (N, 3)
        dst = np.array([poses[i].position_carm_mm for i in ids])
        chol = np.linalg.cholesky(np.array([vids[i].covariance_mm2 for i in ids]) + 1e-9 * np.eye(3))  # (N, 3, 3)
        # All draws at once (B samples): video points, common focal scale, fluoroscopy points.
        s = src + np.einsum("nij,bnj->bni", chol, rng.normal(size=(n, len(ids), 3)))
        s = s * (1.0 + rng.normal(scale=focal_rel_sigma, size=(n, 1, 1)))
        d = dst + rng.normal(scale=fluoro_sigma_mm, size=(n, *dst.shape))
        carm_from_drill = absolute_orientation_batch(s, d)  # (B, 4, 4)
    tilt = np.radians(axis_sigma_deg) * rng.normal(size=(n, 3))
    k = np.linalg.norm(tilt, axis=1, keepdims=True)
    unit = np.divide(tilt, k, out=np.zeros_like(tilt), where=k > 0)
    direction_d = np.cos(k) * axis_drill.direction + np.sin(k) * np.cross(unit, axis_drill.direction)
    point_d = axis_drill.point_mm + rng.normal(scale=axis_sigma_mm, size=(n, 3))
    point_c = np.einsum("bij,bj->bi", carm_from_drill[:, :3, :3], point_d) + carm_from_drill[:, :3, 3]
    direction_c = np.einsum("bij,bj->bi", carm_from_drill[:, :3, :3], direction_d)
    direction_c /= np.linalg.norm(direction_c, axis=1, keepdims=True)
    # Each drawn axis is scored as an error is: its point nearest the working point against the registered axis's
    # (``ref``). Not the drawn axis's distance from ``ref``: for an axis turned far (a one-marker mirror, 62 deg) that
    # is its foot from ``ref``, tens of millimetres nearer than its point at the working point.
    nearest = point_c + np.sum((working_point_carm_mm - point_c) * direction_c, axis=1, keepdims=True) * direction_c
    pos = np.linalg.norm(nearest - ref, axis=1)
    ang = np.degrees(np.arccos(np.clip(direction_c @ axis_c.direction, -1.0, 1.0)))
    p90, p95 = (float(v) for v in np.percentile(pos, [90, 95]))
    a90, a95 = (float(v) for v in np.percentile(ang, [90, 95]))
    # The data do not rule out the mirror solution, nor (two markers that fit only alone) each marker's own: the bounds
    # reach the axes they give.
    others = (() if registration.mirror_carm_from_drill is None else (registration.mirror_carm_from_drill,)) + tuple(registration.alone_carm_from_drill)
    for other in others:
        alt = axis_drill.transformed(other)
        alt_pos = float(np.linalg.norm(alt.closest_point(working_point_carm_mm) - ref))
        alt_ang = alt.angle_deg(axis_c)
        p90, p95, a90, a95 = max(p90, alt_pos), max(p95, alt_pos), max(a90, alt_ang), max(a95, alt_ang)
    return PredictedError(
        position_mm=p95, angle_deg=a95, cone_half_angle_deg=a95, position90_mm=p90, angle90_deg=a90,
        reliable=bool(p90 <= position_limit_mm and a90 <= angle_limit_deg) and not lone_unchecked(registration, marker_poses if fluoro_poses is None else fluoro_poses)
        and not lone_name_unchecked(registration, video),
    )


def stands_alone(pose: MarkerPose | None) -> bool:
    """Whether fluoroscopy alone fixed ``pose``: it converged on its BBs, no mirror solution is open, and its ring was
    identified at identify's own cost (not ``needs_camera``)."""
    return pose is not None and bool(pose.converged) and pose.mirror_carm_from_marker is None and not pose.needs_camera


def lone_name_unchecked(registration: DrillRegistration, video: VideoDetections) -> bool:
    """A registration on one marker whose tag was named by a code read in part (``named_among_posed``) that does not
    identify it dictionary-wide (not ``identified_by_code``): no other marker, and no code, checks the name."""
    if len(registration.used_ids) != 1:
        return False
    tag = video.by_id().get(registration.used_ids[0])
    return tag is not None and tag.named_among_posed and not tag.identified_by_code


def lone_unchecked(registration: DrillRegistration, fluoro_poses: tuple[MarkerPose, ...]) -> bool:
    """A registration on one marker whose fluoroscopy pose (of ``fluoro_poses``) does not stand alone."""
    if len(registration.used_ids) != 1:
        return False
    return not stands_alone({p.marker_id: p for p in fluoro_poses}.get(registration.used_ids[0]))
