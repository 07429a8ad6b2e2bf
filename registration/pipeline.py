"""The live pipeline, composed once: camera frame -> video markers -> video-to-fluoro registration -> drill axis in C.

Both the registration node (every camera frame) and ``drillnav register`` (one
frame) call :func:`track_frame`, so a calibration reaches every step the same
way. The calibration a frame is tracked with is one immutable
:class:`LiveCalibration` (camera, drill axis and the marker locator built from
that camera): a service swaps it as a single reference, so no frame ever meets
a new camera with an old locator.

The joint solve of every marker pose and the drill pose (``joint_solve.py``)
costs ~17 ms a frame on top of ~10 ms for the rest, too much for every frame
at 30 frames/s on two cores. So a live caller carries a
:class:`JointRefinement` from frame to frame: a frame runs the joint solve when
the registration or calibration changed or the last solve is older than
``joint_period_ns``; the frames between use the marker poses that solve refined
(mirror settled, normals fixed by the camera) in the Horn + corner PnP path, and
its covariance (carried with the drill, about a pivot fixed in D) for the
predicted error. One frame (``drillnav register``) always runs the joint solve.

The frames between are tracked only on the markers that solve refined and on those fluoroscopy alone poses
firmly (two views or more, no mirror solution: :attr:`JointRefinement.tracked_poses`). A marker posed in one view
is a few millimetres off along the beam, or mirrored, and nothing on the tracking path weighs it: a frame that
would be tracked on fewer markers than it sees posed, below two, runs the joint solve instead, which weighs it (and
refines it for the frames after); a caller with a worker (``solve_untracked=False``) has it tracked on what it can
use and flagged ``FrameAxis.wants_solve``, and runs that solve in the worker. A solve flagged by its own bound does
not replace a refinement whose frame was surer (reliable, or flagged with smaller bounds); the frame is then tracked
on that one. A tracked frame's covariance is the solve's plus its own corners'
noise (:mod:`.tracking_covariance`).

A live caller that can solve elsewhere (the registration node: a worker
process) passes ``joint_period_ns=None``: a frame then runs the joint solve only
when no refinement fits its registration and calibration, and the caller asks
for the periodic re-solve itself (:func:`refinement_due`) and adopts the result
(:func:`joint_refinement`) on a later frame, so the ~27 ms solve leaves the frame
path.

Tags the detector misses (a glove over a corner, glare on a glossy tag) are looked for where the frame's own
registration predicts them, and the frame registered again with them (:func:`register_with_recovery`,
:mod:`.tag_recovery`): only markers posed in fluoroscopy and missing from the frame, so a frame that finds
every tag pays nothing. A marker posed in one fluoroscopy view has its depth along that view's beam fixed by its BB
pattern's scale alone, so its missing tag is also looked for with the marker slid along that beam
(:func:`predict_slid_tags`), on the joint solve's frames only. A frame that shares no marker with fluoroscopy has no registration to predict from: its
missing tags are searched for without a prediction (:func:`search_missing_tags`, :mod:`.tag_search`: tag outlines
with a part hidden, of which ArUco made no candidate), about 50 ms on a 1280x720 frame, paid only by a frame that
would otherwise be refused. So is a tag that the registration puts in the frame but that the recovery did not find
where predicted (a registration on one or two markers can be off by more than the recovery's reach); that search is
made by the joint solve's frames only, never on the tracking path.

A frame still refused for want of a shared marker, or registered on one marker, then tries the tags whose code
reads only in part (blur, a highlight), named among the posed markers it misses (:mod:`.tag_hypotheses`): the joint
solve must keep a named tag beside another marker for the name to stand (:func:`register_with_recovery`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .axis_uncertainty import AxisUncertainty
from .camera import PinholeCamera
from .errors import DrillnavError, MarkersNotFound
from .joint_solve import frame_corner_sigma_px
from .line import Line3D
from .marker_pose import MarkerPose
from .markers import MarkerSet
from .transforms import apply, invert
from .video_fluoro import HORN_MIN_MARKERS, RELIABLE_ANGLE_DEG, RELIABLE_POSITION_MM, DrillRegistration, PredictedError, predicted_axis_error, register_video_to_fluoro
from .tag_recovery import MIN_SHARE_IN_FRAME, predict_tag_corners, share_in_frame
from .tracking_covariance import corner_pnp_covariance
from .video_markers import VideoDetections, VideoMarkerLocator, with_markers

__all__ = ["LiveCalibration", "FrameAxis", "JointRefinement", "ReliableLimits", "track_frame", "joint_refinement", "refinement_fits",
           "refinement_due", "recover_missing_tags", "NAMED_BELOW_MARKERS", "NAMED_MAX_FRE_MM", "predict_missing_tags", "predict_tag_places", "search_missing_tags", "register_with_recovery", "JOINT_PERIOD_NS",
           "BEAM_SLIDE_MM", "predict_slid_tags",
           "frame_predicted_error"]

JOINT_PERIOD_NS = 500_000_000  # a live frame re-runs the joint solve at least this often (ns)
# A joint registration on fewer markers than this (or none) tries the tags named among the posed markers
# (:mod:`.tag_hypotheses`). Not two: on twin seeds 6600-6605 and 6900-6905 (M = 5) a named tag's few-pixel corners
# made 13 of 25 registrations on two markers worse (2.00 -> 3.86 mm at worst), where they made 19 of 21 on one better.
NAMED_BELOW_MARKERS = 2
# A registration with named tags stands only when every marker it uses lies within this of where fluoroscopy puts it
# (``DrillRegistration.fre_mm``). A wrong name puts its marker tens of millimetres off, and with two markers in one
# view the joint solve can bend both to it: on twin seed 6305 two such registrations had 113 and 2314 mm (188.7 and
# 1838 mm off at the entry). Against runs without the rule, nothing else moved on seeds 6100-6105, 6300-6305,
# 6600-6605 and 6900-6905 (M = 5); the right names checked by hand had at most 5.2 mm.
NAMED_MAX_FRE_MM = 10.0
# Nor when the tags' corners lie, RMS over every tag it uses, over this from where the registration puts them
# (``DrillRegistration.corner_rms_px``). Two markers whose names are swapped lie as far apart in the camera as in
# fluoroscopy, each within a few millimetres of where the other is posed, but their tags turned: twin seed 5006's third
# frame (inlet+outlet), its two named tags swapped, registered 101 mm off with its corners 83 px RMS from the solve's
# (FRE 9.5 and 5.7 mm); named right, 0.5 px. An outline's corners lie a few pixels off (OUTLINE_CORNER_SIGMA_PX), one
# corner 28 px at the worst seen (twin seed 3001: a tag cut by the frame's edge), whose RMS over a tag is under 20 px.
# 20 and 40 px moved the same registrations of the docs table's seeds (docs/accuracy_history.md, 7 Dec 2026).
NAMED_MAX_CORNER_RMS_PX = 40.0
# How far (px, per axis) a missing tag is looked for around its prediction from a registration on one or two
# markers, on the recovery's 8 px grid (48 tries at most per tag, paid only by a tag not found where predicted;
# benchmarks/tag_detection.py: 28-67 ms a frame when every missed tag of it is tried).
WEAK_REACH_PX = 24.0
# A marker posed in one fluoroscopy view has its depth along that view's beam fixed by its BB pattern's scale alone:
# on the operating-room twin such poses lay up to 15 mm off along it (seeds 4400-7205, the tags the recovery then
# missed: 17-79 px from their predictions). Its missing tag is also looked for with the marker slid along the beam
# this far either side (mm; video_claims.SLIDE_MM, the same depth, for its BBs in another view), in steps whose
# images lie SLIDE_STEP_PX apart, at most MAX_SLIDE_STEPS a side (:func:`predict_slid_tags`). 12 px: the tag lies
# within 6 px of a step, inside the recovery's 8 px reach about a prediction.
BEAM_SLIDE_MM = 25.0
SLIDE_STEP_PX = 12.0
MAX_SLIDE_STEPS = 16


@dataclass(frozen=True, kw_only=True)
class LiveCalibration:
    """Camera intrinsics, the drill axis in the camera frame D, and the locator built from that camera."""

    camera: PinholeCamera
    axis_drill: Line3D
    locator: VideoMarkerLocator
    axis_uncertainty: AxisUncertainty = AxisUncertainty()  # drill.json's stated uncertainty of axis_drill (the predicted error's)

    @classmethod
    def build(cls, *, camera: PinholeCamera, axis_drill: Line3D, marker_set: MarkerSet, axis_uncertainty: AxisUncertainty | None = None) -> LiveCalibration:
        locator = VideoMarkerLocator(camera=camera, marker_set=marker_set)  # each marker's own dictionary, tag size and offset
        return cls(camera=camera, axis_drill=axis_drill, locator=locator, axis_uncertainty=axis_uncertainty or AxisUncertainty())


@dataclass(frozen=True, kw_only=True)
class ReliableLimits:
    """Limits on the predicted error's 90 % bounds (mm at the working point, degrees) beyond which an axis is unreliable."""

    position_mm: float = RELIABLE_POSITION_MM
    angle_deg: float = RELIABLE_ANGLE_DEG


@dataclass(frozen=True, kw_only=True)
class JointRefinement:
    """The last joint solve, carried between live frames.

    ``source_poses`` and ``calibration`` are the registration and calibration
    it was solved with (compared by identity: either swapped means a new solve);
    ``poses`` the marker poses it refined; ``covariance_drill`` (6, 6) of the
    drill pose about ``pivot_drill_mm`` (3,), a point fixed in frame D (mm);
    ``at_ns`` when it ran (the caller's clock, ns: the node gives the capture stamp, so a replay re-solves on the same frames).
    """

    source_poses: tuple[MarkerPose, ...]
    calibration: LiveCalibration
    poses: tuple[MarkerPose, ...]
    covariance_drill: NDArray[np.float64]
    pivot_drill_mm: NDArray[np.float64]
    at_ns: int
    # ((view, (2,) pincushion and S shift at the field's corner, px), ...): each image intensifier view's distortion
    # as the solve estimated it; the frames after it draw their axis with it.
    detector_distortion_px: tuple = ()
    refined_ids: tuple[int, ...] = ()  # the markers the solve used (its poses in ``poses``)
    reliable: bool = True  # the solve's own frame was (its 90 % bounds within the limits)
    bound90: tuple[float, float] = (0.0, 0.0)  # the solve's own frame's 90 % bounds (mm at its working point, deg)

    def better_than(self, predicted: PredictedError, *, limits: ReliableLimits) -> bool:
        """Whether this refinement's frame was surer than a new solve's frame, whose ``predicted`` error is given.

        A reliable solve is never worse. A flagged one is worse than a reliable refinement, and than a flagged one
        whose 90 % bounds, each over its limit, are smaller.
        """
        if predicted.reliable:
            return False
        if self.reliable:
            return True
        score = lambda p, a: max(p / limits.position_mm, a / limits.angle_deg)  # noqa: E731
        return score(*self.bound90) < score(predicted.position90_mm, predicted.angle90_deg)

    @property
    def tracked_poses(self) -> tuple[MarkerPose, ...]:
        """The markers the frames after the solve are registered on (Horn + corner PnP, no joint solve).

        Those the solve refined, and those fluoroscopy alone poses firmly: in two views or more, with no mirror
        solution, identified without the camera. A marker posed in one view (its depth along the beam a few
        millimetres off) or with its mirror still open would pull a frame's axis that way where it has no joint solve to
        weigh it: a frame that would rest on fewer than two of these while it sees more posed is solved (in the node,
        tracked on what it can use while the worker solves it).
        """
        refined = set(self.refined_ids)
        return tuple(p for p in self.poses if p.marker_id in refined or (
            p.converged and p.n_views >= 2 and p.mirror_carm_from_marker is None and not p.needs_camera and not p.loose))


def _refined_poses(poses: tuple[MarkerPose, ...], reg: DrillRegistration) -> tuple[MarkerPose, ...]:
    """The markers the joint solve used, at its poses (mirror settled); the others as they were."""
    used = set(reg.used_ids)
    return tuple(replace(p, carm_from_marker=reg.carm_from_marker[p.marker_id], mirror_carm_from_marker=None, further_solutions=(), solution_observations=(),
                         converged=True)
                 if p.marker_id in used and p.marker_id in reg.carm_from_marker else p for p in poses)


def joint_refinement(reg: DrillRegistration, *, poses: tuple[MarkerPose, ...], calibration: LiveCalibration, at_ns: int,
                     predicted: PredictedError | None = None) -> JointRefinement | None:
    """What a joint solve ``reg`` (of ``poses`` with ``calibration``, on the frame stamped ``at_ns``) leaves for the frames after it.

    ``predicted``: the solve's frame's predicted error (its reliability and bounds ride with the refinement).

    None when the solve gave no covariance (a fallback path): the next frame then solves again.
    """
    if reg.covariance_drill is None or reg.pivot_carm_mm is None:
        return None
    # reg.marker_poses adds the markers claimed through the video (edge-on in fluoroscopy): the frames after it use them too
    return JointRefinement(source_poses=poses, calibration=calibration, poses=_refined_poses(reg.marker_poses or poses, reg), covariance_drill=reg.covariance_drill,
                           pivot_drill_mm=apply(invert(reg.carm_from_drill), reg.pivot_carm_mm), at_ns=at_ns,
                           detector_distortion_px=reg.detector_distortion_px, refined_ids=tuple(reg.used_ids),
                           **({} if predicted is None else dict(reliable=predicted.reliable, bound90=(predicted.position90_mm, predicted.angle90_deg))))


def refinement_fits(refinement: JointRefinement | None, *, poses: tuple[MarkerPose, ...], calibration: LiveCalibration) -> bool:
    """Whether ``refinement`` was solved with this registration and calibration (by identity: a swap of either is a new solve)."""
    return refinement is not None and refinement.source_poses is poses and refinement.calibration is calibration


def refinement_due(refinement: JointRefinement, *, now_ns: int, joint_period_ns: int = JOINT_PERIOD_NS) -> bool:
    """Whether ``refinement`` is at least ``joint_period_ns`` old at ``now_ns`` (the caller's clock, ns)."""
    return now_ns - refinement.at_ns >= joint_period_ns


def _shared_ids(video: VideoDetections, poses: tuple[MarkerPose, ...]) -> set[int]:
    """The markers the frame found that are posed (or have BBs) in fluoroscopy."""
    seen = {m.marker_id for m in video.markers}
    return {p.marker_id for p in poses if p.marker_id in seen and (p.converged or p.observations)}


def _shares_a_marker(video: VideoDetections, poses: tuple[MarkerPose, ...]) -> bool:
    """Whether a marker the frame found is posed (or has BBs) in fluoroscopy: without one nothing registers."""
    return bool(_shared_ids(video, poses))


def search_missing_tags(image: NDArray[np.uint8], video: VideoDetections, *, locator: VideoMarkerLocator, poses: tuple[MarkerPose, ...]) -> VideoDetections:
    """``video`` with the tags of markers fluoroscopy posed (or found BBs of) that the frame misses, found with no
    prediction (:meth:`.VideoMarkerLocator.search`): for a frame that shares no marker with fluoroscopy, which
    would otherwise be refused. Returns ``video`` itself when nothing is missing or nothing was found."""
    wanted = {p.marker_id for p in poses if p.converged or p.observations} & locator.marker_ids
    return locator.search(image, video, wanted) if wanted else video


def _missing(video: VideoDetections, poses: tuple[MarkerPose, ...], locator: VideoMarkerLocator, *, unsettled: bool = False) -> list[MarkerPose]:
    """The markers posed in fluoroscopy (converged) that the locator knows and the frame did not find; ``unsettled``:
    instead those posed over two views whose fit did not converge (:func:`_placeable`)."""
    have = {m.marker_id for m in video.markers}
    return [p for p in poses if _placeable(p, unsettled=unsettled) and p.marker_id not in have and p.marker_id in locator.marker_ids]


def _placeable(pose: MarkerPose, *, unsettled: bool = False) -> bool:
    """Whether the registration may say where ``pose``'s tag lies: a converged pose; with ``unsettled``, instead a
    marker identified in two or more views whose fit over them did not converge.

    Such a fit misses ``register_markers``' residual limit when one view's BBs are crowded or pulled (a marker seen
    steeply), or when the views converge alone but not together. Its BBs in two views still fix where it is: on the
    operating-room twin (seeds 8003, 9301, 9901, the tags the camera then missed) such markers lay 0.4-0.7 mm from
    the truth, while markers not converged in one view lay 17-21 mm off. No place vouches for a tag found where an
    unsettled pose puts it (a view's BBs may be paired wrongly): its code alone names it.
    """
    if not unsettled:
        return pose.converged
    return not pose.converged and not pose.loose and len({id(o[0]) for o in pose.observations}) >= 2


def recover_missing_tags(image: NDArray[np.uint8], video: VideoDetections, *, locator: VideoMarkerLocator, camera: PinholeCamera,
                         poses: tuple[MarkerPose, ...], marker_set: MarkerSet, carm_from_drill: NDArray[np.float64],
                         carm_from_marker: dict[int, NDArray[np.float64]] | None = None) -> VideoDetections:
    """``video`` (what ``locator`` found in ``image``) with the missing tags of markers posed in fluoroscopy recovered.

    Each missing marker's tag is predicted through ``camera`` from ``carm_from_drill`` (4, 4) and its pose in C
    (:func:`predict_missing_tags`); then looked for there and its identity verified
    (:meth:`.VideoMarkerLocator.recover`). Returns ``video`` itself when nothing is missing or nothing was recovered.
    """
    expected = predict_missing_tags(video, locator=locator, camera=camera, poses=poses, marker_set=marker_set, carm_from_drill=carm_from_drill,
                                    carm_from_marker=carm_from_marker)
    if not expected:
        return video
    placed = predict_tag_places(locator=locator, camera=camera, poses=poses, marker_set=marker_set, carm_from_drill=carm_from_drill,
                                carm_from_marker=carm_from_marker)
    return locator.recover(image, video, expected, placed_px=placed)


def predict_missing_tags(video: VideoDetections, *, locator: VideoMarkerLocator, camera: PinholeCamera, poses: tuple[MarkerPose, ...],
                         marker_set: MarkerSet, carm_from_drill: NDArray[np.float64],
                         carm_from_marker: dict[int, NDArray[np.float64]] | None = None, unsettled: bool = False) -> dict[int, NDArray[np.float64]]:
    """{marker id: (K, 4, 2) predicted tag corners, px}: the markers posed in fluoroscopy that ``video`` misses and
    whose tag the registration ``carm_from_drill`` (4, 4) puts mostly in the camera's frame.

    Each marker's pose in C is ``carm_from_marker[id]`` (a registration's refined pose) when given, else every
    solution fluoroscopy left open (:attr:`.MarkerPose.solutions`: K = 2 for a mirror, more for a BB pattern
    paired two ways). ``unsettled``: instead the markers posed over two views whose fit did not converge
    (:func:`_placeable`).
    """
    missing = {p.marker_id for p in _missing(video, poses, locator, unsettled=unsettled)}
    places = predict_tag_places(locator=locator, camera=camera, poses=tuple(p for p in poses if p.marker_id in missing), marker_set=marker_set,
                                carm_from_drill=carm_from_drill, carm_from_marker=carm_from_marker, unsettled=unsettled)
    expected = {}
    for marker_id, cands in places.items():
        # Only tags mostly in the frame (a tag cut by its edge is fitted on what is in it): a marker out of view costs nothing more.
        cands = [c for c in cands if share_in_frame(c, width=camera.width, height=camera.height) >= MIN_SHARE_IN_FRAME]
        if cands:
            expected[marker_id] = np.stack(cands)
    return expected


def predict_tag_places(*, locator: VideoMarkerLocator, camera: PinholeCamera, poses: tuple[MarkerPose, ...], marker_set: MarkerSet,
                       carm_from_drill: NDArray[np.float64], carm_from_marker: dict[int, NDArray[np.float64]] | None = None,
                       unsettled: bool = False) -> dict[int, NDArray[np.float64]]:
    """{marker id: (K, 4, 2) px}: where the registration ``carm_from_drill`` (4, 4) puts the tag of every marker posed in
    fluoroscopy (converged) that the locator knows, in the frame or not; K = 0 when every candidate lies behind the camera.

    Each marker's pose in C is ``carm_from_marker[id]`` (a registration's refined pose) when given, else every
    solution fluoroscopy left open (:attr:`.MarkerPose.solutions`: K = 2 for a mirror, more for a BB pattern
    paired two ways). ``unsettled``: instead every marker posed over two views whose fit did not converge
    (:func:`_placeable`).
    """
    refined = carm_from_marker or {}
    places = {}
    for p in poses:
        if not _placeable(p, unsettled=unsettled) or p.marker_id not in locator.marker_ids:
            continue
        starts = (refined[p.marker_id],) if p.marker_id in refined else p.solutions
        cands = [predict_tag_corners(carm_from_drill=carm_from_drill, carm_from_marker=t, tag_corners_marker_mm=marker_set.by_id(p.marker_id).tag_corners_mm(), camera=camera)
                 for t in starts]
        cands = [c for c in cands if c is not None]
        places[p.marker_id] = np.stack(cands) if cands else np.zeros((0, 4, 2))
    return places


def _one_view_beam(pose: MarkerPose) -> NDArray[np.float64] | None:
    """(3,) the unit direction in C of the beam through ``pose``'s marker in the one view its BBs were observed in;
    None when they were observed in two or more views (or none)."""
    views = {id(o[0]): o[0] for o in pose.observations}
    if len(views) != 1:
        return None
    ray = pose.position_carm_mm - next(iter(views.values())).source_position_mm
    return ray / np.linalg.norm(ray)


def _inside(point_px: NDArray[np.float64], quad_px: NDArray[np.float64]) -> bool:
    """Whether ``point_px`` (2,) lies inside the convex quadrilateral ``quad_px`` (4, 2), either winding."""
    edges = np.roll(quad_px, -1, axis=0) - quad_px
    to_point = point_px - quad_px
    cross = edges[:, 0] * to_point[:, 1] - edges[:, 1] * to_point[:, 0]
    return bool(np.all(cross >= 0) or np.all(cross <= 0))


def predict_slid_tags(video: VideoDetections, *, locator: VideoMarkerLocator, camera: PinholeCamera, poses: tuple[MarkerPose, ...],
                      marker_set: MarkerSet, carm_from_drill: NDArray[np.float64], step_px: float = SLIDE_STEP_PX,
                      slide_mm: float = BEAM_SLIDE_MM) -> dict[int, NDArray[np.float64]]:
    """{marker id: (K, 4, 2) px}: the missing tags of markers posed (converged) in one fluoroscopy view, predicted
    through ``camera`` from ``carm_from_drill`` (4, 4) with the marker slid along that view's beam, out to
    ``slide_mm`` either side of where its BBs put it (each solution fluoroscopy left open), in steps whose images lie
    at most ``step_px`` apart, nearest steps first; the place itself is
    left out (the recovery looked there). Only predictions mostly in the frame (``MIN_SHARE_IN_FRAME``) and not
    centred on a tag the frame found.

    No place vouches for a tag found so (the depth is what is unknown): the caller names it by its code alone.
    """
    missing = {p.marker_id for p in _missing(video, poses, locator)}
    found = [m.corners_px for m in video.markers]
    out = {}
    for p in poses:
        beam = _one_view_beam(p) if p.marker_id in missing else None
        if beam is None:
            continue
        corners_mm = marker_set.by_id(p.marker_id).tag_corners_mm()
        tried = []
        for k, start in enumerate(p.solutions):
            def at(depth_mm: float, start=start) -> NDArray[np.float64] | None:
                moved = start.copy()
                moved[:3, 3] += depth_mm * beam
                return predict_tag_corners(carm_from_drill=carm_from_drill, carm_from_marker=moved, tag_corners_marker_mm=corners_mm, camera=camera)

            for sign in (1.0, -1.0):
                # Steps fine enough for the faster end of this side (perspective: the image moves faster nearer the camera).
                rate = 0.0
                for d in (0.0, sign * slide_mm):
                    a, b = at(d - 0.5), at(d + 0.5)
                    if a is not None and b is not None:
                        rate = max(rate, float(np.linalg.norm(b.mean(axis=0) - a.mean(axis=0))))
                n = int(min(np.ceil(slide_mm * rate / step_px), MAX_SLIDE_STEPS))
                for j in range(1, n + 1):
                    c = at(sign * j * slide_mm / n)
                    # A place a found tag holds holds no other tag.
                    if (c is not None and share_in_frame(c, width=camera.width, height=camera.height) >= MIN_SHARE_IN_FRAME
                            and not any(_inside(c.mean(axis=0), quad) for quad in found)):
                        tried.append((j / n, k, c))
        if tried:
            out[p.marker_id] = np.stack([c for _, _, c in sorted(tried, key=lambda t: (t[0], t[1]))])
    return out


def _merged(a: dict[int, NDArray[np.float64]], b: dict[int, NDArray[np.float64]]) -> dict[int, NDArray[np.float64]]:
    """{id: (K_a + K_b, 4, 2)}: two sets of predicted tag corners (a registration's two solutions) stacked per marker."""
    return {i: np.concatenate([c for c in (a.get(i), b.get(i)) if c is not None]) for i in a.keys() | b.keys()}


def _recover_predicted(image: NDArray[np.uint8], video: VideoDetections, reg: DrillRegistration, *, locator: VideoMarkerLocator,
                       camera: PinholeCamera, poses: tuple[MarkerPose, ...], marker_set: MarkerSet, joint: bool,
                       search: bool) -> tuple[VideoDetections, dict[int, NDArray[np.float64]], bool]:
    """One pass of :func:`register_with_recovery`'s recovery: the missing tags looked for where the registration ``reg``
    puts them: (detections, {marker id: predicted corners} looked for, whether ``reg`` is weak: fewer than
    ``HORN_MIN_MARKERS`` markers on the joint solve's frames)."""
    if reg.fit_carm_from_drill is not None:
        # Registered half-way to a lone marker's mirror image: the tags are looked for where the best fit puts them.
        reg = replace(reg, carm_from_drill=reg.fit_carm_from_drill, carm_from_marker={**reg.carm_from_marker, **reg.fit_carm_from_marker})
    expected = predict_missing_tags(video, locator=locator, camera=camera, poses=poses, marker_set=marker_set, carm_from_drill=reg.carm_from_drill,
                                    carm_from_marker=reg.carm_from_marker)
    # A mirror image the refinement slid from (``mirror_unrefined``) widens the bound only: the search goes as with none.
    mirror = None if reg.mirror_unrefined else reg.mirror_carm_from_drill
    if mirror is not None:
        # One view left the constellation's mirror open (a registration on one or two markers): the missing tags
        # are looked for where either solution puts them, so the one the frame bears out brings the markers that settle it.
        mirrored = predict_missing_tags(video, locator=locator, camera=camera, poses=poses, marker_set=marker_set,
                                        carm_from_drill=mirror)
        expected = _merged(expected, mirrored)
    weak = search and joint and len(reg.used_ids) < HORN_MIN_MARKERS
    more = video
    # Where the registration puts every posed marker's tag: one placed away from a missing tag is no rival to its identity.
    settled = predict_tag_places(locator=locator, camera=camera, poses=poses, marker_set=marker_set, carm_from_drill=reg.carm_from_drill,
                                 carm_from_marker=reg.carm_from_marker)
    if expected:
        placed = settled
        if mirror is not None:
            placed = _merged(placed, predict_tag_places(locator=locator, camera=camera, poses=poses, marker_set=marker_set,
                                                        carm_from_drill=mirror))
        # A registration on one or two markers predicts the missing tags tens of pixels off (measured: 10-25 px on
        # the operating-room twin); a frame that may search (the joint solve's, whose checks name a misplaced corner)
        # also tries the prediction shifted.
        # A tag found where predicted is named by its place too: the marker posed there. With the mirror open, the
        # places are where either solution puts each posed marker's tag (under the mirror, every solution fluoroscopy
        # left it), and a marker that one of them places here is a rival. Twin seed 10901 (AP+lateral, second frame, a C-arm of 1000 / 600 mm source
        # distances): on marker 14 alone, its mirror open, marker 3's glared tag lay within 1 px of where the mirror puts
        # it and was not named by its code (marker 16, posed, was a rival); named by its place, the axis 46 -> 0.7 mm off.
        more = locator.recover(image, video, expected, reach_px=WEAK_REACH_PX if weak else 0.0, placed_px=placed,
                               by_place=True)
    if joint:
        # Markers identified in two views whose fit did not converge (a steep view's crowded BBs): where their BBs put
        # them, their tags are looked for too, named by their code alone (no place vouches for an unsettled pose).
        # With the constellation's mirror open, where either solution puts them: twin seed 27002 (inlet+outlet, first
        # frame), on marker 3 alone (one view, 47 deg off, its mirror 1 deg), marker 7's gloved tag lay where the mirror
        # puts it and the registration put it out of the frame.
        drills = (reg.carm_from_drill,) if mirror is None else (reg.carm_from_drill, mirror)
        guessed, unsettled_places = {}, {}
        for drill in drills:
            guessed = _merged(guessed, predict_missing_tags(more, locator=locator, camera=camera, poses=poses, marker_set=marker_set,
                                                            carm_from_drill=drill, unsettled=True))
            unsettled_places = _merged(unsettled_places, predict_tag_places(locator=locator, camera=camera, poses=poses, marker_set=marker_set,
                                                                            carm_from_drill=drill, unsettled=True))
        if guessed:
            around = _merged(settled, unsettled_places)
            more = locator.recover(image, more, guessed, reach_px=WEAK_REACH_PX if weak else 0.0, placed_px=around, by_place=False)
            expected = {**expected, **guessed}
    if joint and search:
        # Markers posed in one view whose tags were not where their BBs' depth put them: looked for along that view's
        # beam, named by their code alone (the joint solve's frames only: up to 2 x MAX_SLIDE_STEPS tries a solution).
        slid = predict_slid_tags(more, locator=locator, camera=camera, poses=poses, marker_set=marker_set, carm_from_drill=reg.carm_from_drill)
        if slid:
            more = locator.recover(image, more, slid, placed_px=settled, by_place=False)
    return more, expected, weak


def register_with_recovery(image: NDArray[np.uint8], video: VideoDetections, *, locator: VideoMarkerLocator, camera: PinholeCamera,
                           poses: tuple[MarkerPose, ...], marker_set: MarkerSet, joint: bool = True,
                           search: bool = True, name_outlines: bool = True) -> tuple[VideoDetections, DrillRegistration]:
    """Register ``video`` (:func:`.register_video_to_fluoro`), recover the missing tags where that registration predicts
    them (:func:`recover_missing_tags`), and register again if any was recovered: (detections, registration). When
    that registration uses more markers than the first, the tags still missing are looked for once more where it
    puts them (a first registration on one marker, its mirror open, predicts them tens of pixels off).

    A frame that shares no marker with fluoroscopy first has the missing tags searched for without a prediction
    (:func:`search_missing_tags`); a tag that the registration puts in the frame but that the recovery did not find
    where predicted is searched for the same way afterwards, and so are the tags of the set's markers that fluoroscopy
    placed nowhere (found, they claim their markers' BBs). ``search`` False skips both (a caller that searched
    already, or the tracking path, which cannot spend ~50 ms a frame).

    A joint registration that is refused for want of a shared marker, or that rests on one marker
    (``NAMED_BELOW_MARKERS``), then tries the tags whose code reads only in part, named among the posed markers
    the frame misses (:func:`_registration_with_named_tags`); ``name_outlines`` False skips that.

    The one home of this sequence: ``track_frame`` and the accuracy study call it. Raises what the first
    registration raises.
    """
    every = poses
    # A loose hypothesis (a ring matched against one marker alone) names no marker until the camera bears it out: it
    # predicts no tag and starts no search.
    poses = tuple(p for p in poses if not p.loose)
    searched = search and not _shares_a_marker(video, poses)
    if searched:
        video = search_missing_tags(image, video, locator=locator, poses=poses)
    named = joint and name_outlines
    try:
        reg = register_video_to_fluoro(video, every, marker_set, camera, joint=joint)
    except MarkersNotFound:
        got = _registration_with_named_tags(image, video, locator=locator, camera=camera, poses=poses, every=every, marker_set=marker_set,
                                            used_before=0) if named else None
        if got is None:
            raise
        return _recovered_again(image, *got, locator=locator, camera=camera, poses=poses, every=every, marker_set=marker_set, joint=joint,
                                search=search)
    more, expected, weak = _recover_predicted(image, video, reg, locator=locator, camera=camera, poses=poses, marker_set=marker_set,
                                              joint=joint, search=search)
    left = set(expected) - {m.marker_id for m in more.markers}
    if weak:
        # A registration on one marker (or two) may be far off, its marker posed upside down in fluoroscopy (twin
        # seed 6400: a 180 deg turn fitted 9 BBs at 0.48 px): the posed markers it puts out of the frame are searched for too.
        left |= {p.marker_id for p in _missing(more, poses, locator)}
    if search and not searched:
        # The set's markers that fluoroscopy placed nowhere (a loose hypothesis included) have no predicted tag; found,
        # their tags claim their BBs where the camera puts them (:func:`.video_claims.claim_from_video`). A gloved
        # corner is what hides such tags from ArUco most (twin, markers stuck flat: 33 of the 60 tags missed in
        # AP+lateral frames belonged to markers that fluoroscopy identified in neither view).
        left |= set(locator.marker_ids) - {m.marker_id for m in more.markers} - {p.marker_id for p in poses if p.converged or p.observations}
    if search and not searched and left:
        # Predicted in the frame but not where the prediction put it (a registration on one or two markers is
        # off by more than the recovery's tolerance), or put out of it by a weak one: searched for with no
        # prediction, in the whole frame.
        more = locator.search(image, more, left)
    if more is not video:
        before = len(reg.used_ids)
        video, reg = more, register_video_to_fluoro(more, every, marker_set, camera, joint=joint)
        if len(reg.used_ids) > before:
            # A registration that gained markers predicts the tags still missing better than the one it started from (on
            # one marker, its mirror open: 5-38 px off on the operating-room twin, then 1-2 px): they are looked for once more.
            video, reg = _recovered_again(image, video, reg, locator=locator, camera=camera, poses=poses, every=every, marker_set=marker_set,
                                          joint=joint, search=search)
    if named and (len(reg.used_ids) < NAMED_BELOW_MARKERS or _in_one_view_of_two(reg, video, every=every, locator=locator)):
        got = _registration_with_named_tags(image, video, locator=locator, camera=camera, poses=poses, every=every, marker_set=marker_set,
                                            used_before=len(reg.used_ids))
        if got is not None:
            return _recovered_again(image, *got, locator=locator, camera=camera, poses=poses, every=every, marker_set=marker_set, joint=joint,
                                    search=search)
    return video, reg


def _recovered_again(image: NDArray[np.uint8], video: VideoDetections, reg: DrillRegistration, *, locator: VideoMarkerLocator,
                     camera: PinholeCamera, poses: tuple[MarkerPose, ...], every: tuple[MarkerPose, ...], marker_set: MarkerSet,
                     joint: bool, search: bool) -> tuple[VideoDetections, DrillRegistration]:
    """(detections, registration) after one more pass of :func:`_recover_predicted` where ``reg`` puts the tags still
    missing, registered again when it found any; ``(video, reg)`` as given otherwise.

    For a registration that gained markers since the missing tags were last looked for: the recovery's own second
    pass, and a registration on tags named among the posed (:func:`_registration_with_named_tags`). Twin seed 12101,
    markers flat, AP+lateral: the frame's detector found marker 1's tag alone, a registration on it was refused,
    marker 6's tag named in part brought a registration on two markers, and marker 45's tag (a gloved corner) lay
    within 12 px of where that registration put it, verified there, unlooked-for until this pass.

    A registration with the recovered tags that fails (a tag verified where predicted that the solve cannot fit:
    degenerate, not converged) leaves the frame with the registration it had, not refused.
    """
    again, _, _ = _recover_predicted(image, video, reg, locator=locator, camera=camera, poses=poses, marker_set=marker_set, joint=joint, search=search)
    if again is video:
        return video, reg
    try:
        return again, register_video_to_fluoro(again, every, marker_set, camera, joint=joint)
    except DrillnavError:  # the recovered tags are not borne out: the frame keeps the registration it had
        return video, reg


def _views(pose: MarkerPose) -> set[int]:
    """The fluoroscopy views (by identity) in which ``pose``'s BBs were found."""
    return {id(view) for view, _, _ in pose.observations}


def _in_one_view_of_two(reg: DrillRegistration, video: VideoDetections, *, every: tuple[MarkerPose, ...], locator: VideoMarkerLocator) -> bool:
    """Whether every marker ``reg`` uses was found in one and the same fluoroscopy view, while a posed marker the
    frame misses was found in another: such a registration rests on one view's depth (a marker's place along its
    beam is fixed by its BB pattern's scale alone, millimetres off), and the missing marker's tag, named among the
    posed (:func:`_registration_with_named_tags`), would give it the second view."""
    by_id = {p.marker_id: p for p in every}
    used = [_views(by_id[i]) if i in by_id else set() for i in reg.used_ids]
    if not used or not all(used) or len(one := set.union(*used)) != 1:
        return False
    return any(_views(p) - one for p in _missing(video, every, locator))


def _registration_with_named_tags(image: NDArray[np.uint8], video: VideoDetections, *, locator: VideoMarkerLocator, camera: PinholeCamera,
                                  poses: tuple[MarkerPose, ...], every: tuple[MarkerPose, ...], marker_set: MarkerSet,
                                  used_before: int) -> tuple[VideoDetections, DrillRegistration] | None:
    """The joint registration of ``video`` with the tags whose code reads only in part, named among the markers posed
    in fluoroscopy (``every``: loose hypotheses included) that it misses (:meth:`.VideoMarkerLocator.name_among_posed`),
    and those of markers fluoroscopy identified without posing them whose code identifies them dictionary-wide, when
    it bears them out: (detections with the named tags it used, registration), or None.

    Borne out: the registration uses at least two markers (one, where a named marker it uses is
    ``identified_by_code``: its code identifies it dictionary-wide; or, in a frame otherwise refused
    (``used_before`` 0), ``named_among_set``: its cells name it among every tag of the set and its corners are its
    fitted edges', and the registration is then flagged, :func:`.video_fluoro.lone_name_unchecked`), more than ``used_before`` (the markers the frame's
    registration used without them; 0 when it was refused), one of them named, and every marker it uses lies within
    ``NAMED_MAX_FRE_MM`` of where fluoroscopy puts it, its tags' corners within ``NAMED_MAX_CORNER_RMS_PX`` (RMS) of where it
    puts them. A named tag whose marker misfits the others is rejected by the
    joint solve like any marker, and dropped; markers kept agree on their places in the camera and in fluoroscopy,
    which a wrong name, tens of millimetres off, does not.
    ``every``: the poses the registration is given (loose hypotheses included, as for the frame's own).
    """
    # A loose hypothesis's marker is wanted too: the camera's word on the ring it waits for is that marker's tag, and
    # a name read in part is borne out, like any, only beside another marker (corroborate_loose, the claims), unless
    # its code identifies it dictionary-wide.
    wanted = {p.marker_id for p in _missing(video, every, locator)}
    named = locator.name_among_posed(image, video, wanted)
    # A marker fluoroscopy identified but whose fit did not converge (one view: a mirror image or a residual over the
    # limit) has no pose to name its tag among; its tag is named only where its code identifies it dictionary-wide,
    # and the joint solve then fixes its normal and layout from the camera and its place from its BBs. Looked for
    # after the posed markers' names (whose outlines it does not take), so that it never turns one of them. Twin
    # seed 28402 (AP+lateral, first frame): the camera read no whole tag; tag 46 named among the posed and tag 20,
    # cut by the frame's edge, its marker identified in the lateral view alone, registered 0.3 deg off, refused before.
    unposed = {p.marker_id for p in every if not p.converged and not p.loose and p.observations and p.marker_id in locator.marker_ids}
    unposed -= wanted | {m.marker_id for m in video.markers}
    if unposed:
        by_code = locator.name_among_posed(image, with_markers(video, named), unposed)
        named = tuple(sorted(named + tuple(m for m in by_code if m.identified_by_code), key=lambda m: m.marker_id))
    if not named:
        return None
    trial = with_markers(video, named)
    try:
        reg = register_video_to_fluoro(trial, every, marker_set, camera, joint=True)
    except DrillnavError:  # the names are not borne out (nothing usable, degenerate, not converged): the frame keeps its own result
        return None
    used = set(reg.used_ids)
    # A name whose code identifies it dictionary-wide stands alone, as a tag the search found would; any other only
    # beside another marker, but for a name the cells read give no other tag of the set, placed on its fitted edges, in a
    # frame otherwise refused (flagged: nothing checks it). Twin seed 10402 (random pair, second drill pose): the
    # frame's one tag in view glared, 7 cells read name marker 44 among the set by 2; refused with three markers in each
    # view, it registers 3.1 mm off under a 3.2 mm bound.
    alone = any((m.identified_by_code or (used_before == 0 and m.named_among_set)) and m.marker_id in used for m in named)
    if len(used) < max(1 if alone else 2, used_before + 1) or not used & {m.marker_id for m in named}:
        return None
    if any(reg.fre_mm.get(i, np.inf) > NAMED_MAX_FRE_MM for i in used) or reg.corner_rms_px > NAMED_MAX_CORNER_RMS_PX:
        return None
    return replace(trial, markers=tuple(m for m in trial.markers if not m.named_among_posed or m.marker_id in used)), reg


@dataclass(frozen=True, kw_only=True)
class FrameAxis:
    """One frame's result.

    ``axis_carm`` passes through the working point: the axis point nearest the
    centroid of the markers used (frame C, mm). ``axis_full_carm`` is the same
    line with the drill calibration's own point (for drawing).
    """

    video: VideoDetections
    registration: DrillRegistration
    axis_carm: Line3D
    axis_full_carm: Line3D
    predicted_error: PredictedError
    refinement: JointRefinement | None = None  # hand it to the next frame's track_frame
    # Tracked on fewer markers than it sees posed (solve_untracked False): a joint solve of this frame would weigh
    # the others (a marker fluoroscopy posed in one view); the caller should run one.
    wants_solve: bool = False

    @property
    def working_point_carm_mm(self) -> NDArray[np.float64]:
        return self.axis_carm.point_mm

    @property
    def named_ids(self) -> tuple[int, ...]:
        """The markers the registration used whose tags were named among the posed markers (outline corners)."""
        return _named_ids(self.video, self.registration)


def _named_ids(video: VideoDetections, reg: DrillRegistration) -> tuple[int, ...]:
    used = set(reg.used_ids)
    return tuple(sorted(m.marker_id for m in video.markers if m.named_among_posed and m.marker_id in used))


def track_frame(image: NDArray[np.uint8], *, calibration: LiveCalibration, poses: tuple[MarkerPose, ...], marker_set: MarkerSet,
                limits: ReliableLimits = ReliableLimits(), refinement: JointRefinement | None = None, now_ns: int = 0,
                joint_period_ns: int | None = JOINT_PERIOD_NS, previous_carm_from_drill: NDArray[np.float64] | None = None,
                solve_untracked: bool = True) -> FrameAxis:
    """The drill axis in C from one camera frame and the fluoroscopy marker poses.

    ``limits``: the 90 % bounds above which the axis is flagged unreliable (``predicted_error.reliable``).
    ``refinement``, ``now_ns``: the previous frame's :class:`JointRefinement` and a monotonic time (live callers;
    see the module docstring); without them the frame runs the joint solve. ``solve_untracked`` False: a frame
    that would be tracked on fewer markers than it sees posed, below two, is tracked on its one marker and flagged
    ``wants_solve`` instead of solved here (a caller with a worker). ``joint_period_ns`` None: an old
    refinement is never re-solved here (the caller schedules that; a refinement of another registration or
    calibration still is). A frame registered afresh on tags named among the posed markers (``FrameAxis.named_ids``)
    hands on the refinement it was given where that still fits, not one of its own outline corners.

    Markers posed in fluoroscopy that the frame misses are recovered where its registration predicts them
    (:func:`recover_missing_tags`) before the registration that gives the axis. ``previous_carm_from_drill``
    (4, 4): a recent frame's registration (a live caller's last axis, a few frames old at most: the tolerance is
    8 px), which predicts them when none of the tags this frame found is posed in fluoroscopy (no registration of
    its own to predict from).

    Raises ``MarkersNotFound`` when no marker of the set is seen, and the
    registration's own errors (too few shared markers) as they are.
    """
    fluoro_poses = poses  # as fluoroscopy gave them: a lone marker's is judged on them, not on a joint solve's refinement
    video = calibration.locator.locate(image)
    recover = dict(locator=calibration.locator, camera=calibration.camera)
    in_use = refinement.poses if refinement_fits(refinement, poses=poses, calibration=calibration) else poses
    in_use = tuple(p for p in in_use if not p.loose)  # hypotheses, not poses (see register_with_recovery)
    posed = {p.marker_id for p in in_use if p.converged}
    if previous_carm_from_drill is not None and not posed & {m.marker_id for m in video.markers}:
        video = recover_missing_tags(image, video, poses=in_use, marker_set=marker_set, carm_from_drill=previous_carm_from_drill, **recover)
    searched = not _shares_a_marker(video, in_use)
    if searched:  # nothing to register from, nor to predict the missing tags: search for them
        video = search_missing_tags(image, video, locator=calibration.locator, poses=in_use)
    # A frame that found no tag is registered afresh: tags whose code reads only in part may still be named among the
    # posed markers (register_with_recovery), or it is refused for what it is.
    # So is a frame that would be tracked on fewer markers than it sees posed, below two (a marker fluoroscopy poses
    # weakly is left to the joint solve, not dropped where one marker would remain).
    fits = refinement_fits(refinement, poses=poses, calibration=calibration)
    tracked_seen = len(_shared_ids(video, refinement.tracked_poses)) if fits else 0
    can_track = tracked_seen >= max(1, min(2, len(_shared_ids(video, in_use))))
    # A caller that solves elsewhere (solve_untracked False: the node's worker) has such a frame tracked on the one
    # marker it can use, and asks for a solve (FrameAxis.wants_solve) that weighs the others.
    wants_solve = not can_track and tracked_seen >= 1 and not solve_untracked
    can_track = can_track or wants_solve
    fresh = not can_track or (joint_period_ns is not None and refinement_due(refinement, now_ns=now_ns, joint_period_ns=joint_period_ns))
    tracked = None
    if fresh:
        try:
            solved_video, solved = register_with_recovery(image, video, poses=poses, marker_set=marker_set, search=not searched, **recover)
        except MarkersNotFound:
            if not video.markers:
                raise MarkersNotFound(f"no marker of the marker set ({len(marker_set.ids)} ids) is visible in the camera frame") from None
            raise
        solved_pe = frame_predicted_error(solved_video, solved.marker_poses or poses, solved, calibration=calibration, limits=limits, fluoro_poses=fluoro_poses)
        # A registration on named tags (outline corners, a few millimetres) gives this frame its axis, but does not
        # replace a refinement that still fits: the markers it refined are tracked on frames whose tags ArUco reads.
        # Nor does a solve its own bound flags replace one that gave surer frames (two markers, one of them posed
        # wrong, can throw a re-solve 100 mm off): the frame is tracked on that one where it sees one of its markers.
        named = bool(_named_ids(solved_video, solved))
        keep = fits and (named or refinement.better_than(solved_pe[1], limits=limits))
        if not keep:
            refinement = joint_refinement(solved, poses=poses, calibration=calibration, at_ns=now_ns, predicted=solved_pe[1])
        elif not named:  # tried now: the next try is a period away
            refinement = replace(refinement, at_ns=now_ns)
            if _shared_ids(video, refinement.tracked_poses):
                try:
                    tracked = _tracked(image, video, refinement=refinement, marker_set=marker_set, recover=recover)
                except DrillnavError:  # the solve's own (flagged) axis, then
                    tracked = None
        if tracked is None:
            video, reg, poses, (work, pe) = solved_video, solved, solved.marker_poses or poses, solved_pe
    else:
        tracked = _tracked(image, video, refinement=refinement, marker_set=marker_set, recover=recover)
    if tracked is not None:
        video, reg = tracked
        poses = reg.marker_poses or refinement.poses
        work, pe = frame_predicted_error(video, poses, reg, calibration=calibration, limits=limits, fluoro_poses=fluoro_poses)
    axis = calibration.axis_drill.transformed(reg.carm_from_drill)
    return FrameAxis(video=video, registration=reg, axis_carm=Line3D(point_mm=work, direction=axis.direction), axis_full_carm=axis, predicted_error=pe,
                     refinement=refinement, wants_solve=wants_solve and tracked is not None)


def _tracked(image: NDArray[np.uint8], video: VideoDetections, *, refinement: JointRefinement, marker_set: MarkerSet,
             recover: dict) -> tuple[VideoDetections, DrillRegistration]:
    """Tracking: this frame's Horn + PnP registration on the joint-refined markers.

    Its covariance is the solve's (the markers' uncertainty) plus its own corners' on the markers it used, those held
    fixed (:func:`.tracking_covariance.corner_pnp_covariance`; each corner's noise the larger of its tag's stated
    noise and the fit's RMS residual): a frame tracked on one tag is far less sure of the drill's tilt than the
    solve's frame on three.
    """
    video, reg = register_with_recovery(image, video, poses=refinement.tracked_poses, marker_set=marker_set, joint=False, search=False, **recover)
    pivot = apply(reg.carm_from_drill, refinement.pivot_drill_mm)
    vids = video.by_id()
    ids = [i for i in reg.used_ids if i in vids and i in reg.carm_from_marker]
    own = np.zeros((6, 6))
    if ids:  # every marker used has its tag and its pose (register_video_to_fluoro): never empty in practice
        points = np.concatenate([apply(reg.carm_from_marker[i], marker_set.by_id(i).tag_corners_mm()) for i in ids])
        sigma = np.repeat([max(vids[i].corner_sigma_px, reg.corner_rms_px) for i in ids], 4)
        own = corner_pnp_covariance(reg.carm_from_drill, points_carm_mm=points, sigma_px=sigma, camera=recover["camera"], pivot_carm_mm=pivot,
                                    frame_shape_sigma_px=frame_corner_sigma_px([v.edge_sigma_px for v in video.markers]))
    return video, replace(reg, covariance_drill=refinement.covariance_drill + own, pivot_carm_mm=pivot,
                          method="horn+pnp on joint-refined markers", detector_distortion_px=refinement.detector_distortion_px)


def frame_predicted_error(video: VideoDetections, poses: tuple[MarkerPose, ...], reg: DrillRegistration, *, calibration: LiveCalibration,
                          limits: ReliableLimits, fluoro_poses: tuple[MarkerPose, ...]) -> tuple[NDArray[np.float64], PredictedError]:
    """The working point (3,) (the axis point nearest the centroid of the markers used, frame C, mm) and the predicted error there."""
    axis = calibration.axis_drill.transformed(reg.carm_from_drill)
    centroid = np.mean([p.position_carm_mm for p in poses if p.marker_id in reg.used_ids], axis=0)
    work = axis.closest_point(centroid)
    u = calibration.axis_uncertainty
    pe = predicted_axis_error(video, poses, reg, calibration.axis_drill, working_point_carm_mm=work, axis_sigma_mm=u.sigma_mm,
                              axis_sigma_deg=u.per_direction_deg, position_limit_mm=limits.position_mm, angle_limit_deg=limits.angle_deg,
                              fluoro_poses=fluoro_poses)  # vectorised: ~1 ms
    return work, pe
