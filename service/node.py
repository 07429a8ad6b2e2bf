"""The registration node: keeps the drill axis registered and streaming.

Camera frames arrive on ``camera/image``; only the newest waits (a bounded
queue of one), so under overload stale frames are dropped and counted, never
queued. Each new fluoroscopy shot (``fluoro/shot``) triggers marker detection
and a new marker registration in a worker thread; every camera frame then gives
``carm_from_drill`` and the axis in C with its predicted error. With a
:class:`~drillnav.service.ct_tracker.CtTracker` (video-CT mode), each marker
registration also hands the shots to the CT registration, and every frame's
axis is published in the CT frame too, with conformance to the plan.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import zenoh

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.carm import CArmView
from drillnav.registration.errors import DrillnavError
from drillnav.registration.fluoro_markers import FluoroDetections, detect_markers
from drillnav.registration.line import Line3D
from drillnav.registration.marker_pose import MarkerPose, register_markers
from drillnav.registration.markers import MarkerSet
from drillnav.registration.overlay import annotate, draw_axis, draw_detections, to_display
from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro
from drillnav.registration.video_markers import VideoMarkerLocator
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key

__all__ = ["RegistrationNode", "NodeCounters"]


@dataclass
class NodeCounters:
    frames_received: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0
    axes_published: int = 0
    shots_received: int = 0
    registrations: int = 0
    registration_failures: int = 0
    last_latency_ms: float = 0.0
    latencies_ms: deque = field(default_factory=lambda: deque(maxlen=2000))


@dataclass
class _Shot:
    image: np.ndarray
    view: CArmView
    stamp_ns: int
    detections: FluoroDetections


class RegistrationNode:
    def __init__(self, *, session: zenoh.Session, prefix: str, marker_set: MarkerSet, camera: PinholeCamera, axis_drill: Line3D, max_views: int = 2,
                 overlay_period_s: float = 0.5, ct_tracker=None) -> None:
        self.session, self.prefix = session, prefix
        self.ct_tracker = ct_tracker
        self.marker_set, self.camera, self.axis_drill = marker_set, camera, axis_drill
        self.max_views = max_views
        self.overlay_period_s = overlay_period_s
        self.locator = VideoMarkerLocator(camera=camera, marker_ids=marker_set.ids, tag_size_mm=marker_set.markers[0].tag_size_mm)
        self.counters = NodeCounters()
        self.state = "waiting for fluoroscopy"
        self.registration_id = 0
        self.poses: tuple[MarkerPose, ...] = ()
        self.shots: dict[str, _Shot] = {}
        self.last_axis: dict | None = None
        self.last_axis_ct: dict | None = None
        self.last_error: str | None = None
        self._frame: deque = deque(maxlen=1)
        self._shots_in: deque = deque(maxlen=4)
        self._wake = threading.Condition()
        self._stop = threading.Event()
        self._overlay_axis: tuple[Line3D, float, int] | None = None
        self._pub_axis = session.declare_publisher(key(prefix, "axis_carm"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self._pub_axis_ct = session.declare_publisher(key(prefix, "axis_ct"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self._pub_status = session.declare_publisher(key(prefix, "status"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self._pub_events = session.declare_publisher(key(prefix, "events"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self._pub_markers = session.declare_publisher(key(prefix, "fluoro_markers"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self._subs = [
            session.declare_subscriber(key(prefix, "camera_image"), self._on_frame),
            session.declare_subscriber(key(prefix, "fluoro_shot"), self._on_shot),
        ]
        self._threads = [threading.Thread(target=self._frame_loop, name="node-frames", daemon=True),
                         threading.Thread(target=self._shot_loop, name="node-shots", daemon=True),
                         threading.Thread(target=self._status_loop, name="node-status", daemon=True),
                         threading.Thread(target=self._overlay_loop, name="node-overlay", daemon=True)]
        for t in self._threads:
            t.start()

    # -- inputs ---------------------------------------------------------------------------
    def _on_frame(self, sample: zenoh.Sample) -> None:
        self.counters.frames_received += 1
        with self._wake:
            if self._frame:
                self.counters.frames_dropped += 1
            self._frame.append(sample.payload.to_bytes())
            self._wake.notify_all()

    def _on_shot(self, sample: zenoh.Sample) -> None:
        self.counters.shots_received += 1
        with self._wake:
            self._shots_in.append(sample.payload.to_bytes())
            self._wake.notify_all()

    def request_registration(self) -> None:
        """Re-register from the shots already held (e.g. after a marker was bumped and re-imaged)."""
        with self._wake:
            self._shots_in.append(b"")
            self._wake.notify_all()

    # -- work -----------------------------------------------------------------------------
    def _event(self, level: str, message: str) -> None:
        self._pub_events.put(msg.encode_json({"stamp_ns": time.time_ns(), "level": level, "message": message}))

    def _shot_loop(self) -> None:
        while not self._stop.is_set():
            with self._wake:
                while not self._shots_in and not self._stop.is_set():
                    self._wake.wait(0.2)
                if self._stop.is_set():
                    return
                data = self._shots_in.popleft()
            try:
                if data:
                    image, view, stamp, name = msg.decode_fluoro_shot(data)
                    det = detect_markers(image, self.marker_set, pixel_spacing_mm=view.pixel_spacing_mm[1])
                    self.shots[name] = _Shot(image=image, view=view, stamp_ns=stamp, detections=det)
                    while len(self.shots) > self.max_views:
                        oldest = min(self.shots, key=lambda n: self.shots[n].stamp_ns)
                        del self.shots[oldest]
                    self._event("info", f"shot '{name}': markers {sorted(det.by_id())} identified" + "".join(f"; {r.reason}" for r in det.rejected))
                self._register()
            except (DrillnavError, ValueError) as exc:
                self.counters.registration_failures += 1
                self.last_error = str(exc)
                self.state = "registration failed: " + str(exc)
                self._event("error", f"registration failed: {exc}")

    def _register(self) -> None:
        names = list(self.shots)
        poses = register_markers([self.shots[n].detections for n in names], [self.shots[n].view for n in names], self.marker_set)
        good = [p for p in poses if p.converged]
        if len(good) < 3:
            raise DrillnavError(f"only {len(good)} marker pose(s) converged in views {names}; at least 3 are needed")
        self.poses = tuple(poses)
        self.registration_id += 1
        self.counters.registrations += 1
        self.state = "registered"
        self.last_error = None
        self._pub_markers.put(msg.encode_json({
            "stamp_ns": time.time_ns(), "registration_id": self.registration_id, "views": names,
            "markers": [{"id": p.marker_id, "position_carm_mm": p.position_carm_mm.tolist(), "residual_px": p.residual_px, "views": p.n_views, "converged": p.converged} for p in poses],
        }))
        self._event("info", f"registration {self.registration_id} from views {names}: {len(good)} markers")
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

    def _process_frame(self, data: bytes) -> None:
        image, stamp, _ = msg.decode_compressed_image(data)
        self.counters.frames_processed += 1
        video = self.locator.locate(image)
        if not self.poses:
            return
        reg = register_video_to_fluoro(video, self.poses, self.marker_set, self.camera)
        axis = self.axis_drill.transformed(reg.carm_from_drill)
        centroid = np.mean([p.position_carm_mm for p in self.poses if p.marker_id in reg.used_ids], axis=0)
        work = axis.closest_point(centroid)
        pe = predicted_axis_error(video, self.poses, reg, self.axis_drill, working_point_carm_mm=work)  # vectorised: ~1 ms
        now = time.time_ns()
        doc = {
            "stamp_ns": now, "frame_id": "carm", "point_mm": work.tolist(), "direction": axis.direction.tolist(),
            "predicted_error": {"position_mm": pe.position_mm, "angle_deg": pe.angle_deg},
            "source_frame_stamp_ns": stamp, "registration_id": self.registration_id,
            "markers_used": list(reg.used_ids), "markers_rejected": list(reg.rejected_ids), "fre_mm": {str(k): v for k, v in reg.fre_mm.items()},
            "carm_from_drill": reg.carm_from_drill.tolist(),
        }
        self._pub_axis.put(msg.encode_json(doc))
        self.last_axis = doc
        if self.ct_tracker is not None:
            doc_ct = self.ct_tracker.axis_message(Line3D(point_mm=work, direction=axis.direction), stamp_ns=time.time_ns(), source_frame_stamp_ns=stamp,
                                                  predicted_error=doc["predicted_error"])
            if doc_ct is not None:
                doc_ct["registration_id"] = self.registration_id
                self._pub_axis_ct.put(msg.encode_json(doc_ct))
                self.last_axis_ct = doc_ct
        self.counters.axes_published += 1
        latency = (now - stamp) / 1e6
        self.counters.last_latency_ms = latency
        self.counters.latencies_ms.append(latency)
        with self._wake:
            self._overlay_axis = (axis, pe.angle_deg, now)
            self._wake.notify_all()

    def _overlay_loop(self) -> None:
        """Overlays of the newest axis on each held shot, at most every ``overlay_period_s``, off the frame path."""
        base: dict[tuple[str, int], np.ndarray] = {}  # the shot drawn with its detections, kept per shot
        while not self._stop.wait(self.overlay_period_s):
            with self._wake:
                while self._overlay_axis is None and not self._stop.is_set():
                    self._wake.wait(0.2)
                if self._stop.is_set():
                    return
                (axis, cone_deg, stamp), self._overlay_axis = self._overlay_axis, None
            shots = dict(self.shots)
            base = {k: v for k, v in base.items() if k[0] in shots and shots[k[0]].stamp_ns == k[1]}
            for name, shot in shots.items():
                k = (name, shot.stamp_ns)
                if k not in base:
                    base[k] = draw_detections(to_display(shot.image), shot.detections)
                bgr = annotate(draw_axis(base[k], shot.view, axis, cone_half_angle_deg=cone_deg), view_name=name, stamp_ns=shot.stamp_ns, legend=False)
                self.session.put(key(self.prefix, "overlay", name), msg.compressed_image(bgr, stamp_ns=stamp, frame_id=f"carm/{name}", fmt="jpeg", quality=80))

    def status(self) -> dict:
        c = self.counters
        lat = np.array(c.latencies_ms) if c.latencies_ms else np.zeros(1)
        return {
            "stamp_ns": time.time_ns(), "state": self.state, "registration_id": self.registration_id, "views": list(self.shots),
            "frames_received": c.frames_received, "frames_processed": c.frames_processed, "frames_dropped": c.frames_dropped,
            "axes_published": c.axes_published, "shots_received": c.shots_received, "registrations": c.registrations,
            "registration_failures": c.registration_failures, "latency_ms_p50": float(np.percentile(lat, 50)), "latency_ms_p99": float(np.percentile(lat, 99)),
            "last_error": self.last_error,
            **(self.ct_tracker.status() if self.ct_tracker is not None else {}),
        }

    def _status_loop(self) -> None:
        while not self._stop.wait(1.0):
            self._pub_status.put(msg.encode_json(self.status()))

    def close(self) -> None:
        self._stop.set()
        with self._wake:
            self._wake.notify_all()
        for s in self._subs:
            s.undeclare()
        for t in self._threads:
            t.join(timeout=5)
        if self.ct_tracker is not None:
            self.ct_tracker.close()
