"""The live pipeline's joint refinement: the joint solve at most every JOINT_PERIOD_NS, the frames between on its refined markers."""

import os
import signal
import time
from dataclasses import replace

import numpy as np
import pytest

from drillnav.registration.pipeline import JOINT_PERIOD_NS, JointRefinement, LiveCalibration, ReliableLimits, track_frame
from drillnav.service.joint_worker import JointSolveWorker
from twin_replay import recorded_live_inputs



@pytest.fixture(scope="module")
def live():
    return recorded_live_inputs()


def test_frames_between_joint_solves_use_its_refined_markers_and_agree_with_it(live):
    scene, poses, cal, frames = live
    first = track_frame(frames[0], calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=None, now_ns=0)
    assert first.registration.method == "joint" and first.refinement is not None
    ref = first.refinement
    for k, frame in enumerate(frames[1:8], start=1):
        fa = track_frame(frame, calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=ref, now_ns=k * 33_000_000)
        assert fa.registration.method == "horn+pnp on joint-refined markers" and fa.refinement is ref
        full = track_frame(frame, calibration=cal, poses=poses, marker_set=scene.marker_set)  # the joint solve on this frame
        assert np.linalg.norm(fa.axis_carm.point_mm - full.axis_carm.point_mm) < 0.3
        assert np.degrees(np.arccos(min(1.0, float(fa.axis_carm.direction @ full.axis_carm.direction)))) < 0.2
        # The carried covariance gives a predicted error of the joint solve's size, not the Monte-Carlo fallback's.
        assert fa.predicted_error.position90_mm == pytest.approx(full.predicted_error.position90_mm, rel=0.3)


def test_a_new_registration_calibration_or_period_runs_the_joint_solve_again(live):
    scene, poses, cal, frames = live
    ref = track_frame(frames[0], calibration=cal, poses=poses, marker_set=scene.marker_set, now_ns=0).refinement
    again = track_frame(frames[1], calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=ref, now_ns=JOINT_PERIOD_NS)
    assert again.registration.method == "joint" and again.refinement is not ref
    new_poses = tuple(list(poses))  # another registration (a new tuple), though equal
    assert track_frame(frames[1], calibration=cal, poses=new_poses, marker_set=scene.marker_set, refinement=ref, now_ns=1).registration.method == "joint"
    new_cal = LiveCalibration.build(camera=cal.camera, axis_drill=cal.axis_drill, marker_set=scene.marker_set)
    assert track_frame(frames[1], calibration=new_cal, poses=poses, marker_set=scene.marker_set, refinement=ref, now_ns=1).registration.method == "joint"


# Limits no registration meets: every solve under them is flagged by its own bound.
STRICT = ReliableLimits(position_mm=1e-3, angle_deg=1e-3)


def test_a_re_solve_flagged_by_its_own_bound_does_not_replace_a_reliable_refinement(live):
    # (On the hard twin, seed 6100's random pair, a periodic re-solve on two markers came out 178 mm off, flagged; the
    # 15 frames tracked on it after were 49-181 mm off. benchmarks/live_path.py measures that case.)
    scene, poses, cal, frames = live
    first = track_frame(frames[0], calibration=cal, poses=poses, marker_set=scene.marker_set, now_ns=0)
    assert first.refinement.reliable and first.predicted_error.reliable
    kept = track_frame(frames[1], calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=first.refinement,
                       now_ns=JOINT_PERIOD_NS, limits=STRICT)
    # The re-solve was due and ran; flagged, it is not adopted: the frame is tracked on the refinement it had, whose
    # clock restarts (the next try is a period away).
    assert kept.registration.method == "horn+pnp on joint-refined markers"
    assert kept.refinement.poses is first.refinement.poses and kept.refinement.at_ns == JOINT_PERIOD_NS
    # The same re-solve under the usual limits is adopted.
    adopted = track_frame(frames[1], calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=first.refinement, now_ns=JOINT_PERIOD_NS)
    assert adopted.registration.method == "joint" and adopted.refinement.poses is not first.refinement.poses
    # A refinement that was itself flagged gives way to a flagged solve with smaller bounds, not to one with larger.
    flagged = track_frame(frames[0], calibration=cal, poses=poses, marker_set=scene.marker_set, now_ns=0, limits=STRICT).refinement
    assert not flagged.reliable and flagged.bound90 == (first.predicted_error.position90_mm, first.predicted_error.angle90_deg)
    for bound, replaced in ((1e3, True), (1e-9, False)):
        worse = replace(flagged, bound90=(bound, bound))
        again = track_frame(frames[1], calibration=cal, poses=poses, marker_set=scene.marker_set, refinement=worse, now_ns=JOINT_PERIOD_NS, limits=STRICT)
        assert (again.refinement.poses is not worse.poses) == replaced
        assert again.registration.method == ("joint" if replaced else "horn+pnp on joint-refined markers")


def test_which_of_a_refinement_and_a_new_solve_is_surer():
    from drillnav.registration.video_fluoro import PredictedError

    limits = ReliableLimits(position_mm=2.0, angle_deg=2.0)
    pe = lambda p, a, ok: PredictedError(position_mm=p, angle_deg=a, cone_half_angle_deg=a, position90_mm=p, angle90_deg=a, reliable=ok)  # noqa: E731
    ref = lambda p, a, ok: JointRefinement(source_poses=(), calibration=None, poses=(), covariance_drill=np.eye(6), pivot_drill_mm=np.zeros(3),  # noqa: E731
                                           at_ns=0, reliable=ok, bound90=(p, a))
    assert not ref(1.0, 1.0, True).better_than(pe(0.5, 0.5, True), limits=limits)   # a reliable solve is never worse
    assert not ref(1.0, 1.0, True).better_than(pe(3.0, 3.0, True), limits=limits)
    assert ref(1.0, 1.0, True).better_than(pe(1.0, 1.0, False), limits=limits)       # flagged (one marker): worse than reliable
    assert ref(3.0, 1.0, False).better_than(pe(1.0, 5.0, False), limits=limits)      # 1.5 x its limit against 2.5 x
    assert not ref(3.0, 1.0, False).better_than(pe(2.5, 2.5, False), limits=limits)  # against 1.25 x


def test_the_worker_does_not_adopt_a_periodic_solve_flagged_by_its_own_bound(live):
    scene, poses, cal, frames = live
    frames = (frames * 4)[:30]
    stamps = _stamps(len(frames))
    with JointSolveWorker(marker_set=scene.marker_set, joint_period_ns=400_000_000, adopt_after_ns=100_000_000, wait_s=30.0) as worker:
        worker.wait_ready()
        first = worker.track(frames[0], calibration=cal, poses=poses, stamp_ns=stamps[0])
        out = [worker.track(f, calibration=cal, poses=poses, stamp_ns=s, limits=STRICT) for f, s in zip(frames[1:], stamps[1:])]
        counters = worker.counters
    assert first.refinement.reliable
    assert counters.requested >= 1 and counters.unreliable >= 1 and counters.adopted == 0 and counters.failed == 0
    assert "flagged unreliable" in counters.last_failure
    assert all(fa.refinement.poses is first.refinement.poses for fa in out)
    assert all(fa.registration.method == "horn+pnp on joint-refined markers" for fa in out)


def _stamps(n: int, *, period_ns: int = 33_333_333) -> list[int]:
    return [1_000_000_000 + k * period_ns for k in range(n)]


def test_the_worker_solves_periodically_off_the_frame_path_and_frames_adopt_on_capture_time(live):
    scene, poses, cal, frames = live
    frames = (frames * 4)[:40]  # ~1.3 s of capture time at 30 frames/s: two periodic solves
    stamps = _stamps(len(frames))
    # Frames come faster than capture time here: the adopting frame may wait (wait_s) so the schedule is capture time's alone.
    with JointSolveWorker(marker_set=scene.marker_set, joint_period_ns=400_000_000, adopt_after_ns=100_000_000, wait_s=30.0) as worker:
        worker.wait_ready()
        out = [worker.track(f, calibration=cal, poses=poses, stamp_ns=s) for f, s in zip(frames, stamps)]
        counters = worker.counters
    assert out[0].registration.method == "joint"  # the first frame of a registration: solved at once, on the frame path
    assert all(fa.registration.method != "joint" for fa in out[1:]), "a periodic solve ran on the frame path"
    # Requested on the first frame 0.4 s after the last solve, adopted on the first frame 0.1 s after that: capture time alone decides.
    req1 = next(k for k, s in enumerate(stamps) if s - stamps[0] >= 400_000_000)
    adopt1 = next(k for k, s in enumerate(stamps) if s >= stamps[req1] + 100_000_000)
    req2 = next(k for k, s in enumerate(stamps) if s - stamps[req1] >= 400_000_000)
    adopt2 = next(k for k, s in enumerate(stamps) if s >= stamps[req2] + 100_000_000)
    expected = [stamps[0]] * adopt1 + [stamps[req1]] * (adopt2 - adopt1) + [stamps[req2]] * (len(out) - adopt2)
    assert [fa.refinement.at_ns for fa in out] == expected
    assert counters.requested >= 2 and counters.adopted == 2 and counters.late == 0 and counters.failed == 0
    # The worker's solve is the frame path's solve of the same frame: the same refined markers.
    inline = track_frame(frames[req1], calibration=cal, poses=poses, marker_set=scene.marker_set, now_ns=stamps[req1]).refinement
    adopted = out[adopt1].refinement
    for a, b in zip(adopted.poses, inline.poses):
        np.testing.assert_allclose(a.carm_from_marker, b.carm_from_marker, atol=1e-9)
    np.testing.assert_allclose(adopted.covariance_drill, inline.covariance_drill, rtol=1e-6, atol=1e-12)


def test_a_new_registration_drops_the_pending_solve_and_a_dead_worker_is_replaced(live):
    scene, poses, cal, frames = live
    stamps = _stamps(24)
    with JointSolveWorker(marker_set=scene.marker_set, joint_period_ns=100_000_000, adopt_after_ns=100_000_000, wait_s=30.0) as worker:
        worker.wait_ready()
        for k in range(5):  # a solve is requested at frame 3
            worker.track(frames[k % len(frames)], calibration=cal, poses=poses, stamp_ns=stamps[k])
        assert worker.counters.requested == 1
        new_poses = tuple(list(poses))  # another registration, though equal
        fa = worker.track(frames[5 % len(frames)], calibration=cal, poses=new_poses, stamp_ns=stamps[5])
        assert fa.registration.method == "joint" and fa.refinement.source_poses is new_poses  # solved at once, never the old one adopted
        assert worker.counters.dropped == 1 and worker.counters.adopted == 0
        # Kill the worker process mid-run: a new process gets the same solve, and a frame adopts it.
        for proc in list(worker._pool._processes.values()):  # noqa: SLF001 - the test needs the real process to kill
            proc.kill()
            proc.join(5)
        for k in range(6, 14):  # request at the first frame 0.1 s after frame 5, adopted 0.1 s later
            worker.track(frames[k % len(frames)], calibration=cal, poses=new_poses, stamp_ns=stamps[k])
        c = worker.counters
        assert c.requested >= 2 and c.adopted == 1 and c.failed == 0, c
        worker.wait_ready()  # a new process (the dead one's replacement) serves the next request
        for k in range(14, 24):
            worker.track(frames[k % len(frames)], calibration=cal, poses=new_poses, stamp_ns=stamps[k])
        assert c.adopted >= 2 and c.late == 0 and c.failed == 0, c


def _worker_pids(worker) -> list[int]:
    return [p.pid for p in worker._pool._processes.values()]  # noqa: SLF001 - the test pauses the real process


def test_a_late_worker_never_holds_a_frame_it_is_adopted_later_or_replaced_when_stuck(live):
    """The worker process paused (SIGSTOP, as a starved process looks): frames go on with the refinement they have and
    never solve it themselves; resumed, the first frame after the solve is done adopts it; paused past give_up_ns of
    capture time, it is replaced and the next request is adopted."""
    scene, poses, cal, frames = live
    stamps = _stamps(200)
    paused: list[int] = []
    try:
        with JointSolveWorker(marker_set=scene.marker_set, joint_period_ns=100_000_000, adopt_after_ns=100_000_000, wait_s=0.0,
                              give_up_ns=1_000_000_000) as worker:
            worker.wait_ready()
            paused = _worker_pids(worker)
            for pid in paused:
                os.kill(pid, signal.SIGSTOP)
            out = [worker.track(frames[k % len(frames)], calibration=cal, poses=poses, stamp_ns=stamps[k]) for k in range(10)]
            c = worker.counters
            assert c.requested == 1 and c.late == 1 and c.adopted == 0, c
            assert all(fa.registration.method != "joint" for fa in out[1:]), "a frame solved the late solve itself"
            for pid in paused:
                os.kill(pid, signal.SIGCONT)
            k = 10
            deadline = time.monotonic() + 30
            while c.adopted == 0 and time.monotonic() < deadline:  # real time for the resumed worker; capture time stays short of give-up
                fa = worker.track(frames[k % len(frames)], calibration=cal, poses=poses, stamp_ns=stamps[10])
                time.sleep(0.05)
            assert c.adopted == 1 and c.failed == 0, c
            asked = next(s for s in stamps if s - stamps[0] >= 100_000_000)
            assert fa.refinement.at_ns == asked  # the solve of the frame that asked for it (0.1 s after the first)
            # Stuck: paused again past give_up_ns of capture time after its adoption fell due.
            for pid in paused:
                os.kill(pid, signal.SIGSTOP)
            for k in range(11, 60):
                fa = worker.track(frames[k % len(frames)], calibration=cal, poses=poses, stamp_ns=stamps[k])
                assert fa.registration.method != "joint"
            assert c.failed == 1 and "did not answer" in c.last_failure, c
            assert set(_worker_pids(worker)).isdisjoint(paused)  # a new process
    finally:
        for pid in paused:
            for sig in (signal.SIGCONT, signal.SIGKILL):
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
