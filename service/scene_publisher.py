"""Publishes the navigation scene in Foxglove's schemas on zenoh, from the node's own outputs.

It listens to ``axis/carm``, ``axis/ct``, ``fluoro/shot``, ``fluoro/markers`` and
``registration/events`` and puts protobuf messages on the ``scene/*`` keys
(schemas/topics.py), so the recorder writes them into every MCAP and the
Foxglove bridge serves them live:

- per axis: ``FrameTransform`` carm -> drill_camera and a ``SceneUpdate`` of the axis and its cone
  (camera rate, stamped with the capture stamp); in video-CT mode ``FrameTransform`` carm -> ct;
- per shot: ``FrameTransform`` carm -> carm/<view> and ``CameraCalibration`` of the view;
- per registration: ``FrameTransform`` carm -> marker/<id> and the markers in the ``SceneUpdate``;
- ``ImageAnnotations`` per view (axis, cone edges, markers), at most every ``annotation_period_s``;
- ``Log`` per event.

What does not change between shots (view calibrations and frames, the drill
camera's calibration, markers) is put again every ``republish_period_s``, so a
Foxglove that connects late, or a recording opened in the middle, has it.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import zenoh

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.carm import CArmView
from drillnav.registration.line import Line3D
from drillnav.schemas import foxglove_scene as fox
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key

from .bus import qos_for_key

__all__ = ["ScenePublisher"]


class ScenePublisher:
    """A context manager: subscriptions and the republish thread start in ``__enter__``."""

    def __init__(self, *, session: zenoh.Session, prefix: str, camera: PinholeCamera | None = None,
                 annotation_period_s: float = 0.1, republish_period_s: float = 1.0) -> None:
        if annotation_period_s <= 0 or republish_period_s <= 0:
            raise ValueError("annotation_period_s and republish_period_s must be positive")
        self.session, self.prefix, self.camera = session, prefix, camera
        self.annotation_period_s, self.republish_period_s = annotation_period_s, republish_period_s
        self.decode_errors = 0
        self.published = 0
        self._lock = threading.Lock()
        self._views: dict[str, CArmView] = {}
        self._markers: dict[int, np.ndarray] = {}
        self._latched: dict[tuple[str, str], bytes] = {}  # (key, what) -> message, put again periodically
        self._last_annotations = 0.0
        self._stop = threading.Event()
        self._subs: list = []
        self._thread: threading.Thread | None = None

    def set_camera(self, camera: PinholeCamera) -> None:
        """A new drill-camera calibration (installed over REST), published at once and from then on."""
        self.camera = camera
        cal = fox.drill_camera_calibration(camera, stamp_ns=time.time_ns())
        self._put(key(self.prefix, "scene_calibration", fox.FRAME_DRILL_CAMERA), cal.SerializeToString(), latch="drill_camera")

    def __enter__(self) -> "ScenePublisher":
        p = self.prefix
        if self.camera is not None:
            self.set_camera(self.camera)
        try:
            self._subs = [self.session.declare_subscriber(key(p, "axis_carm"), self._guard(self._on_axis_carm)),
                          self.session.declare_subscriber(key(p, "axis_ct"), self._guard(self._on_axis_ct)),
                          self.session.declare_subscriber(key(p, "fluoro_shot"), self._guard(self._on_shot)),
                          self.session.declare_subscriber(key(p, "fluoro_markers"), self._guard(self._on_markers)),
                          self.session.declare_subscriber(key(p, "events"), self._guard(self._on_event))]
        except Exception:
            self.close()
            raise
        self._thread = threading.Thread(target=self._republish_loop, name="scene-republish", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        for s in self._subs:
            s.undeclare()
        self._subs = []
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    # -- plumbing -------------------------------------------------------------------------
    def _guard(self, handler):
        """A malformed message is counted and skipped; the subscription goes on."""
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                handler(sample.payload.to_bytes())
            except (KeyError, TypeError, ValueError):
                self.decode_errors += 1
        return on_sample

    def _put(self, key_expr: str, data: bytes, *, latch: str | None = None) -> None:
        if latch is not None:
            with self._lock:
                self._latched[(key_expr, latch)] = data
        self.session.put(key_expr, data, **qos_for_key(self.prefix, key_expr))
        self.published += 1

    def _republish_loop(self) -> None:
        while not self._stop.wait(self.republish_period_s):
            with self._lock:
                latched = list(self._latched.items())
            for (key_expr, _), data in latched:
                self.session.put(key_expr, data, **qos_for_key(self.prefix, key_expr))

    # -- handlers -------------------------------------------------------------------------
    def _on_axis_carm(self, data: bytes) -> None:
        doc = msg.decode_json(data)
        stamp = int(doc["source_frame_stamp_ns"])
        axis = Line3D(point_mm=doc["point_mm"], direction=doc["direction"])
        err = doc["predicted_error"]
        p = self.prefix
        self._put(key(p, "scene_tf"), fox.frame_transform(fox.FRAME_CARM, fox.FRAME_DRILL_CAMERA, doc["carm_from_drill"], stamp_ns=stamp).SerializeToString())
        scene = fox.axis_scene(axis, angle_deg=float(err["angle_deg"]), position_mm=float(err["position_mm"]), stamp_ns=stamp)
        self._put(key(p, "scene_entities"), scene.SerializeToString())
        now = time.monotonic()
        if now - self._last_annotations < self.annotation_period_s:
            return
        self._last_annotations = now
        with self._lock:
            views, markers = dict(self._views), dict(self._markers)
        for name, view in views.items():
            ann = fox.view_annotations(view, stamp_ns=stamp, axis_carm=axis, cone_half_angle_deg=float(err["angle_deg"]), markers_carm_mm=markers,
                                       distortion_px=(doc.get("detector_distortion_px") or {}).get(name))
            self._put(key(p, "scene_annotations", name), ann.SerializeToString())

    def _on_axis_ct(self, data: bytes) -> None:
        doc = msg.decode_json(data)
        tf = fox.frame_transform(fox.FRAME_CARM, fox.FRAME_CT, doc["carm_from_ct"], stamp_ns=int(doc["source_frame_stamp_ns"]))
        self._put(key(self.prefix, "scene_tf"), tf.SerializeToString(), latch=fox.FRAME_CT)

    def _on_shot(self, data: bytes) -> None:
        shot = msg.FluoroShot.from_bytes(data)
        view, stamp, name = shot.carm_view, shot.stamp_ns, shot.view
        cal, carm_from_source = fox.view_calibration(view, view_name=name, stamp_ns=stamp)
        with self._lock:
            self._views[name] = view
        p = self.prefix
        self._put(key(p, "scene_tf"), fox.frame_transform(fox.FRAME_CARM, fox.view_frame(name), carm_from_source, stamp_ns=stamp).SerializeToString(),
                  latch=fox.view_frame(name))
        self._put(key(p, "scene_calibration", name), cal.SerializeToString(), latch=name)

    def _on_markers(self, data: bytes) -> None:
        doc = msg.decode_json(data)
        stamp = int(doc["stamp_ns"])
        positions = {int(m["id"]): np.asarray(m["position_carm_mm"], dtype=np.float64) for m in doc["markers"] if m.get("converged", True)}
        with self._lock:
            self._markers = positions
            for k in [k for k in self._latched if k[1].startswith("marker/")]:
                del self._latched[k]  # a marker no longer registered leaves the scene
        p = self.prefix
        for marker_id, pos in positions.items():
            carm_from_marker = np.eye(4)
            carm_from_marker[:3, 3] = pos
            tf = fox.frame_transform(fox.FRAME_CARM, fox.marker_frame(marker_id), carm_from_marker, stamp_ns=stamp)
            self._put(key(p, "scene_tf"), tf.SerializeToString(), latch=fox.marker_frame(marker_id))
        self._put(key(p, "scene_entities"), fox.markers_scene(positions, stamp_ns=stamp).SerializeToString(), latch="markers")

    def _on_event(self, data: bytes) -> None:
        doc = msg.decode_json(data)
        self._put(key(self.prefix, "scene_log"), fox.event_log(str(doc["level"]), str(doc["message"]), stamp_ns=int(doc["stamp_ns"])).SerializeToString())
