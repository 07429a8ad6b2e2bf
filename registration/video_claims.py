"""Identity from the video: markers the camera sees claim their BBs in views where fluoroscopy did not identify them.

A marker seen edge-on (lateral views: markers lie on the anterior skin), or
whose ring is ambiguous, is not identified from its X-ray pattern alone, and
with one view fewer than three markers may remain. The camera sees every tag
with its identity and its pose in the drill frame D, so the markers the camera
sees form one rigid constellation in D. Fitted to the BBs of the markers that
fluoroscopy did identify (one is enough: six unknowns, four or more BBs each),
the constellation predicts every other marker's BBs in every view; the free
blobs there that match a marker's predicted pattern (after a small common
shift, which absorbs the depth error along the beam) become that marker's
observations, and the joint solve takes it like any other.

Pure math: numpy and scipy.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .fluoro_markers import blob_key
from .marker_pose import MarkerPose, beam_image_px, claim_bbs, placing_claim
from .markers import MarkerSet
from .transforms import apply, from_rotvec, invert, make_transform, to_rotvec
from .video_markers import VideoDetections

__all__ = ["drill_from_marker", "fit_constellation", "constellation_fits", "claim_from_video", "claim_from_solution", "corroborate_loose",
           "with_claims", "LOOSE_MIN_CLAIMED_BBS"]

# After the constellation fit the prediction is off by the camera's tag pose error (about a millimetre at
# the marker: ~5 px) and the depth along the beam: a small common shift, well below a neighbour's distance.
SEARCH_PX = 30.0
# Each BB within this of its shifted prediction: low-dose BB centres scatter by 1-3 px (measured on the
# degraded twin), where the cross-view claim's 2.5 px lost markers; 3 BBs on one common shift within a
# 30 px search still do not happen by chance among a view's few dozen blobs.
TOL_PX = 3.5
# Anchors seen in one view only fix the constellation's depth along that view's beam poorly: a marker of 4
# BBs in low dose can sit 10-15 mm off along it (seed 6301, measured). In another view the prediction then
# slides along the image of that beam, so the claim searches this far along it (either sense), asking for
# SLID_MIN_BBS BBs on one shift when the shift goes past SEARCH_PX.
SLIDE_MM = 25.0
SLID_MIN_BBS = 4
# After the joint solve, a marker whose BBs a view still does not show where its pose predicts them is looked for at
# tilts of that pose up to this, in these steps, about either axis in its plane, on at least TILTED_MIN_BBS BBs; a marker
# observed in one view only slides SLIDE_MM along that view's beam's image as well.
TILT_SEARCH_DEG = 15.0
TILT_STEP_DEG = 2.5
TILTED_MIN_BBS = 4


def drill_from_marker(camera_from_tag: NDArray[np.float64], tag_center_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """The marker frame (4, 4) in frame D from the tag's pose: the tag sits at ``tag_center_mm`` in the marker frame."""
    return np.asarray(camera_from_tag, dtype=np.float64) @ make_transform(np.eye(3), -np.asarray(tag_center_mm, dtype=np.float64))


def paired_anchors(anchors: dict[int, tuple], by_id: dict) -> list[dict[int, tuple]]:
    """``anchors`` ({marker id: observations}) with each marker whose BBs pair two ways
    (:attr:`.marker_pose.MarkerPose.solution_observations`, ``by_id``: {id: MarkerPose}) anchoring with each
    pairing in turn, all its BBs; ``[anchors]`` when no marker's do."""
    variants = [{**anchors, i: obs} for i in anchors for obs in by_id[i].solution_observations]
    return variants or [anchors]


def fit_constellation(anchors: dict[int, tuple], drill_from_marker_: dict[int, NDArray[np.float64]],
                      starts: list[NDArray[np.float64]]) -> tuple[NDArray[np.float64], float]:
    """``carm_from_drill`` (4, 4) and the RMS BB residual (px) of the camera's marker constellation fitted to fluoroscopy.

    anchors : {marker id: ((CArmView, design BB centres (N, 3) mm, detected centres (N, 2) px), ...)}.
    drill_from_marker_ : {marker id: (4, 4)} from the camera.
    starts : candidate ``carm_from_drill`` (4, 4); the best fit over all of them wins (a single marker's
        planar pose has a mirror solution, so both are tried).
    """
    return constellation_fits(anchors, drill_from_marker_, starts)[0]


def constellation_fits(anchors: dict[int, tuple], drill_from_marker_: dict[int, NDArray[np.float64]],
                       starts: list[NDArray[np.float64]]) -> list[tuple[NDArray[np.float64], float]]:
    """The fits of :func:`fit_constellation` from the two starts that fit best as they are, best first.

    Anchors in one view only may fit both a solution and its mirror as well (a single marker's planar
    ambiguity); the caller settles which with what else it knows (another view's blobs).
    """
    pts, img, proj = [], [], []
    for i, obs in anchors.items():
        for view, obj, px in obs:
            pts.append(apply(drill_from_marker_[i], obj))
            img.append(np.asarray(px, dtype=np.float64))
            proj.append(np.repeat(view.projection_matrix[None], len(obj), axis=0))
    pts_d, img_a, proj_a = np.concatenate(pts), np.concatenate(img), np.concatenate(proj)

    def residual(x):
        t = from_rotvec(x[:3], x[3:])
        pc = pts_d @ t[:3, :3].T + t[:3, 3]
        h = np.einsum("nij,nj->ni", proj_a[:, :, :3], pc) + proj_a[:, :, 3]
        return (h[:, :2] / h[:, 2:3] - img_a).ravel()

    def rms(x):
        r = residual(x).reshape(-1, 2)
        return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))

    # Refine only the two starts that fit best as they are (the right one and its mirror, typically).
    xs = [np.concatenate(to_rotvec(start)) for start in starts]
    xs = sorted(xs, key=rms)[:2]
    fits = []
    for x0 in xs:
        # Soft L1 beyond 2 px: one anchor identified wrongly must not drag the constellation.
        sol = least_squares(residual, x0, loss="soft_l1", f_scale=2.0, max_nfev=100)
        fits.append((from_rotvec(sol.x[:3], sol.x[3:]), rms(sol.x)))
    return sorted(fits, key=lambda f: f[1])


def claim_from_video(video: VideoDetections, marker_poses: tuple[MarkerPose, ...], marker_set: MarkerSet, *,
                     max_fit_px: float = 8.0, min_bbs: int = 3, place: bool = True) -> tuple[MarkerPose, ...]:
    """``marker_poses`` with the BBs the camera's markers claim in views where fluoroscopy did not identify them.

    Claims are made among every blob; ``place`` leaves the claimed blobs that are no disc
    (:attr:`.marker_pose.MarkerPose.non_disc_blobs`) out of the observations the claims add
    (:func:`.marker_pose.placing_claim`); False keeps them (the claims' count as evidence).

    A marker that fluoroscopy did not identify anywhere is added as a new (not converged) :class:`MarkerPose`
    at its predicted pose, with the claimed BBs as its observations; an identified marker gains the views it
    was missing. Only markers the camera sees and ``marker_set`` holds are claimed; ``marker_poses`` are
    returned as they are when they carry no blobs (``view_blobs``), when no marker the camera sees was
    identified, or when the constellation does not fit fluoroscopy within ``max_fit_px`` (RMS).
    """
    vids = video.by_id()
    views, non_disc = _view_blobs(marker_poses)
    by_id = {p.marker_id: p for p in marker_poses}
    in_set = set(marker_set.ids)
    anchors = {i: p.observations for i, p in by_id.items() if i in vids and (p.observations or p.solution_observations)}
    if not views or not anchors:
        return marker_poses
    d_from_m = {i: drill_from_marker(vids[i].camera_from_tag, marker_set.by_id(i).tag_center_mm) for i in vids if i in in_set}
    # Nothing to claim when every marker the camera sees is observed in every view (the usual live case).
    if all(i in by_id and {id(o[0]) for o in by_id[i].observations} >= set(views) for i in d_from_m):
        return marker_poses
    starts = []
    for i in anchors:
        p = by_id[i]
        for carm_from_marker in p.solutions:
            starts.append(carm_from_marker @ invert(d_from_m[i]))
    # Anchors seen in one view fit the constellation and its mirror alike: the fit whose prediction the other
    # views' blobs bear out (most BBs claimed; the better fit on a tie) is taken.
    anchor_views = {id(o[0]): o[0] for obs in anchors.values() for o in obs}
    depth_view = next(iter(anchor_views.values())) if len(anchor_views) == 1 else None
    best = None
    # A marker whose BBs pair two ways anchors with each pairing: the camera's constellation fits the right one.
    fits = sorted((f for a in paired_anchors(anchors, by_id) for f in constellation_fits(a, d_from_m, starts)), key=lambda f: f[1])
    for carm_from_drill, rms in fits:
        if rms > max_fit_px:
            continue
        got = _claims(carm_from_drill, views=views, by_id=by_id, d_from_m=d_from_m, marker_set=marker_set, min_bbs=min_bbs, depth_view=depth_view)
        if best is None or _count(got) > _count(best[1]):
            best = (carm_from_drill, got)
    if best is None:
        return marker_poses
    carm_from_drill, claims = best
    if not claims:
        return marker_poses
    if place:
        claims = {i: [(view, *placing_claim(obj, img, non_disc.get(id(view), set()), alone=not (i in by_id and by_id[i].observations)))
                      for view, obj, img in per] for i, per in claims.items()}
    out = []
    for p in marker_poses:
        extra = claims.pop(p.marker_id, [])
        out.append(with_claims(p, extra) if extra else p)
    for i, extra in sorted(claims.items()):
        out.append(MarkerPose(marker_id=i, carm_from_marker=carm_from_drill @ d_from_m[i], residual_px=float("nan"),
                              n_views=len(extra), n_points=sum(len(o[1]) for o in extra), converged=False,
                              observations=tuple(extra), view_blobs=next(iter(by_id.values())).view_blobs,
                              non_disc_blobs=next(iter(by_id.values())).non_disc_blobs))
    return tuple(out)


def claim_from_solution(marker_poses: tuple[MarkerPose, ...], carm_from_marker: dict[int, NDArray[np.float64]], marker_set: MarkerSet, *,
                        min_bbs: int = 3, camera_only: dict[int, NDArray[np.float64]] | None = None,
                        distortion: tuple = ()) -> dict[int, tuple]:
    """{marker id: ((view, design BB centres (N, 3) mm, claimed centres (N, 2) px), ...)}: the free blobs of the views where
    a marker of ``carm_from_marker`` ({id: (4, 4)}, a joint solve's poses) has no observations, claimed at the BBs those
    poses predict; only the markers that gained a view, and only the observations they gained.

    The first claims (:func:`claim_from_video`) predict through each tag's pose in the camera, whose tilt is the
    least certain part of it: a marker edge-on in a lateral view, its normal 3.3 deg off that way, spreads its
    predicted BBs 7 px along the line they lie on (twin seed 3000, AP + lateral, markers stuck flat), more than a
    common shift and ``TOL_PX`` take up. Refined by the other views' BBs and the tag corners together, the same
    marker's pose is within about a degree, and its BBs are where the claim looks for them. Free blobs: those no
    marker identified or claimed in that view; claimed blobs that are no disc are left out as
    :func:`claim_from_video` leaves them (:func:`.marker_pose.placing_claim`).

    ``camera_only``: {marker id: (4, 4)} of markers the camera sees that no view observes, each predicted through the
    solve's ``carm_from_drill`` and its tag's pose in the camera; each is claimed like the solve's markers but on
    ``TILTED_MIN_BBS`` or more BBs in a view (nothing else places it), after them, among the blobs they leave.
    ``distortion``: ((view, (2,) px), ...) the intensifier distortion the solve estimated per view
    (:attr:`.joint_solve.JointSolution.detector_distortion_px`): the BBs are predicted where it puts them.
    """
    by_id = {p.marker_id: p for p in marker_poses}
    views, non_disc = _view_blobs(marker_poses)
    if not views:
        return {}
    taken: dict[int, set] = {}
    for p in marker_poses:
        for o in p.observations:
            taken.setdefault(id(o[0]), set()).update(blob_key(c) for c in np.asarray(o[2]).reshape(-1, 2))
    free_views = {k: (view, np.array([c for c in np.asarray(b, dtype=np.float64).reshape(-1, 2) if blob_key(c) not in taken.get(k, set())]).reshape(-1, 2))
                  for k, (view, b) in views.items()}
    poses = {i: t for i, t in carm_from_marker.items() if i in by_id}
    claims = _claims(np.eye(4), views=free_views, by_id=by_id, d_from_m=poses, marker_set=marker_set, min_bbs=min_bbs, distortion=distortion)
    _tilted_claims(claims, views=free_views, by_id=by_id, poses=poses, marker_set=marker_set, distortion=distortion)
    # The camera's markers that no view observes: predicted through the solve, claimed among the blobs left.
    unseen = {i: np.asarray(t, dtype=np.float64) for i, t in (camera_only or {}).items()
              if i not in poses and not (i in by_id and by_id[i].observations) and i in marker_set.ids}
    if unseen:
        left = {k: (view, b) for k, (view, b) in free_views.items()}
        for per in claims.values():
            for view, _, img in per:
                left[id(view)] = (view, _without(left[id(view)][1], img))
        more = _claims(np.eye(4), views=left, by_id={}, d_from_m=unseen, marker_set=marker_set, min_bbs=max(min_bbs, TILTED_MIN_BBS), distortion=distortion)
        _tilted_claims(more, views=left, by_id={}, poses=unseen, marker_set=marker_set, distortion=distortion)
        claims.update(more)
    placed = {i: tuple((view, *placing_claim(obj, img, non_disc.get(id(view), set()))) for view, obj, img in per) for i, per in sorted(claims.items())}
    # A marker nothing else places keeps a view only on two or more BBs placed there (its non-disc blobs left out).
    placed = {i: tuple(o for o in per if i not in unseen or len(o[1]) >= 2) for i, per in placed.items()}
    return {i: per for i, per in placed.items() if per}


def _tilted_claims(claims: dict[int, list], *, views: dict, by_id: dict[int, MarkerPose], poses: dict[int, NDArray[np.float64]],
                   marker_set: MarkerSet, distortion: tuple = ()) -> None:
    """Add to ``claims`` ({id: [(view, design (N, 3), blobs (N, 2))]}) the views' free blobs that a marker still without them
    explains at a tilt of its pose (up to ``TILT_SEARCH_DEG`` about either axis in its plane), at least
    ``TILTED_MIN_BBS`` of them: the largest count, the smallest tilt on a tie. A marker registered on one face-on view
    and its tag alone has its tilt from the camera (12.7 deg off on twin seed 11100, markers stuck flat); edge-on in
    the other view, its BBs then lie across the line its prediction draws.

    A marker observed in one view only also slides, at each tilt (the untilted pose too), up to ``SLIDE_MM`` along
    that view's beam as this view images it: its depth there comes from magnification and the camera, and where every
    marker of the solve was so posed the solve can leave it 14 mm off (twin seed 12101, first pose, markers flat:
    marker 1's lateral BBs 91 px from its prediction, claimed so)."""
    free = {k: b for k, (_, b) in views.items()}
    for per in claims.values():
        for view, _, img in per:
            free[id(view)] = _without(free[id(view)], img)
    steps = np.radians(np.arange(-TILT_SEARCH_DEG, TILT_SEARCH_DEG + 1e-9, TILT_STEP_DEG))
    tilts = sorted(((a, b) for a in steps for b in steps), key=lambda t: np.hypot(*t))
    for i in sorted(poses):
        own_obs = by_id[i].observations if i in by_id else ()
        have = {id(o[0]) for o in own_obs} | {id(c[0]) for c in claims.get(i, [])}
        design = marker_set.by_id(i).bb_centers_mm
        for k, (view, _) in views.items():
            if k in have or len(free[k]) < TILTED_MIN_BBS:
                continue
            best = None
            # Observed in one view only, the pose's depth along that view's beam is its weakest part: slide along its image.
            own = {id(o[0]): o[0] for o in own_obs}
            slide = beam_image_px(view, next(iter(own.values())), poses[i][:3, 3], SLIDE_MM) if len(own) == 1 else None
            coef = _coefficients(distortion, view)
            for a, b in tilts if slide is not None else tilts[1:]:
                pose = poses[i] @ from_rotvec([a, b, 0.0])
                found = claim_bbs(view, pose, design, free[k], search_px=SEARCH_PX, tol_px=TOL_PX, min_bbs=TILTED_MIN_BBS, slide_px=slide,
                                  distortion_px=coef)
                if found is not None and (best is None or len(found[0]) > len(best[0])):
                    best = found
            if best is None:
                continue
            claims.setdefault(i, []).append((view, *best))
            free[k] = _without(free[k], best[1])


def _coefficients(distortion: tuple, view) -> NDArray[np.float64] | None:
    """The estimated distortion (2,) px of ``view`` in ``distortion`` ((view, coefficients), ...); None when it has none."""
    return next((np.asarray(c, dtype=np.float64) for v, c in distortion if v is view), None)


def with_claims(pose: MarkerPose, extra) -> MarkerPose:
    """``pose`` with the observations ``extra`` ((view, design (N, 3) mm, blobs (N, 2) px), ...) claimed in views it had
    none in, added to its own and to each pairing's (:attr:`.marker_pose.MarkerPose.solution_observations`)."""
    return replace(pose, observations=tuple(pose.observations) + tuple(extra), n_views=pose.n_views + len(extra),
                   n_points=pose.n_points + sum(len(o[1]) for o in extra),
                   solution_observations=tuple(tuple(o) + tuple(extra) for o in pose.solution_observations))


def _without(blobs: NDArray[np.float64], taken: NDArray[np.float64]) -> NDArray[np.float64]:
    """``blobs`` (K, 2) less those in ``taken`` (N, 2)."""
    gone = np.any(np.all(np.isclose(blobs[:, None, :], np.asarray(taken)[None, :, :]), axis=2), axis=1)
    return blobs[~gone]


def _view_blobs(marker_poses: tuple[MarkerPose, ...]) -> tuple[dict, dict]:
    """The views' blobs that no identified marker claimed, {id(view): (view, (K, 2) px)}, and the keys of those that are
    no disc, {id(view): {blob key}} (:attr:`.marker_pose.MarkerPose.view_blobs`, ``non_disc_blobs``)."""
    views, non_disc = {}, {}
    for p in marker_poses:
        for view, blobs in p.view_blobs:
            views.setdefault(id(view), (view, blobs))
        for view, centres in p.non_disc_blobs:
            non_disc.setdefault(id(view), {blob_key(c) for c in centres})
    return views, non_disc


# A loose hypothesis (a ring that identified no marker, matched against one marker alone) stands when the camera's
# constellation, fitted to it, has other markers (or the same marker in another view) claim at least this many BBs
# at their predicted places, more than any rival hypothesis does.
LOOSE_MIN_CLAIMED_BBS = 4


def corroborate_loose(video: VideoDetections, marker_poses: tuple[MarkerPose, ...], loose: tuple[MarkerPose, ...],
                      marker_set: MarkerSet) -> tuple[MarkerPose, ...]:
    """``marker_poses`` with the loose hypothesis the camera's constellation bears out, and the BBs it then claims.

    For use when no marker the camera sees was posed in fluoroscopy otherwise: each hypothesis in ``loose``
    (:attr:`.marker_pose.MarkerPose.loose`) whose tag the camera sees anchors the constellation on its own
    (:func:`claim_from_video`); it counts the BBs the other markers, and its own marker in the other views,
    then claim. The hypothesis that claims most, at least LOOSE_MIN_CLAIMED_BBS and strictly more than any other
    id's, joins ``marker_poses`` (still ``needs_camera``, no longer loose) with those claims; none: ``marker_poses``
    as they are. A wrong identity puts the constellation where the other markers' BBs are not.
    """
    vids = video.by_id()
    scored = []
    before = sum(len(o[1]) for p in marker_poses for o in p.observations)
    for hyp in loose:
        if hyp.marker_id not in vids:
            continue
        anchor = replace(hyp, loose=False)
        got = claim_from_video(video, tuple(marker_poses) + (anchor,), marker_set, place=False)
        own = sum(len(o[1]) for o in anchor.observations)
        scored.append((sum(len(o[1]) for p in got for o in p.observations) - before - own, hyp.marker_id, anchor))
    if not scored:
        return tuple(marker_poses)
    scored.sort(key=lambda s: -s[0])
    best = scored[0]
    if best[0] < LOOSE_MIN_CLAIMED_BBS or (len(scored) > 1 and scored[1][0] >= best[0]):
        return tuple(marker_poses)
    return claim_from_video(video, tuple(marker_poses) + (best[2],), marker_set)


def _count(claims: dict[int, list]) -> int:
    return sum(len(c[1]) for per in claims.values() for c in per)


def _claims(carm_from_drill: NDArray[np.float64], *, views: dict, by_id: dict[int, MarkerPose], d_from_m: dict[int, NDArray[np.float64]],
            marker_set: MarkerSet, min_bbs: int, depth_view=None, distortion: tuple = ()) -> dict[int, list]:
    """{marker id: [(view, design BB centres (N, 3) mm, claimed centres (N, 2) px), ...]}: the free blobs each view
    hands to the camera's markers predicted through ``carm_from_drill`` (4, 4), in views where they were not identified.

    Each view's free blobs are handed out greedily, the marker that explains most BBs first, so that two
    predicted markers never share a blob. ``depth_view``: the one view every anchor was seen in (None: more
    than one), whose beam carries the constellation's depth error; other views' claims slide along its image.
    """
    free = {k: np.asarray(b, dtype=np.float64).reshape(-1, 2) for k, (_, b) in views.items()}
    claims: dict[int, list] = {}
    while True:
        best = None
        for i in sorted(d_from_m):
            seen = {id(o[0]) for o in by_id[i].observations} if i in by_id else set()
            seen |= {id(c[0]) for c in claims.get(i, [])}
            pose = carm_from_drill @ d_from_m[i]
            for k, (view, _) in views.items():
                if k in seen or len(free[k]) < min_bbs:
                    continue
                design = marker_set.by_id(i).bb_centers_mm
                coef = _coefficients(distortion, view)
                found = claim_bbs(view, pose, design, free[k], search_px=SEARCH_PX, tol_px=TOL_PX, min_bbs=min_bbs, distortion_px=coef)
                if found is None and depth_view is not None and k != id(depth_view):
                    slide = beam_image_px(view, depth_view, pose[:3, 3], SLIDE_MM)
                    found = claim_bbs(view, pose, design, free[k], search_px=SEARCH_PX, tol_px=TOL_PX, min_bbs=max(min_bbs, SLID_MIN_BBS), slide_px=slide,
                                      distortion_px=coef)
                if found is not None and (best is None or len(found[0]) > len(best[3])):
                    best = (i, k, view, *found)
        if best is None:
            return claims
        i, k, view, obj, img = best
        claims.setdefault(i, []).append((view, obj, img))
        free[k] = _without(free[k], img)
