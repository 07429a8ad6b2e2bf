"""The registration node: keeps the drill axis registered and streaming, whatever arrives.

Camera frames arrive on ``camera/image``; only the newest waits (a bounded
queue of one), so under overload stale frames are dropped and counted, never
queued. Each new fluoroscopy shot (``fluoro/shot``) triggers marker detection
and a new marker registration in a worker thread; every camera frame then goes
through the live pipeline (:func:`~drillnav.registration.pipeline.track_frame`)
to the axis in C with its predicted error, the periodic joint solve in a worker
process (:class:`~drillnav.service.joint_worker.JointSolveWorker`); the tags it
found go out on ``camera/markers`` after the axis. With a
:class:`~drillnav.service.ct_tracker.CtTracker` (video-CT mode), each marker
registration also hands the shots to the CT registration, and every frame's
axis is published in the CT frame too, with conformance to the plan.

No input can stop a stream: every message is decoded into its typed class at
the boundary (``schemas.messages``); one that does not decode is counted per
key, reported once per key and reason as an event, and dropped. Every worker
loop catches what it did not expect (counted, reported once, the loop goes
on), and a supervisor restarts a worker thread that died anyway. Every shot
received ends counted as registered, superseded or failed.

The calibration (camera, drill axis, locator) is one immutable
:class:`~drillnav.registration.pipeline.LiveCalibration`, swapped by reference
in :meth:`RegistrationNode.install_calibration`; without one the node is
``uncalibrated`` and publishes no axis.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import zenoh

from drillnav.registration.axis_uncertainty import AxisUncertainty
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.carm import CArmView
from drillnav.registration.errors import DrillnavError
from drillnav.registration.fluoro_markers import FluoroDetections, detect_in_view
from drillnav.registration.line import Line3D
from drillnav.registration.marker_pose import MarkerPose, register_markers
from drillnav.registration.markers import MarkerSet
from drillnav.registration.overlay import annotate, draw_axis, draw_detections, to_display
from drillnav.registration.pipeline import LiveCalibration, ReliableLimits
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key
from drillnav.service.joint_worker import JointSolveWorker

from . import bus

__all__ = ["RegistrationNode", "NodeCounters"]

MAX_PENDING_SHOTS = 32  # raw shots waiting for the shot loop; beyond it the oldest is refused (counted failed)


@dataclass
class NodeCounters:
    frames_received: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0
    axes_published: int = 0
    shots_received: int = 0
    shots_registered: int = 0
    shots_superseded: int = 0
    shots_failed: int = 0
    registrations: int = 0
    registration_failures: int = 0
    thread_restarts: int = 0
    last_latency_ms: float = 0.0
    latencies_ms: deque = field(default_factory=lambda: deque(maxlen=2000))
    bad_messages: dict[str, int] = field(default_factory=dict)
    loop_errors: dict[str, int] = field(default_factory=dict)


@dataclass
class _Shot:
    image: np.ndarray
    view: CArmView
    stamp_ns: int
    detections: FluoroDetections


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


class RegistrationNode:
    """Use as a context manager: ``with RegistrationNode(session=..., ...) as node:``; threads run inside it.

    ``calibration`` (or ``camera`` and ``axis_drill``) may be None, or only one
    of the two given: the node then streams no axis until
    :meth:`install_calibration` completes it.
    """

    def __init__(self, *, session: zenoh.Session, prefix: str, marker_set: MarkerSet, calibration: LiveCalibration | None = None,
                 camera: PinholeCamera | None = None, axis_drill: Line3D | None = None, axis_uncertainty: AxisUncertainty | None = None, max_views: int = 2,
                 overlay_period_s: float = 0.5, ct_tracker=None, stall_s: float = 1.0, supervise_s: float = 0.25,
                 reliable_limits: ReliableLimits = ReliableLimits(), camera_on_bus: bool = True) -> None:
        """``camera_on_bus=False``: the camera is in this process and hands its frames to :meth:`take_frame`
        (the daemon); True: frames come from the camera key on the bus (a camera elsewhere, a replay).
        ``axis_uncertainty``: drill.json's stated uncertainty of ``axis_drill`` (None: the defaults)."""
        self.camera_on_bus = camera_on_bus
        if calibration is None and camera is not None and axis_drill is not None:
            calibration = LiveCalibration.build(camera=camera, axis_drill=axis_drill, marker_set=marker_set, axis_uncertainty=axis_uncertainty)
        # One of the two alone waits for the other (install_calibration).
        self._half_calibration: dict = {} if calibration is not None else {"camera": camera, "axis_drill": axis_drill, "axis_uncertainty": axis_uncertainty}
        self.session, self.prefix = session, prefix
        self.ct_tracker = ct_tracker
        self.marker_set = marker_set
        self.calibration: LiveCalibration | None = calibration  # read once per frame, replaced whole
        self.max_views = max_views
        self.reliable_limits = reliable_limits
        self.overlay_period_s = overlay_period_s
        self.stall_s, self.supervise_s = stall_s, supervise_s
        self.counters = NodeCounters()
        self.registration_id = 0
        self.poses: tuple[MarkerPose, ...] = ()
        self.shots: dict[str, _Shot] = {}
        # The views of the registration in use (the status's ``views``): a shot is held before its registration is
        # done, and a status naming it then would tell a client that frames are already tracked against it.
        self.registered_views: tuple[str, ...] = ()
        self.last_axis: msg.DrillAxis | None = None
        self.last_axis_ct: msg.DrillAxis | None = None
        self.last_error: str | None = None
        self._registration_state = "waiting for fluoroscopy"
        self._sequence = 0
        self.joint = JointSolveWorker(marker_set=marker_set)  # the periodic joint solve, off the frame path (service/joint_worker.py)
        self._frame: deque = deque(maxlen=1)
        self._shots_in: deque = deque()
        self._wake = threading.Condition()
        self._stop = threading.Event()
        self._reported: set[tuple[str, str]] = set()
        self._overlay_axis: tuple[Line3D, float, int, dict[str, tuple[float, float]]] | None = None
        self._last_frame_in_ns = 0     # monotonic: when a frame last arrived
        self._last_frame_done_ns = 0   # monotonic: when the frame loop last finished a frame (axis or a refusal)
        self._started_ns = 0
        self._workers: dict[str, tuple[Callable[[], None], threading.Thread]] = {}
        self._stack: contextlib.ExitStack | None = None

    # -- lifecycle --------------------------------------------------------------------------------
    def __enter__(self) -> RegistrationNode:
        with contextlib.ExitStack() as stack:
            json_enc = zenoh.Encoding.APPLICATION_JSON
            s, p = self.session, self.prefix
            self._pub_axis = stack.enter_context(bus.declare_publisher(s, p, "axis_carm", encoding=json_enc))
            self._pub_axis_ct = stack.enter_context(bus.declare_publisher(s, p, "axis_ct", encoding=json_enc))
            self._pub_status = stack.enter_context(bus.declare_publisher(s, p, "status", encoding=json_enc))
            self._pub_events = stack.enter_context(bus.declare_publisher(s, p, "events", encoding=json_enc))
            self._pub_markers = stack.enter_context(bus.declare_publisher(s, p, "fluoro_markers", encoding=json_enc))
            self._pub_video = stack.enter_context(bus.declare_publisher(s, p, "camera_markers", encoding=json_enc))
            if self.camera_on_bus:
                stack.enter_context(s.declare_subscriber(key(p, "camera_image"), self._on_frame))
            stack.enter_context(s.declare_subscriber(key(p, "fluoro_shot"), self._on_shot))
            stack.enter_context(self.joint)  # closed after the frame thread is joined (the stack unwinds in reverse)
            self._stop.clear()
            stack.callback(self._join_workers)
            self._started_ns = self._last_frame_done_ns = time.monotonic_ns()
            for name, target in (("frames", self._frame_loop), ("shots", self._shot_loop), ("overlay", self._overlay_loop), ("status", self._status_loop)):
                self._start_worker(name, target)
            self._start_worker("supervisor", self._supervise)
            if self.ct_tracker is not None:
                stack.callback(self.ct_tracker.close)
            self._stack = stack.pop_all()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._stack is not None:
            stack, self._stack = self._stack, None
            stack.close()

    def _join_workers(self) -> None:
        self._stop.set()
        with self._wake:
            self._wake.notify_all()
        deadline = time.monotonic() + 2.0  # daemon threads: one wedged in a computation must not hold the exit
        for _, thread in list(self._workers.values()):
            thread.join(timeout=max(0.0, deadline - time.monotonic()))

    def _start_worker(self, name: str, target: Callable[[], None]) -> None:
        thread = threading.Thread(target=target, name=f"node-{name}", daemon=True)
        # Started before it is listed: a signal handler that raises (the CLI's, during start-up) can interrupt
        # start() itself, and the unwinding's join of a listed thread that never started raised RuntimeError
        # ("cannot join thread before it is started"), turning a clean SIGTERM into a failed start-up. A thread
        # started but not listed sees the stop event and ends.
        thread.start()
        self._workers[name] = (target, thread)

    def _supervise(self) -> None:
        """Restart any worker thread that died (its loop catches Exceptions; this is for whatever escapes)."""
        while not self._stop.wait(self.supervise_s):
            for name, (target, thread) in list(self._workers.items()):
                if name != "supervisor" and not thread.is_alive() and not self._stop.is_set():
                    self.counters.thread_restarts += 1
                    self._event("error", f"worker thread '{name}' died; restarted ({self.counters.thread_restarts} restart(s) so far)")
                    self._start_worker(name, target)

    # -- inputs (zenoh's threads: only queue, never compute) --------------------------------------
    def _on_frame(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        try:
            msg.parse_compressed_image(data)  # the envelope only: pixels are decoded in the frame loop, off zenoh's thread
        except ValueError as exc:
            self._refuse("camera_image", exc)
            return
        except Exception as exc:  # noqa: BLE001 - zenoh's callback thread must never see an exception
            self._loop_error("camera callback", exc)
            return
        self._queue_frame(data)

    def take_frame(self, image: np.ndarray, stamp_ns: int) -> None:
        """A frame from a camera in this process, as captured: no JPEG encode and decode on the frame path.

        image : (H, W) grayscale or (H, W, 3) BGR uint8; ``stamp_ns`` its capture stamp (wall clock, ns).
        The bus still carries the frame (the camera loop publishes its JPEG after handing it here) for the
        recorder and the display; a replay of that recording tracks the JPEG, within its compression of live.
        """
        if not (isinstance(image, np.ndarray) and image.dtype == np.uint8 and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3))):
            shape = getattr(image, "shape", None)
            self._refuse("camera_image", ValueError(f"camera frame: expected (H, W) or (H, W, 3) uint8 pixels, got {type(image).__name__} {shape}"))
            return
        self._queue_frame((image, int(stamp_ns)))

    def _queue_frame(self, item: bytes | tuple[np.ndarray, int]) -> None:
        """Only the newest frame waits: a frame still queued when the next arrives is dropped and counted."""
        self.counters.frames_received += 1
        self._last_frame_in_ns = time.monotonic_ns()
        with self._wake:
            if self._frame:
                self.counters.frames_dropped += 1
            self._frame.append(item)
            self._wake.notify_all()

    def _on_shot(self, sample: zenoh.Sample) -> None:
        # Decoded in the shot loop (a PNG of a megapixel takes milliseconds): a newer shot of the same view counts the older superseded.
        self.counters.shots_received += 1
        with self._wake:
            if len(self._shots_in) >= MAX_PENDING_SHOTS:
                self._shots_in.popleft()
                self.counters.shots_failed += 1
                self._report_once("fluoro_shot", "too many shots waiting: the oldest was dropped", level="warning")
            self._shots_in.append(sample.payload.to_bytes())
            self._wake.notify_all()

    def request_registration(self) -> None:
        """Re-register from the shots already held (e.g. after a marker was bumped and re-imaged)."""
        with self._wake:
            self._shots_in.append(None)
            self._wake.notify_all()

    def install_calibration(self, *, camera: PinholeCamera | None = None, axis_drill: Line3D | None = None,
                            axis_uncertainty: AxisUncertainty | None = None) -> LiveCalibration | None:
        """Replace the camera and/or drill calibration; the locator is rebuilt with the camera, all in one new bundle.

        With only one of the two and no calibration yet, it is kept until the other comes. ``axis_uncertainty``
        goes with ``axis_drill`` (drill.json's stated uncertainty; None: the defaults).
        """
        current = self.calibration
        pending = self._half_calibration
        cam = camera if camera is not None else (current.camera if current is not None else pending.get("camera"))
        if axis_drill is not None:
            axis, unc = axis_drill, axis_uncertainty
        elif current is not None:
            axis, unc = current.axis_drill, current.axis_uncertainty
        else:
            axis, unc = pending.get("axis_drill"), pending.get("axis_uncertainty")
        if cam is None or axis is None:
            self._half_calibration = {"camera": cam, "axis_drill": axis, "axis_uncertainty": unc}
            return None
        if current is not None and camera is None:
            bundle = LiveCalibration(camera=current.camera, axis_drill=axis, locator=current.locator,  # same camera: same locator
                                     axis_uncertainty=unc or AxisUncertainty())
        else:
            bundle = LiveCalibration.build(camera=cam, axis_drill=axis, marker_set=self.marker_set, axis_uncertainty=unc)
        self.calibration = bundle  # one reference: a frame sees the old bundle or the new, never a mix
        self._half_calibration = {}
        return bundle

    # -- reporting ----------------------------------------------------------------------------------
    def _event(self, level: str, message: str, *, key_name: str | None = None, reason: str | None = None) -> None:
        self._pub_events.put(msg.Event(stamp_ns=time.time_ns(), level=level, message=message, key=key_name, reason=reason).to_bytes())

    def _report_once(self, where: str, reason: str, *, level: str = "error") -> None:
        """An event the first time ``where`` meets ``reason`` (a flood of one fault is one event, and counters)."""
        short = reason.split(" (", 1)[0][:200]
        if (where, short) in self._reported:
            return
        self._reported.add((where, short))
        k = key(self.prefix, where) if where in ("camera_image", "fluoro_shot") else None
        self._event(level, f"{k or where}: {short}", key_name=k, reason=short)

    def _refuse(self, topic: str, exc: Exception) -> None:
        k = key(self.prefix, topic)
        self.counters.bad_messages[k] = self.counters.bad_messages.get(k, 0) + 1
        self._report_once(topic, f"message refused: {exc}")

    def _loop_error(self, loop: str, exc: BaseException) -> None:
        self.counters.loop_errors[loop] = self.counters.loop_errors.get(loop, 0) + 1
        self._report_once(f"loop {loop}", f"unexpected {type(exc).__name__}: {exc}")

    # -- work -----------------------------------------------------------------------------
    def _shot_loop(self) -> None:
        while not self._stop.is_set():
            with self._wake:
                while not self._shots_in and not self._stop.is_set():
                    self._wake.wait(0.2)
                if self._stop.is_set():
                    return
                batch = list(self._shots_in)
                self._shots_in.clear()
            try:
                self._take_shots(batch)
            except Exception as exc:  # noqa: BLE001 - a worker survives what it did not foresee
                self._loop_error("shots", exc)

    def _take_shots(self, batch: list[bytes | None]) -> None:
        newest: dict[str, msg.FluoroShot] = {}
        refresh = False
        for data in batch:
            if data is None:
                refresh = True
                continue
            try:
                shot = msg.FluoroShot.from_bytes(data)
            except ValueError as exc:
                self.counters.shots_failed += 1
                self._refuse("fluoro_shot", exc)
                continue
            if shot.view in newest:
                self.counters.shots_superseded += 1
            newest[shot.view] = shot
        if not newest and not refresh:
            return
        detected = 0
        for name, shot in newest.items():
            try:
                det = detect_in_view(shot.image_log, shot.carm_view, self.marker_set)
            except (DrillnavError, ValueError) as exc:
                self.counters.shots_failed += 1
                self._event("error", f"shot '{name}' refused: {exc}")
                continue
            self.shots[name] = _Shot(image=shot.image_log, view=shot.carm_view, stamp_ns=shot.stamp_ns, detections=det)
            detected += 1
            while len(self.shots) > self.max_views:
                oldest = min(self.shots, key=lambda n: self.shots[n].stamp_ns)
                del self.shots[oldest]
            self._event("info", f"shot '{name}': markers {sorted(det.by_id())} identified" + "".join(f"; {r.reason}" for r in det.rejected))
        if not detected and not refresh:
            return
        try:
            self._register()
            self.counters.shots_registered += detected
        except (DrillnavError, ValueError) as exc:
            self.counters.shots_failed += detected
            self.counters.registration_failures += 1
            self.last_error = str(exc)
            self._registration_state = "registration failed: " + str(exc)
            self._event("error", f"registration failed: {exc}")

    def _register(self) -> None:
        names = list(self.shots)
        if not names:
            raise DrillnavError("no fluoroscopy shot held yet")
        poses = register_markers([self.shots[n].detections for n in names], [self.shots[n].view for n in names], self.marker_set)
        good = [p for p in poses if p.converged and not p.needs_camera]
        waiting = [p for p in poses if p.converged and p.needs_camera]
        # One is enough: the camera's markers claim the others' BBs when each frame is registered (video_claims). With
        # none, rings matched only loosely (needs_camera, loose) still let a frame whose camera bears one out register.
        if not good and not waiting:
            raise DrillnavError(f"no marker pose converged in views {names}; at least 1 is needed")
        self.poses = tuple(poses)
        self.registered_views = tuple(names)
        self.registration_id += 1
        self.counters.registrations += 1
        self._registration_state = "registered"
        self.last_error = None
        self._pub_markers.put(msg.FluoroMarkers(
            stamp_ns=time.time_ns(), registration_id=self.registration_id, views=tuple(names),
            markers=tuple(msg.MarkerPoseMsg(id=int(p.marker_id), position_carm_mm=tuple(float(v) for v in p.position_carm_mm), residual_px=float(p.residual_px),
                                            views=int(p.n_views), converged=bool(p.converged), needs_camera=bool(p.needs_camera))
                         for p in poses if not p.loose),  # a loose match is a hypothesis about a ring, not a marker's pose
        ).to_bytes())
        self._event("info", f"registration {self.registration_id} from views {names}: {len(good)} markers"
                    + (f", {len(waiting)} more waiting on the camera" if waiting else ""))
        if self.ct_tracker is not None:
            self.ct_tracker.submit([(self.shots[n].view, self.shots[n].image, self.shots[n].detections) for n in names], self.registration_id)

    def _frame_loop(self) -> None:
        while not self._stop.is_set():
            with self._wake:
                while not self._frame and not self._stop.is_set():
                    self._wake.wait(0.2)
                if self._stop.is_set():
                    return
                data = self._frame.popleft()
            try:
                self._process_frame(data)
            except (DrillnavError, ValueError) as exc:
                self.last_error = str(exc)
            except Exception as exc:  # noqa: BLE001 - a worker survives what it did not foresee
                self._loop_error("frames", exc)
            self._last_frame_done_ns = time.monotonic_ns()

    def _process_frame(self, data: bytes | tuple[np.ndarray, int]) -> None:
        if isinstance(data, tuple):
            image, stamp = data
        else:
            try:
                image, stamp, _ = msg.decode_compressed_image(data)
            except ValueError as exc:
                self._refuse("camera_image", exc)
                return
        self.counters.frames_processed += 1
        calibration, poses = self.calibration, self.poses  # one read each: a swap mid-frame does not mix calibrations
        if calibration is None or not poses:
            return
        # Scheduled on capture time: a replay re-solves and adopts on the same frames.
        fa = self.joint.track(image, calibration=calibration, poses=poses, stamp_ns=stamp, limits=self.reliable_limits)
        reg, pe = fa.registration, fa.predicted_error
        # Each intensifier view's estimated distortion, by the name of the shot it was estimated on (views by identity).
        shots = dict(self.shots)
        distortion = {name: (float(c[0]), float(c[1])) for v, c in reg.detector_distortion_px for name, shot in shots.items() if shot.view is v}
        now = time.time_ns()
        error = msg.PredictedError(position_mm=float(pe.position_mm), angle_deg=float(pe.angle_deg),
                                   position90_mm=_finite_or_none(pe.position90_mm), angle90_deg=_finite_or_none(pe.angle90_deg))
        axis_msg = msg.DrillAxis(
            stamp_ns=now, frame_id="carm", **msg.drill_axis_fields(point_mm=fa.axis_carm.point_mm, direction=fa.axis_carm.direction, carm_from_drill=reg.carm_from_drill),
            predicted_error=error, source_frame_stamp_ns=stamp, registration_id=self.registration_id, sequence=self._sequence, reliable=bool(pe.reliable),
            markers_used=tuple(int(i) for i in reg.used_ids), markers_rejected=tuple(int(i) for i in reg.rejected_ids),
            fre_mm={str(k): float(v) for k, v in reg.fre_mm.items()}, detector_distortion_px=distortion,
        )
        self._pub_axis.put(axis_msg.to_bytes())
        self._sequence += 1
        self.last_axis = axis_msg
        if self.ct_tracker is not None:
            axis_ct = self.ct_tracker.axis_message(fa.axis_carm, stamp_ns=time.time_ns(), source_frame_stamp_ns=stamp, predicted_error=error,
                                                   registration_id=self.registration_id, sequence=self._sequence - 1)
            if axis_ct is not None:
                self._pub_axis_ct.put(axis_ct.to_bytes())
                self.last_axis_ct = axis_ct
        self.counters.axes_published += 1
        latency = (now - stamp) / 1e6
        self.counters.last_latency_ms = latency
        self.counters.latencies_ms.append(latency)
        with self._wake:
            self._overlay_axis = (fa.axis_full_carm, pe.angle_deg, now, distortion)
            self._wake.notify_all()
        # After the axis (never in its latency): the tags this frame showed, for the display's camera preview and tools.
        self._pub_video.put(msg.VideoMarkers(
            stamp_ns=stamp, image_size=fa.video.image_size, ignored_ids=fa.video.ignored_ids, unplaced_ids=fa.video.unplaced_ids,
            misread_ids=fa.video.misread_ids,
            markers=tuple(msg.VideoTag(id=int(m.marker_id), corners_px=tuple(map(tuple, m.corners_px.tolist()))) for m in fa.video.markers),
        ).to_bytes())

    def _overlay_loop(self) -> None:
        """Overlays of the newest axis on each held shot, at most every ``overlay_period_s``, off the frame path."""
        base: dict[tuple[str, int], np.ndarray] = {}  # the shot drawn with its detections, kept per shot
        while not self._stop.wait(self.overlay_period_s):
            with self._wake:
                while self._overlay_axis is None and not self._stop.is_set():
                    self._wake.wait(0.2)
                if self._stop.is_set():
                    return
                (axis, cone_deg, stamp, distortion), self._overlay_axis = self._overlay_axis, None
            try:
                shots = dict(self.shots)
                base = {k: v for k, v in base.items() if k[0] in shots and shots[k[0]].stamp_ns == k[1]}
                for name, shot in shots.items():
                    k = (name, shot.stamp_ns)
                    if k not in base:
                        base[k] = draw_detections(to_display(shot.image), shot.detections)
                    coef = np.asarray(distortion[name]) if name in distortion else None
                    bgr = annotate(draw_axis(base[k], shot.view, axis, cone_half_angle_deg=cone_deg, distortion_px=coef), view_name=name,
                                   stamp_ns=shot.stamp_ns, legend=False)
                    bus.put(self.session, self.prefix, "overlay", msg.compressed_image(bgr, stamp_ns=stamp, frame_id=f"carm/{name}", fmt="jpeg", quality=80), name)
            except Exception as exc:  # noqa: BLE001 - a worker survives what it did not foresee
                self._loop_error("overlay", exc)

    # -- state ------------------------------------------------------------------------------------
    @property
    def state(self) -> str:
        return "uncalibrated" if self.calibration is None else self._registration_state

    def status(self) -> msg.Status:
        c = self.counters
        lat = np.array(c.latencies_ms) if c.latencies_ms else np.zeros(1)
        pending = max(0, c.shots_received - c.shots_registered - c.shots_superseded - c.shots_failed)
        ct = self.ct_tracker.status() if self.ct_tracker is not None else {}
        return msg.Status(
            stamp_ns=time.time_ns(), state=self.state, registration_id=self.registration_id, views=self.registered_views,
            frames_received=c.frames_received, frames_processed=c.frames_processed, frames_dropped=c.frames_dropped,
            axes_published=c.axes_published, shots_received=c.shots_received, registrations=c.registrations,
            registration_failures=c.registration_failures,
            shots=msg.ShotCounts(received=c.shots_received, registered=c.shots_registered, superseded=c.shots_superseded, failed=c.shots_failed, pending=pending),
            bad_messages=dict(c.bad_messages), loop_errors=dict(c.loop_errors), thread_restarts=c.thread_restarts,
            latency_ms_p50=float(np.percentile(lat, 50)), latency_ms_p99=float(np.percentile(lat, 99)),
            last_error=self.last_error, calibrated=self.calibration is not None, **ct,
            joint_solves={k: int(getattr(self.joint.counters, k)) for k in ("requested", "adopted", "late", "restarted", "dropped", "failed", "unreliable")},
        )

    def health(self) -> str | None:
        """None when every stream the node should produce flows; else why not (one line)."""
        now = time.monotonic_ns()
        stall_ns = int(self.stall_s * 1e9)
        for name, (_, thread) in self._workers.items():
            if not thread.is_alive() and not self._stop.is_set():
                return f"worker thread '{name}' is dead"
        if self._last_frame_in_ns and now - self._last_frame_in_ns < stall_ns and self._last_frame_done_ns < self._last_frame_in_ns - stall_ns:
            return f"frames arrive but none was processed for {(now - self._last_frame_done_ns) / 1e9:.1f} s (the frame loop is stuck)"
        return None

    def _status_loop(self) -> None:
        while not self._stop.wait(1.0):
            try:
                self._pub_status.put(self.status().to_bytes())
            except Exception as exc:  # noqa: BLE001 - a worker survives what it did not foresee
                self._loop_error("status", exc)
