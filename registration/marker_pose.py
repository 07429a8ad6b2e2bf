"""Marker poses in the C-arm frame from one or several views.

Known-component registration with the marker's design as the component: each
identified BB gives a 2D-3D correspondence. IPPE in every view that sees the
marker initialises the pose (planar target); both of its solutions are kept,
because a planar target seen nearly face-on in a weak-perspective view has two
poses that fit almost equally (mirror images about the line of sight, normals
apart by about twice the tilt). Each candidate is refined by Levenberg-Marquardt
over every BB in every view; the best fit wins, and the runner-up is kept as
``mirror_carm_from_marker`` when it fits nearly as well, so that the camera's
view of the tag can choose later (:mod:`drillnav.registration.joint_solve`).
A view whose BBs the marker's pattern pairs two ways nearly as well
(:attr:`.markers.Identification.alternative_bb_index`: a subset of the pattern
symmetric about a line, seen nearly edge-on) is solved with each pairing too.
When the two pairings' poses fit about as well (turned over about that line of
symmetry), the other is kept as the mirror, and the observations keep only the
BBs both pairings agree on, which fit either.
Each pose gets a residual (RMS px) and a convergence flag.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .carm import REFERENCE_PIXEL_MM, CArmView, intensifier_shift_px
from .fluoro_markers import FluoroDetections, blob_key
from .markers import MarkerSet
from .transforms import apply, from_rotvec, invert, make_transform, to_rotvec

__all__ = ["MarkerPose", "register_markers", "planar_candidates", "claim_bbs", "beam_image_px", "placing_claim", "MIRROR_RATIO",
           "MIN_CLAIM_PLACING_BBS", "MIN_LONE_CLAIM_PLACING_BBS"]


@dataclass(frozen=True, kw_only=True)
class MarkerPose:
    """carm_from_marker (4, 4); residual_px: RMS BB reprojection error over all views; n_views, n_points used."""

    marker_id: int
    carm_from_marker: NDArray[np.float64]
    residual_px: float
    n_views: int
    n_points: int
    converged: bool
    # The other planar solution when it fits within MIRROR_RATIO of the best (None: unambiguous).
    mirror_carm_from_marker: NDArray[np.float64] | None = None
    # (view, design BB centres (N, 3) mm, detected centres (N, 2) px) per view: the joint solve re-uses them.
    observations: tuple = ()
    # Further poses (4, 4) that fit within MIRROR_RATIO, where a view's BBs pair with the design two ways: the
    # pairings' poses and their mirrors, for the camera's view of the tag to choose among (:attr:`solutions`).
    further_solutions: tuple = ()
    # Per solution of :attr:`solutions`, the observations that solution's pairing makes (all of its BBs), where a
    # view's BBs pair two ways; () otherwise. ``observations`` then holds only the BBs every pairing agrees on.
    solution_observations: tuple = ()
    # (view, blob centres (N, 2) px) per view register_markers was given: the blobs no identified marker
    # claimed there. A marker the camera sees but fluoroscopy did not identify (edge-on, ambiguous ring)
    # claims its BBs among them by projection (:mod:`.video_claims`).
    view_blobs: tuple = ()
    # (view, blob centres (K, 2) px) per view of ``view_blobs``: those of its blobs whose footprint is no disc
    # (:attr:`.fluoro_markers.DetectedBB.places` False: merged with another BB's, a K-wire's or the ring's shadow). A
    # claim counts them; its observations leave them out (:func:`placing_claim`).
    non_disc_blobs: tuple = ()
    # (view, log image (H, W)) per view register_markers was given whose detections kept their image
    # (:attr:`.fluoro_markers.FluoroDetections.image_log`): an edge-on marker's ring stroke is measured there
    # (:mod:`.edge_on_ring`).
    view_images: tuple = ()
    # Posed from rings whose BB pattern matched this marker only at the looser cost a second witness allows
    # (:data:`.fluoro_markers.CORROBORATED_MAX_COST_MM`): its identity stands where the camera sees its tag, and
    # nowhere else (:func:`.video_fluoro.register_video_to_fluoro` leaves it out otherwise).
    needs_camera: bool = False
    # Posed from a ring that identified no marker, matched against this marker alone
    # (:attr:`.fluoro_markers.RejectedRing.loose`): a hypothesis, one of several a ring may carry, until the
    # camera's constellation bears it out (:func:`.video_claims.corroborate_loose`); never counted otherwise.
    loose: bool = False

    @property
    def position_carm_mm(self) -> NDArray[np.float64]:
        """X_C: the central BB in frame C."""
        return self.carm_from_marker[:3, 3].copy()

    @property
    def solutions(self) -> tuple[NDArray[np.float64], ...]:
        """Every pose (4, 4) fluoroscopy leaves open, best first: the pose, its mirror, the further solutions."""
        mirror = () if self.mirror_carm_from_marker is None else (self.mirror_carm_from_marker,)
        return (self.carm_from_marker, *mirror, *self.further_solutions)


# A mirror solution whose RMS residual is within this factor of the best is kept as an alternative:
# with 0.3 px BB noise the two planar solutions of a marker tilted under ~15 deg to the beam differ by less.
MIRROR_RATIO = 3.0


# BBs whose design positions spread less than this (mm, RMS across their best-fit line) are collinear: a line of BBs
# leaves the marker's turn about that line free, and no view poses it.
MIN_OFF_LINE_MM = 0.5


def planar_candidates(view: CArmView, obj: NDArray[np.float64], img: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Both planar solutions (carm_from_marker (4, 4)) of a marker from one view's BBs: design centres obj (N, 3) mm
    in the marker's plane (z = 0), detected centres img (N, 2) px, N >= 4.

    IPPE gives both. Its homography needs four points no three of which are collinear, and four BBs often have
    three on one line (the central BB between two opposite ones): there IPPE gives nothing, and SQPnP's solution is
    taken with its mirror, the same image in weak perspective: the layout turned half a turn in its plane, then the
    whole half a turn about the beam through the marker, its normal mirrored about that beam. Both are refined by
    the caller. Raises ValueError when the BBs are collinear (checked first: IPPE returns an arbitrary turn about
    their line) or no solution is found.
    """
    centred = obj[:, :2] - obj[:, :2].mean(axis=0)
    if len(obj) < 4 or np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(obj)) < MIN_OFF_LINE_MM:
        raise ValueError("the marker's BBs are collinear: no planar pose")
    k, source_from_carm = view.decompose()
    carm_from_source = invert(source_from_carm)
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, k, None, flags=cv2.SOLVEPNP_IPPE)
    if n:
        return [carm_from_source @ make_transform(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs)]
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok or float(tvec.ravel()[2]) <= 0.0:
        raise ValueError("no planar pose for the marker's BBs (IPPE and SQPnP failed)")
    rotation, t = cv2.Rodrigues(rvec)[0], tvec.ravel()
    beam = t / np.linalg.norm(t)
    half_turn_about_beam = 2.0 * np.outer(beam, beam) - np.eye(3)
    mirror = half_turn_about_beam @ rotation @ np.diag([-1.0, -1.0, 1.0])
    return [carm_from_source @ make_transform(r, t) for r in (rotation, mirror)]


def _refine(observations, carm_from_marker0: NDArray[np.float64]):
    rv0, t0 = to_rotvec(carm_from_marker0)

    def residual(x: NDArray[np.float64]) -> NDArray[np.float64]:
        t = from_rotvec(x[:3], x[3:])
        return np.concatenate([(view.project(apply(t, obj)) - img).ravel() for view, obj, img in observations])

    # Capped: a start on the wrong mirror side creeps for hundreds of steps towards the right one; the
    # right start converges in a few, and the other start is only needed as the mirror alternative.
    sol = least_squares(residual, np.concatenate([rv0, t0]), method="lm", xtol=1e-10, ftol=1e-10, max_nfev=60)
    r = sol.fun.reshape(-1, 2)
    return from_rotvec(sol.x[:3], sol.x[3:]), float(np.sqrt(np.mean(np.sum(r * r, axis=1)))), bool(sol.success)


def _distinct(a: NDArray[np.float64], b: NDArray[np.float64]) -> bool:
    return float(a[:3, 2] @ b[:3, 2]) < np.cos(np.radians(1.0)) or float(np.linalg.norm(a[:3, 3] - b[:3, 3])) > 0.5


def _planar_starts(observations) -> list[NDArray[np.float64]]:
    """Both planar solutions of the view with the most BBs that gives them (IPPE needs 4; a view with 3 claimed BBs
    only joins the refinement); [] when none does (every view's BBs nearly collinear: edge-on)."""
    for view, obj, img in sorted(observations, key=lambda o: -len(o[1])):
        if len(obj) < 4:
            break
        try:
            return planar_candidates(view, obj, img)
        except (ValueError, cv2.error):  # BBs nearly collinear (edge-on): try the next view
            continue
    return []


def _agreed(a: tuple, b: tuple) -> tuple:
    """Per view of ``a``, the (view, design centres, detected centres) that pairings ``a`` and ``b`` both make (a
    view where they make none, or that ``b`` lacks, left out)."""
    out = []
    for view, obj_a, img_a in a:
        other = next(((o, i) for v, o, i in b if v is view), None)
        if other is None:
            continue
        obj_b, img_b = other
        keep = [k for k in range(len(obj_a))
                if any(np.allclose(img_a[k], img_b[j]) and np.allclose(obj_a[k], obj_b[j]) for j in range(len(obj_b)))]
        if keep:
            out.append((view, obj_a[keep], img_a[keep]))
    return tuple(out)


def _open(fits: list) -> MarkerPose | None:
    """The pose of the best of ``fits`` ([MarkerPose] of one marker, each on its own pairing of the BBs, best first),
    with the others that fit nearly as well on as many BBs left open as its solutions (:attr:`MarkerPose.solutions`,
    each with its pairing's observations); None when ``fits`` is empty."""
    if not fits:
        return None
    best = fits[0]
    rivals = [f for f in fits[1:] if f.n_points == best.n_points and f.residual_px <= MIRROR_RATIO * max(best.residual_px, 0.1)
              and _distinct(f.carm_from_marker, best.carm_from_marker)]
    if not rivals:
        return best
    agreed = _agreed(best.observations, rivals[0].observations)
    return replace(best, mirror_carm_from_marker=rivals[0].carm_from_marker, further_solutions=tuple(f.carm_from_marker for f in rivals[1:]),
                   solution_observations=(best.observations, *(f.observations for f in rivals)), observations=agreed,
                   n_views=len(agreed), n_points=sum(len(o[1]) for o in agreed))


def _solve_one(marker_id: int, observations: list[tuple[CArmView, NDArray[np.float64], NDArray[np.float64]]], max_residual_px: float,
               alternatives: list | tuple = ()) -> MarkerPose:
    """``alternatives``: per view of ``observations``, that view's BBs paired with the design the other way (None:
    paired one way only); each is tried in place of its view's observations, one view at a time."""
    variants = [tuple(observations)]
    for j, alt in enumerate(alternatives):
        if alt is not None:
            variants.append(tuple(alt if k == j else o for k, o in enumerate(observations)))
    # Both planar solutions of each pairing, refined over every view: the wrong mirror no longer fits the others.
    fits = sorted(((*_refine(obs, c), obs) for obs in variants for c in _planar_starts(obs)), key=lambda f: f[1])
    if not fits:
        raise ValueError(f"marker {marker_id}: no view's BBs give a planar pose (IPPE failed)")
    pose, rms, success, obs = fits[0]
    near = [f for f in fits[1:] if _distinct(f[0], pose) and f[1] <= MIRROR_RATIO * max(rms, 0.1)]
    turned = next((f for f in near if f[3] is not obs), None)
    further: tuple = ()
    if turned is not None:
        # The other pairing fits about as well: the pose turned over about the pattern's line of symmetry. Every
        # solution that fits nearly as well stays open for the camera's view of the tag to settle, and only the
        # BBs both pairings agree on stay observed (they fit either).
        kept: list = []
        for f in near:
            if all(_distinct(f[0], k[0]) for k in kept):
                kept.append(f)
        mirror, further = kept[0][0], tuple(f[0] for f in kept[1:])
        paired, obs = (obs, *(f[3] for f in kept)), _agreed(obs, turned[3])
    else:
        mirror, paired = next((f[0] for f in near), None), ()
    return MarkerPose(
        marker_id=marker_id,
        carm_from_marker=pose,
        residual_px=rms,
        n_views=len(obs),
        n_points=sum(len(o[1]) for o in obs),
        converged=bool(success and rms <= max_residual_px),
        mirror_carm_from_marker=mirror,
        further_solutions=further,
        solution_observations=paired,
        observations=tuple(obs),
    )


def _try_solve(marker_id: int, observations, max_residual_px: float, alternatives: list | None = None) -> MarkerPose | None:
    """A marker whose BBs give no planar pose in any view (nearly collinear) is left out, not fatal to the others.

    Solved over all the views that identified it; when that does not converge and exactly one view alone does,
    that view's pose is kept: the other view's BBs were matched wrongly (clutter inside the ring, a BB merged with
    metal) and must not leave the marker without a pose. When several views converge alone but not together,
    nothing tells which is right (each has its mirror), and the joint result stands, not converged.
    """
    alternatives = alternatives or [None] * len(observations)
    try:
        pose = _solve_one(marker_id, observations, max_residual_px, alternatives)
    except ValueError:
        pose = None
    if (pose is not None and pose.converged) or len(observations) < 2:
        return pose
    alone = []
    for obs, alt in zip(observations, alternatives):
        try:
            alone.append(_solve_one(marker_id, [obs], max_residual_px, [alt]))
        except ValueError:
            continue
    good = [p for p in alone if p.converged]
    return good[0] if len(good) == 1 else pose


# A marker-view keeps its BBs whose blob is no disc unless this many others pose it (see _paired). On the
# operating-room twin (seeds 10400-10405, every pair, M = 5, 93 registrations) leaving them out only where five
# remain moved 16 registrations, 10 nearer the truth (3.0 -> 1.2 mm, 1.4 -> 0.8 mm); leaving them out everywhere,
# and out of the blobs a marker may claim, lost a lateral view's second marker (0.4 -> 149 mm, flagged).
MIN_PLACING_BBS = 5
# A claim (a marker's BBs found by projection in a view that did not identify it, from another view's pose or the
# camera's constellation) finds its BBs among every blob, and leaves the blobs that are no disc out of its
# observations where this many round ones remain. Edge-on in a lateral view a marker's BBs merge: on the
# operating-room twin (seed 10800, AP+lateral) a claimed blob of elongation 1.46 lay 2.94 px off its BB where the
# other claimed BBs were within 0.1 px (against the twin's distorted truth); left out, the two-view registration went
# from 1.35 to 0.90 mm off at the entry (docs/identity_and_error.md).
MIN_CLAIM_PLACING_BBS = 2
# A claim that is all a marker's fluoroscopy shows (the camera's marker, identified in no view) places it alone: the
# camera fixes its orientation, and the claimed BBs its position, depth from their spread. There the misshapen blobs
# are left out only where this many round ones remain: two round BBs of a marker cut by the field's edge placed it
# 2.2 mm off at the entry where its third, cut blob kept it at 0.6 mm (seeds 10400 and 10802, one view, measured).
MIN_LONE_CLAIM_PLACING_BBS = 3


def placing_claim(design_mm: NDArray[np.float64], blobs_px: NDArray[np.float64], non_disc: set, *, alone: bool = False
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A claim's design BBs (N, 3) and blob centres (N, 2) without the blobs whose keys (:func:`.fluoro_markers.blob_key`) are in
    ``non_disc``, where at least :data:`MIN_CLAIM_PLACING_BBS` remain (``alone``, the claim is all the marker's
    fluoroscopy shows: :data:`MIN_LONE_CLAIM_PLACING_BBS`); as they are otherwise."""
    if not non_disc:
        return design_mm, blobs_px
    keep = np.array([blob_key(c) not in non_disc for c in blobs_px], dtype=bool)
    if keep.all() or keep.sum() < (MIN_LONE_CLAIM_PLACING_BBS if alone else MIN_CLAIM_PLACING_BBS):
        return design_mm, blobs_px
    return np.asarray(design_mm)[keep], np.asarray(blobs_px)[keep]


def _paired(view: CArmView, marker, bb_index: NDArray[np.int64], marker_set: MarkerSet):
    """(view, design BB centres (N, 3) mm, detected centres (N, 2) px) of ``marker``'s BBs (a
    :class:`.fluoro_markers.DetectedMarker`) paired with the design by ``bb_index`` (N,); None under 4 paired.

    A BB whose blob is no disc (:attr:`.fluoro_markers.DetectedBB.places`: merged with a K-wire's or another BB's
    shadow, cut by the field's edge; its centroid lies pixels off the BB's centre) is left out where at least
    ``MIN_PLACING_BBS`` others pose the marker; with fewer, every paired BB counts (a steep view's crowded BBs are
    what poses its marker at all, and the joint solve charges a crowded BB its detector's pull)."""
    ok = bb_index >= 0
    placing = ok & np.array([b.places for b in marker.bbs], dtype=bool)
    if placing.sum() >= MIN_PLACING_BBS:
        ok = placing
    if ok.sum() < 4:
        return None
    obj = marker_set.by_id(marker.marker_id).bb_centers_mm[bb_index[ok]]
    img = np.array([b.center_px for b, keep in zip(marker.bbs, ok) if keep])
    return view, obj, img


def register_markers(
    detections: list[FluoroDetections],
    views: list[CArmView],
    marker_set: MarkerSet,
    *,
    max_residual_px: float = 1.5,
    workers: int = 2,
) -> tuple[MarkerPose, ...]:
    """Pose of every marker identified in at least one view, solved jointly over the views that see it.

    Markers are independent, so they are solved in parallel (threads: the work is in numpy/OpenCV).
    """
    if len(detections) != len(views):
        raise ValueError(f"{len(detections)} detection sets for {len(views)} views")
    per_marker: dict[int, list] = {}
    alternatives: dict[int, list] = {}
    for det, view in zip(detections, views):
        for m in det.markers:
            found = _paired(view, m, m.bb_index, marker_set)
            if found is None:
                continue
            per_marker.setdefault(m.marker_id, []).append(found)
            alternatives.setdefault(m.marker_id, []).append(None if m.alternative_bb_index is None else _paired(view, m, m.alternative_bb_index, marker_set))
    # Rings whose pattern matched a marker only at the looser cost, that marker identified in no view: posed too,
    # marked as needing the camera's corroboration.
    identified = set(per_marker) | {m.marker_id for det in detections for m in det.markers}
    per_candidate: dict[int, list] = {}
    candidate_alternatives: dict[int, list] = {}
    for det, view in zip(detections, views):
        for m in det.candidates():
            found = None if m.marker_id in identified else _paired(view, m, m.bb_index, marker_set)
            if found is None:
                continue
            per_candidate.setdefault(m.marker_id, []).append(found)
            candidate_alternatives.setdefault(m.marker_id, []).append(
                None if m.alternative_bb_index is None else _paired(view, m, m.alternative_bb_index, marker_set))
    # Rings that identified no marker, matched against each marker alone (identified in no view, no candidate): per
    # marker the ring it matches best, posed as a hypothesis for the camera's constellation to settle.
    per_loose: dict[int, tuple] = {}
    for det, view in zip(detections, views):
        for r in det.rejected:
            for m in r.loose:
                found = None if m.marker_id in identified or m.marker_id in per_candidate else _paired(view, m, m.bb_index, marker_set)
                if found is None:
                    continue
                key = (m.identification_cost_mm, -len(found[1]))
                if m.marker_id not in per_loose or key < per_loose[m.marker_id][0]:
                    alt = None if m.alternative_bb_index is None else _paired(view, m, m.alternative_bb_index, marker_set)
                    per_loose[m.marker_id] = (key, [found], [alt])
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        poses = [p for p in pool.map(lambda item: _try_solve(item[0], item[1], max_residual_px, alternatives[item[0]]), sorted(per_marker.items()))
                 if p is not None]
        poses += [replace(p, needs_camera=True)
                  for p in pool.map(lambda item: _try_solve(item[0], item[1], max_residual_px, candidate_alternatives[item[0]]), sorted(per_candidate.items()))
                  if p is not None]
        poses += [replace(p, needs_camera=True, loose=True)
                  for p in pool.map(lambda item: _try_solve(item[0], item[1][1], max_residual_px, item[1][2]), sorted(per_loose.items()))
                  if p is not None and p.converged]
    if len(views) >= 2:
        poses = _rings_taken_back(poses, detections, views, marker_set, max_residual_px)
    # Blobs of each view that no identified marker explains: the unidentified markers' BBs are among them.
    # Only markers that got a pose claim their blobs: one identified but not posed (IPPE failed: its BBs nearly collinear)
    # leaves them free, for the video's identities to claim.
    # A view whose identification of a marker its pose left out (the views did not converge together: that view's BBs
    # paired wrongly) claims none of its blobs: the pose claims them there by projection, paired anew.
    posed_in = {p.marker_id: {id(o[0]) for o in p.observations} for p in poses}
    claimed = [{blob_key(b.center_px) for m in det.markers if id(view) in posed_in.get(m.marker_id, ()) for b in m.bbs}
               | {blob_key(c) for p in poses if not (p.loose or p.needs_camera) for v, _, img in p.observations if v is view for c in img}
               for det, view in zip(detections, views)]
    free = [np.array([b.center_px for b in det.blobs if blob_key(b.center_px) not in claimed[k]]).reshape(-1, 2) for k, det in enumerate(detections)]
    non_disc = [{blob_key(b.center_px) for b in det.blobs if not b.places and blob_key(b.center_px) not in claimed[k]} for k, det in enumerate(detections)]
    blobs = dict(view_blobs=tuple(zip(views, free)),
                 non_disc_blobs=tuple((v, np.array(sorted(n)).reshape(-1, 2)) for v, n in zip(views, non_disc)),
                 view_images=tuple((v, det.image_log) for det, v in zip(detections, views) if det.image_log is not None))
    if len(views) < 2:
        return tuple(replace(p, **blobs) for p in poses)
    # A marker identified in one view but not in another (edge-on in a lateral view, rings overlapping)
    # claims its BBs there by projection from its pose, then is solved again over both views.
    out = []
    for pose in poses:
        if pose.loose:  # a hypothesis: it claims nothing in the other views before the camera bears it out
            out.append(replace(pose, **blobs))
            continue
        design = marker_set.by_id(pose.marker_id).bb_centers_mm
        claim = dict(views=views, free=free, non_disc=non_disc, design=design, max_residual_px=max_residual_px)
        if pose.solution_observations:
            # Its BBs pair two ways: each solution claims in the other views with the BBs its own pairing makes. The
            # right one also finds the BBs the symmetric part lacks; where both find as many, both stay open.
            tries = [_claimed_elsewhere(pose.marker_id, start, obs, (start,), **claim) for start, obs in zip(pose.solutions, pose.solution_observations)]
            tries = sorted((t for t in tries if t is not None and t.converged), key=lambda t: (-t.n_points, t.residual_px))
            pose = _open(tries) or pose
        else:
            again = _claimed_elsewhere(pose.marker_id, pose.carm_from_marker, pose.observations, pose.solutions, **claim)
            if again is not None and (again.converged or not pose.converged):
                pose = again
        out.append(replace(pose, **blobs))
    return tuple(out)


def _one_view(pose: MarkerPose, *, paired_two_ways: bool = False) -> int | None:
    """id() of the one view whose BBs pose ``pose``; None when several do, when it is a hypothesis, and (unless
    ``paired_two_ways``) when its BBs pair with the design two ways."""
    if pose.loose or pose.needs_camera or (pose.solution_observations and not paired_two_ways) or not pose.converged:
        return None
    seen = {id(o[0]) for o in pose.observations}
    return next(iter(seen)) if len(seen) == 1 else None


def _rings_taken_back(poses: list, detections: list[FluoroDetections], views: list[CArmView], marker_set: MarkerSet,
                      max_residual_px: float) -> list:
    """``poses`` with each ring identified in one view only as marker B given to marker A instead, where A, identified
    in one other view only, claims B's BBs there by projection from its pose and fits both views at ``max_residual_px``,
    and B's ring is the flatter of the two (nearer edge-on, where the pattern tells less).

    Two markers cannot lie at one place: a ring where another view's marker projects its own pattern is that marker's,
    and an edge-on ring's few distinguishable BB heights fit another marker's pattern as well as its own. Twin seed
    31801 (flat markers, AP+lateral, second pose): marker 29 posed in the AP view, its ring edge-on in the lateral view
    (axes 0.12 apart) identified as marker 45 at 0.59 mm; the camera saw 45's tag, and the registration on the two
    disagreeing markers was 151 mm off (flagged).
    """
    rings = {(m.marker_id, id(view)): (min(m.ring_ellipse[1]) / max(max(m.ring_ellipse[1]), 1e-9), np.array([b.center_px for b in m.bbs]).reshape(-1, 2))
             for det, view in zip(detections, views) for m in det.markers}
    out = list(poses)
    for a in list(out):
        va = _one_view(a)
        if va is None or not any(p is a for p in out):  # by identity: a pose holds arrays, which == cannot compare
            continue
        for b in list(out):
            vb = _one_view(b, paired_two_ways=True)
            if vb is None or b is a or vb == va or (a.marker_id, vb) in rings or (b.marker_id, vb) not in rings:
                continue
            ratio_b, blobs_b = rings[(b.marker_id, vb)]
            if ratio_b >= rings[(a.marker_id, va)][0]:
                continue
            free = [blobs_b if id(v) == vb else np.zeros((0, 2)) for v in views]
            trial = _claimed_elsewhere(a.marker_id, a.carm_from_marker, a.observations, a.solutions, views=views, free=free,
                                       non_disc=[set() for _ in views], design=marker_set.by_id(a.marker_id).bb_centers_mm,
                                       max_residual_px=max_residual_px)
            if trial is None or not trial.converged:
                continue
            if sum(len(o[2]) for o in trial.observations if id(o[0]) == vb) < CROSS_VIEW_SLID_MIN_BBS:
                continue
            out = [trial if p is a else p for p in out if p is not b]
            break
    return out


def _claimed_elsewhere(marker_id: int, start: NDArray[np.float64], observations: tuple, slide_starts, *, views, free, non_disc, design,
                       max_residual_px: float) -> MarkerPose | None:
    """The marker solved again over ``observations`` and the BBs it claims among the ``free`` blobs of the views
    they lack, by projection from ``start`` (4, 4), less the claimed blobs that are no disc (``non_disc``: per view,
    a set of :func:`.fluoro_markers.blob_key`; :func:`placing_claim`); None when it claims none.

    Posed in one view, the marker's depth along that view's beam is poorly fixed (4-7 BBs in low dose: 5-12 mm), which
    slides its pattern in another view along that beam's image; and both planar solutions stay open: each of
    ``slide_starts`` then also claims sliding along it.
    """
    seen = {id(o[0]) for o in observations}
    source = observations[0][0] if len(seen) == 1 else None
    extra = []
    for k, view in enumerate(views):
        if id(view) in seen or not len(free[k]):
            continue
        found = claim_bbs(view, start, design, free[k])
        if found is None and source is not None:
            for s in slide_starts:
                found = claim_bbs(view, s, design, free[k], search_px=CROSS_VIEW_ACROSS_PX, tol_px=CROSS_VIEW_SLID_TOL_PX, min_bbs=CROSS_VIEW_SLID_MIN_BBS,
                                  slide_px=beam_image_px(view, source, s[:3, 3], CROSS_VIEW_SLIDE_MM))
                if found is not None:
                    break
        if found is not None:
            extra.append((view, *placing_claim(*found, non_disc[k])))
    if not extra:
        return None
    every = list(observations) + extra
    try:
        return _solve_one(marker_id, every, float(np.hypot(max_residual_px, intensifier_allowance_px(every))))
    except ValueError:
        return None


def intensifier_allowance_px(observations) -> float:
    """The largest 1-sigma shift (px) an image intensifier's uncorrected distortion can put on a marker's BBs in one of
    ``observations``' views (``CArmView.distortion_sigma_px`` at the field's corner, growing with the cube of the
    radius: :func:`.carm.intensifier_shift_px`); 0 on flat panels. One marker's fit over two such views cannot take
    up both views' shifts at once: what is left of them is in its residual."""
    out = 0.0
    for view, _design, img in observations:
        if view.distortion_sigma_px > 0 and len(img):
            centre_px = np.asarray(img, dtype=np.float64).mean(axis=0)
            shift = intensifier_shift_px(centre_px, view.center_px, view.corner_radius_px, np.array([view.distortion_sigma_px, 0.0]))
            out = max(out, float(np.linalg.norm(shift)))
    return out


# A marker posed in one view claims its BBs in another view sliding along the image of the first view's beam,
# this far in depth (either sense) and this far across it, asking then for this many BBs on one shift; the marker
# is then solved over both views, and kept so only when that fit converges (its RMS within ``max_residual_px``
# combined with what an intensifier's distortion leaves: :func:`intensifier_allowance_px`).
CROSS_VIEW_SLIDE_MM = 25.0
CROSS_VIEW_ACROSS_PX = 20.0
CROSS_VIEW_SLID_MIN_BBS = 4
CROSS_VIEW_SLID_TOL_PX = 3.5  # low-dose BB centres scatter 1-3 px, and a one-view pose's tilt bends the pattern a little


def beam_image_px(view: CArmView, source_view: CArmView, position_carm_mm: NDArray[np.float64], depth_mm: float) -> NDArray[np.float64]:
    """(2,) the image in ``view`` of ``depth_mm`` along ``source_view``'s ray through ``position_carm_mm`` (3,), px."""
    ray = position_carm_mm - source_view.source_position_mm
    ray = ray / np.linalg.norm(ray)
    ends = view.project(np.stack([position_carm_mm - depth_mm * ray, position_carm_mm + depth_mm * ray]))
    return (ends[1] - ends[0]) / 2.0


def claim_bbs(view: CArmView, carm_from_marker, design_bbs_mm, blobs_px, *, search_px: float = 60.0, tol_px: float = 2.5, min_bbs: int = 3,
              slide_px: NDArray[np.float64] | None = None, distortion_px: NDArray[np.float64] | None = None):
    """The design BBs (N, 3) and blob centres (N, 2) a pose explains in a view, after the best common shift.

    The pose from one view is off along that view's beam by a millimetre or two, which shifts the whole
    projected pattern in another view: each (design BB, blob) pair proposes a shift, the one that matches
    most BBs wins. None when fewer than ``min_bbs`` match, or when a shift that places the pattern elsewhere (over
    two tolerances away) matches as many: an ambiguous claim is none.

    search_px, tol_px : in the reference detector's pixels (:data:`.carm.REFERENCE_PIXEL_MM`), so the same
        millimetres on any detector; converted to ``view``'s own here.
    slide_px : (2,) in ``view``'s own pixels: the farthest the pattern may slide along one image direction (px, in either sense), on
        top of ``search_px`` across it: the image in this view of the pose's depth uncertainty along another
        view's beam (an epipolar line). None: ``search_px`` in every direction.
    distortion_px : (2,) the view's intensifier distortion (:meth:`.carm.CArmView.distorted_px`) the BBs are predicted
        with; None: none (a flat panel, or none estimated).
    """
    if len(blobs_px) < min_bbs:
        return None
    per_px = REFERENCE_PIXEL_MM / float(view.pixel_spacing_mm[1])
    search_px, tol_px = search_px * per_px, tol_px * per_px
    pred = view.distorted_px(view.project(apply(carm_from_marker, design_bbs_mm)), distortion_px)
    shifts = (blobs_px[None, :, :] - pred[:, None, :]).reshape(-1, 2)
    if slide_px is None:
        shifts = shifts[np.hypot(shifts[:, 0], shifts[:, 1]) <= search_px]
    else:
        reach = float(np.linalg.norm(slide_px))
        along = shifts @ (np.asarray(slide_px, dtype=np.float64) / max(reach, 1e-9))
        across = np.sqrt(np.maximum(np.sum(shifts * shifts, axis=1) - along * along, 0.0))
        shifts = shifts[(across <= search_px) & (np.abs(along) <= reach + search_px)]
    if not len(shifts):
        return None
    d = np.linalg.norm(pred[None, :, None, :] + shifts[:, None, None, :] - blobs_px[None, None], axis=3)  # (S, N, B)
    j = np.argmin(d, axis=2)
    near = np.take_along_axis(d, j[:, :, None], axis=2)[:, :, 0]
    ok = near <= tol_px
    tried = []
    for k in np.argsort(-ok.sum(axis=1), kind="stable")[:8]:
        keep = _one_bb_per_blob(ok[k], j[k], near[k])
        tried.append((int(keep.sum()), keep, j[k], shifts[k]))
    n_best = max(t[0] for t in tried)
    if n_best < min_bbs:
        return None
    _, ok, j, shift = next(t for t in tried if t[0] == n_best)
    # As many BBs on a shift that places the pattern elsewhere (farther than two tolerances: not the same match with
    # one pair's shift for another's) is no claim: which of the two is the marker nothing here tells.
    if any(t[0] == n_best and np.hypot(*(t[3] - shift)) > 2.0 * tol_px for t in tried):
        return None
    return np.asarray(design_bbs_mm)[ok], blobs_px[j[ok]]


def _one_bb_per_blob(ok: NDArray[np.bool_], blob_of: NDArray[np.intp], dist_px: NDArray[np.float64]) -> NDArray[np.bool_]:
    """``ok`` (N,) with each blob kept for the nearest of the BBs it explains only (``blob_of`` (N,): each BB's nearest
    blob, ``dist_px`` (N,): how far). Edge-on, a marker's BBs merge: a merged blob is one BB, not two. Dropping the
    further BB, not the whole shift, keeps the shift that puts the marker where it is: rejecting it let a shift by one
    BB spacing along the edge-on line win on three BBs (seed 13402's lateral view, flat markers: 27 px off)."""
    keep = ok.copy()
    order = np.argsort(dist_px, kind="stable")
    taken: set[int] = set()
    for i in order:
        if keep[i]:
            b = int(blob_of[i])
            if b in taken:
                keep[i] = False
            taken.add(b)
    return keep
