"""The periodic joint solve off the frame path: a worker process, and the capture-time schedule on which frames adopt it.

The joint solve of every marker pose and the drill pose (``registration/joint_solve.py``, ~27 ms on the twin) ran
on the frame thread every ``JOINT_PERIOD_NS`` of capture time: one frame in fifteen at 30 frames/s took four times
as long as the others, and that frame set the daemon's p99. :class:`JointSolveWorker` gives it to a worker process
(spawned: never fork a process that runs zenoh's threads; a process, not a thread, because the solve is mostly
Python in scipy's ``least_squares`` and would hold the GIL the frame thread needs), and the frames go on with the
refinement they have.

Schedule (on capture stamps, so a recording replayed gives the axes it gave live while the worker keeps up):

- a frame whose refinement does not fit the registration or calibration in use (a new shot, a new calibration)
  still runs the joint solve on the frame path, as before: the first axis of a new registration is joint-solved;
- a frame stamped ``s`` whose refinement is ``JOINT_PERIOD_NS`` old asks the worker for a solve of its own
  detections;
- that solve is adopted by the first frame stamped at or after ``s + adopt_after_ns`` (three frames at 30 frames/s
  by default; the solve takes ~20 ms). If the worker is late (a loaded machine), that frame waits at most
  ``wait_s`` (0 in the daemon: never) and goes on with the refinement it has; the first frame after the solve is
  done adopts it. The frame path never solves it itself: an inline solve was a 40 ms frame, the stream's p99.
- a worker process that died is replaced and given the same solve again; one that has not answered
  ``GIVE_UP_NS`` of capture time after the adoption was due is replaced and the solve dropped (the next period
  asks again);
- a solve requested under another registration or calibration than the adopting frame's is dropped (never mixed).
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.marker_pose import MarkerPose
from drillnav.registration.markers import MarkerSet
from drillnav.registration.pipeline import (JOINT_PERIOD_NS, FrameAxis, JointRefinement, LiveCalibration, ReliableLimits, frame_predicted_error,
                                            joint_refinement, refinement_due, refinement_fits, track_frame)
from drillnav.registration.video_fluoro import DrillRegistration, register_video_to_fluoro
from drillnav.registration.video_markers import VideoDetections

__all__ = ["JointSolveWorker", "JointSolveCounters", "ADOPT_AFTER_NS", "WAIT_S", "GIVE_UP_NS"]

ADOPT_AFTER_NS = 100_000_000  # capture time from a solve's frame to the frame that adopts it (ns): ~4x the solve's own time
WAIT_S = 0.0  # how long the adopting frame may wait for a late worker: never, on the live frame path (tests wait, to
# pin the adopting frame)
# A registration this recent (capture time) predicts where the next frame's missing tags are (tracking a tag under a
# glove): at a freehand drill's speed the camera moves under a few millimetres in 100 ms.
PREVIOUS_POSE_NS = 100_000_000
GIVE_UP_NS = 2_000_000_000  # a worker silent this long (capture time) past the adoption is stuck: replaced, the solve dropped

_marker_set: MarkerSet | None = None  # the worker process's own copy, sent once


def _init_worker(marker_set: MarkerSet) -> None:
    global _marker_set
    _marker_set = marker_set


def _solve(video: VideoDetections, poses: tuple[MarkerPose, ...], camera: PinholeCamera) -> DrillRegistration | str:
    # A failure comes back as its message: a typed error with keyword-only fields may not survive pickling.
    try:
        return register_video_to_fluoro(video, poses, _marker_set, camera)
    except Exception as exc:  # noqa: BLE001 - reported by the adopting frame
        return f"{type(exc).__name__}: {exc}"


def _ready() -> bool:
    return True


@dataclass
class JointSolveCounters:
    requested: int = 0      # periodic solves given to the worker
    adopted: int = 0        # of them, adopted by a frame
    late: int = 0           # not done when their adoption was due: adopted by a later frame (or dropped)
    restarted: int = 0      # given again to a new worker process, the old one having died
    dropped: int = 0        # requested under a registration or calibration replaced before adoption
    failed: int = 0         # the solve raised, or the worker stuck (the frames keep the refinement they had)
    unreliable: int = 0     # flagged by its own bound, and less sure than the refinement in use: not adopted (kept that one)
    last_failure: str | None = None


@dataclass(frozen=True, kw_only=True)
class _Pending:
    at_ns: int
    video: VideoDetections
    poses: tuple[MarkerPose, ...]
    calibration: LiveCalibration
    future: concurrent.futures.Future
    limits: ReliableLimits = ReliableLimits()
    late: bool = False  # its adoption was due and it was not done


class JointSolveWorker:
    """Tracks frames like :func:`~drillnav.registration.pipeline.track_frame`, with the periodic joint solve in a worker process.

    Use as a context manager (the process starts in ``__enter__``); call :meth:`track` from one thread only (the
    node's frame thread).
    """

    def __init__(self, *, marker_set: MarkerSet, joint_period_ns: int = JOINT_PERIOD_NS, adopt_after_ns: int = ADOPT_AFTER_NS,
                 wait_s: float = WAIT_S, give_up_ns: int = GIVE_UP_NS) -> None:
        if adopt_after_ns < 0 or joint_period_ns <= 0 or wait_s < 0:
            raise ValueError(f"joint_period_ns must be > 0, adopt_after_ns and wait_s >= 0 (got {joint_period_ns}, {adopt_after_ns}, {wait_s})")
        self.marker_set = marker_set
        self.joint_period_ns, self.adopt_after_ns, self.wait_s, self.give_up_ns = joint_period_ns, adopt_after_ns, wait_s, give_up_ns
        self.counters = JointSolveCounters()
        self.refinement: JointRefinement | None = None
        # The last frame's registration (capture stamp, its marker poses, carm_from_drill): a frame whose own tags are
        # not posed in fluoroscopy (the posed ones gloved or glared) looks for them where it put them.
        self._last: tuple[int, tuple[MarkerPose, ...], NDArray[np.float64]] | None = None
        self._pending: _Pending | None = None
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._started: concurrent.futures.Future | None = None

    def __enter__(self) -> JointSolveWorker:
        self._pool = self._new_pool()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        pool, self._pool, self._pending = self._pool, None, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def _new_pool(self) -> concurrent.futures.ProcessPoolExecutor:
        pool = concurrent.futures.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                      initializer=_init_worker, initargs=(self.marker_set,))
        self._started = pool.submit(_ready)  # start the process now (imports take a second or two), not on the first periodic solve
        return pool

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        """Block until the worker process has started (a caller that feeds frames faster than capture time, e.g. a test)."""
        self._started.result(timeout=timeout_s)

    def track(self, image: NDArray[np.uint8], *, calibration: LiveCalibration, poses: tuple[MarkerPose, ...], stamp_ns: int,
              limits: ReliableLimits = ReliableLimits()) -> FrameAxis:
        """One frame (capture stamp ``stamp_ns``) to its axis; raises what ``track_frame`` raises."""
        pending = self._pending
        if pending is not None and not (pending.poses is poses and pending.calibration is calibration):
            pending.future.cancel()
            self._pending, pending = None, None
            self.counters.dropped += 1
        if pending is not None and stamp_ns >= pending.at_ns + self.adopt_after_ns:
            adopted = self._adopt(pending, stamp_ns=stamp_ns)
            if adopted is not None:
                self.refinement = adopted
        last = self._last
        previous = last[2] if last is not None and last[1] is poses and 0 <= stamp_ns - last[0] <= PREVIOUS_POSE_NS else None
        fa = track_frame(image, calibration=calibration, poses=poses, marker_set=self.marker_set, limits=limits, refinement=self.refinement,
                         now_ns=stamp_ns, joint_period_ns=None, previous_carm_from_drill=previous, solve_untracked=False)
        self.refinement = fa.refinement
        self._last = (stamp_ns, poses, fa.registration.carm_from_drill)
        # A frame registered on named tags (outline corners) is not the periodic solve's frame: the next one may be.
        # So is a frame tracked on fewer markers than it sees posed: it asks for its solve now, not a period later.
        if (self._pending is None and fa.refinement is not None and self._pool is not None and not fa.named_ids
                and (fa.wants_solve or refinement_due(fa.refinement, now_ns=stamp_ns, joint_period_ns=self.joint_period_ns))):
            future = self._submit(fa.video, poses, calibration.camera)
            self._pending = _Pending(at_ns=stamp_ns, video=fa.video, poses=poses, calibration=calibration, future=future, limits=limits)
            self.counters.requested += 1
        return fa

    def _submit(self, video: VideoDetections, poses: tuple[MarkerPose, ...], camera: PinholeCamera) -> concurrent.futures.Future:
        try:
            return self._pool.submit(_solve, video, poses, camera)
        except BrokenProcessPool:  # the worker died (killed, out of memory): a new one, once
            self._replace_pool()
            return self._pool.submit(_solve, video, poses, camera)

    def _adopt(self, p: _Pending, *, stamp_ns: int) -> JointRefinement | None:
        """The solve's refinement if it is done (waiting at most ``wait_s``, and only the first time); None otherwise."""
        try:
            reg = p.future.result(timeout=0.0 if p.late else self.wait_s)
        except concurrent.futures.TimeoutError:
            if not p.late:
                self.counters.late += 1
                self._pending = p = replace(p, late=True)
            # Stuck, not starting: a new process takes seconds to import on a loaded machine, and replacing it then
            # would only start another.
            if stamp_ns > p.at_ns + self.adopt_after_ns + self.give_up_ns and self._started is not None and self._started.done():
                self._pending = None
                self._replace_pool()
                self.counters.failed += 1
                self.counters.last_failure = f"the worker did not answer within {self.give_up_ns / 1e9:g} s of capture time; replaced"
            return None
        except BrokenProcessPool:  # the worker died (killed, out of memory): a new one gets the same solve
            self._replace_pool()
            self._pending = replace(p, future=self._pool.submit(_solve, p.video, p.poses, p.calibration.camera))
            self.counters.restarted += 1
            return None
        except concurrent.futures.CancelledError:
            self._pending = None
            return None
        self._pending = None
        if isinstance(reg, str):
            self.counters.failed += 1
            self.counters.last_failure = reg
            return None
        _, pe = frame_predicted_error(p.video, reg.marker_poses or p.poses, reg, calibration=p.calibration, limits=p.limits, fluoro_poses=p.poses)
        current = self.refinement
        if refinement_fits(current, poses=p.poses, calibration=p.calibration) and current.better_than(pe, limits=p.limits):
            # Flagged by its own bound where the refinement in use gave surer frames (two markers, one posed wrong,
            # can throw a solve 100 mm off): the frames keep that one, and the next period tries again.
            self.counters.unreliable += 1
            self.counters.last_failure = (f"the periodic solve was flagged unreliable (90 % bounds {pe.position90_mm:.1f} mm, "
                                          f"{pe.angle90_deg:.1f} deg); the refinement before it kept")
            return replace(current, at_ns=p.at_ns)
        self.counters.adopted += 1
        return joint_refinement(reg, poses=p.poses, calibration=p.calibration, at_ns=p.at_ns, predicted=pe)

    def _replace_pool(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = self._new_pool()
