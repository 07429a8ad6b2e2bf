"""The daemon: bus, camera, C-arm intake, registration node, recorder and REST API, as one context manager.

``with Daemon(settings) as d:`` starts every part through one
``contextlib.ExitStack``; a failure anywhere in start-up closes what was
already started and raises :class:`StartupError` (one line naming the
problem), and leaving the block stops everything in reverse order, with the
recordings finalised. What can fail fast (zenoh, the REST and DICOM ports,
the camera device, the calibration files) is tried before what is slow (the
digital twin, the CT).

On real devices the daemon starts without calibrations when none is
configured: the camera streams, the status says ``uncalibrated`` and no axis
is published, so a live calibration job can run first; installing both
calibrations (REST) starts the axis.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import os
import re
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drillnav.drivers.fluoro_dicom import read_fluoro
from drillnav.registration.errors import DrillnavError
from drillnav.registration.markers import default_marker_set
from drillnav.registration.overlay import to_display
from drillnav.schemas import messages as msg
from drillnav.schemas.calibration import read_camera_calibration, read_drill_calibration, read_drill_uncertainty
from drillnav.schemas.markers import read_marker_set
from drillnav.schemas.topics import TOPICS, key

from . import bus
from .bus import open_session
from .camera_pump import CameraPump
from .fluoro_polarity import settle_polarity
from .node import RegistrationNode
from .recorder import CarriedState, Recorder
from .settings import Settings

__all__ = ["Daemon", "StartupError"]


class StartupError(DrillnavError):
    """The daemon could not start; the message names the part and the problem (one line)."""


class Daemon:
    """Owns every running part. ``with Daemon(settings, progress=print) as d: ...``."""

    def __init__(self, settings: Settings, *, progress: Callable[[str], None] = lambda line: None, stall_s: float = 2.0) -> None:
        self.settings = settings
        self.token = settings.api.token or ""  # resolved (the twin's random one) at start: see _start
        self.prefix = settings.zenoh.prefix
        self.progress = progress
        self.stall_s = stall_s
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._recorders: dict[str, Recorder] = {}
        self._finished: dict[str, list[str]] = {}
        self.errors: list[str] = []
        self.carm = None
        self.calibration_jobs = None
        self.scp = None
        self.intake = self.audit = self.carried = None
        self.scene_publisher = self.igtl = None  # set by _start_interop when enabled
        self.display_hub = None
        self.pump: CameraPump | None = None
        self._frame_lock = threading.Condition()
        self._latest_frame: tuple[int, Any] | None = None
        self._last_frame_ns = 0  # monotonic, camera loop
        self._recorder_seen: dict[str, tuple[int, int]] = {}  # name -> (messages, monotonic ns when it last grew)
        self._stack: contextlib.ExitStack | None = None
        self.started = False

    # -- lifecycle -------------------------------------------------------------------------
    def __enter__(self) -> Daemon:
        with contextlib.ExitStack() as stack:
            stack.callback(self._stop.set)  # registered first, runs last: every loop sees it
            self._start(stack)
            self._stack = stack.pop_all()
        self.started = True
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.started = False
        if self._stack is not None:
            stack, self._stack = self._stack, None
            stack.close()

    def _start(self, stack: contextlib.ExitStack) -> None:
        s = self.settings
        from .auth import resolve_token

        try:
            self.token = resolve_token(s)  # none on a real device: refused; the twin makes a random one and prints it once
        except DrillnavError as exc:
            raise StartupError(str(exc)) from None
        self.session = stack.enter_context(self._open_session())
        self.progress(f"zenoh up ({s.zenoh.mode}, listening on {', '.join(s.zenoh.listen) or '(none)'})")
        # The latest state (calibration, shots, markers, status) from start-up on, so a recording begun mid-case
        # starts with what it needs to replay alone.
        self.carried = CarriedState(prefix=self.prefix)
        for sub in self.carried.subscribe(self.session):
            stack.callback(sub.undeclare)
        from .audit import AuditLog

        self.audit = AuditLog(folder=s.api.audit_folder, on_entry=self._publish_audit)
        stack.callback(self.audit.close)
        stack.callback(self._close_recorders)  # after the session's subscribers are gone: registered after it, runs before
        api_socket = _bind("REST API", s.api.host, s.api.port)  # bound now: a taken port fails in a second, not after the twin
        stack.callback(api_socket.close)
        from .dicom_intake import DicomIntake

        # The C-STORE SCP (received images fsynced into the watched folder before they are acknowledged), the
        # folder watcher with its journal of processed files, and the retention of incoming images.
        try:
            self.intake = stack.enter_context(DicomIntake(settings=s.dicom, on_error=self._intake_error))
        except OSError as exc:
            raise StartupError(f"dicom.watch_folder {s.dicom.watch_folder}: {exc.strerror or exc}") from None
        self.scp = self.intake.scp
        if self.scp is not None:
            self.progress(f"DICOM up: C-STORE to AE {s.dicom.ae_title} at {s.dicom.scp_host}:{s.dicom.scp_port}" + (" (TLS)" if s.dicom.tls_cert else ""))
        marker_set, calibration = self._devices()
        from drillnav.registration.pipeline import ReliableLimits

        limits = ReliableLimits(position_mm=s.registration.unreliable_position_mm, angle_deg=s.registration.unreliable_angle_deg)
        self.node = stack.enter_context(RegistrationNode(session=self.session, prefix=self.prefix, marker_set=marker_set, **calibration,
                                                         ct_tracker=self._ct_tracker(), reliable_limits=limits, camera_on_bus=False))
        self._publish_calibration()
        self._start_interop(stack, axis_drill=calibration["axis_drill"], camera=calibration["camera"])
        from .display_hub import DisplayHub

        tracker = self.node.ct_tracker  # the surgeon's page: its streams from this session, the CT and plan once
        self.display_hub = stack.enter_context(DisplayHub(session=self.session, prefix=self.prefix,
                                                          plan=[e.trajectory for e in tracker.plan] if tracker is not None else (),
                                                          ct=tracker.ct if tracker is not None else None))
        missing = [k for k, v in calibration.items() if v is None]
        self.progress("registration node up" + (f" (uncalibrated: no {' and no '.join(missing)} calibration yet; no axis until installed)" if missing else ""))
        self._start_calibration_jobs(stack)
        if s.recording.record_on_start:
            self.start_recording("session")
            self.progress(f"recording into {s.recording.folder}/")
        stack.callback(self._join_threads)
        self._spawn(self._camera_loop, "camera")
        self._spawn(self._dicom_loop, "dicom")
        self._start_api(stack, api_socket)
        self.progress(f"REST up on http://{s.api.host}:{api_socket.getsockname()[1]}")
        # Everything built so far (libraries, the twin, the CT) lives as long as the daemon. Out of the
        # collector's sight, its full collections scan only what came after: ~100 ms pauses every
        # half minute, which cost camera frames, become ~1 ms ones.
        gc.collect()
        gc.freeze()
        # A thread that computes in Python (marker detection after a shot) hands the GIL over after 1 ms, not 5:
        # the frame thread waits at most that long at each of its hand-overs.
        sys.setswitchinterval(0.001)
        if self.carm is not None:
            for view in self.carm.scene.views:
                self.carm.shoot(view)

    def _open_session(self):
        s = self.settings.zenoh
        try:
            return open_session(s)  # TLS, authentication and access control from [zenoh] (docs/security.md)
        except (ValueError, DrillnavError) as exc:
            raise StartupError(f"zenoh: {exc}") from None
        except Exception as exc:  # zenoh.ZError: an endpoint that does not parse, or a listen port taken
            text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            first = re.sub(r"\s+at \S+\.rs:\d+\.?", "", text)  # zenoh's Rust source locations say nothing to an operator
            raise StartupError(f"zenoh cannot open a session (listen {s.listen}, connect {s.connect}): {first}") from None

    def _devices(self) -> tuple[Any, dict[str, Any]]:
        """The camera and C-arm devices; the marker set and the calibration's ``camera`` and ``axis_drill`` (either None: not yet calibrated)."""
        s = self.settings
        if s.twin:
            from drillnav.drivers.sim.devices import TwinCArm, TwinDrillCamera
            from drillnav.drivers.sim.scene import AXIS_CALIBRATION_UNCERTAINTY, make_scene

            self.progress("building the digital twin ...")
            scene = make_scene(seed=s.twin_scene.seed, n_markers=s.twin_scene.markers, views=s.twin_scene.views, render=False)
            marker_set = scene.marker_set
            self.camera_device = TwinDrillCamera(scene=scene, fps=s.camera.fps, seed=s.twin_scene.seed,
                                                 unplug_every_s=s.twin_scene.camera_unplug_every_s, unplug_s=s.twin_scene.camera_unplug_s,
                                                 aim_off_mm=s.twin_scene.aim_off_mm)
            send_to = (s.dicom.scp_host, s.dicom.scp_port, s.dicom.ae_title) if s.dicom.scp_enabled else None
            self.carm = TwinCArm(scene=scene, folder=s.dicom.watch_folder / ".twin", seed=s.twin_scene.seed, send_to=send_to)
            self.progress("digital twin up")
            return marker_set, {"camera": scene.calibrated_camera, "axis_drill": scene.calibrated_axis_drill, "axis_uncertainty": AXIS_CALIBRATION_UNCERTAINTY}
        from drillnav.drivers.webcam import Webcam

        device = s.camera.device
        if device.startswith("/dev/") and not os.path.exists(device):
            raise StartupError(f"camera.device {device} does not exist (is the camera plugged in?)")
        try:
            marker_set = read_marker_set(s.markers_file) if s.markers_file else default_marker_set()
            cam_path = s.camera.calibration or self._active_calibration("camera")
            drill_path = s.camera.drill_calibration or self._active_calibration("drill")
            camera = read_camera_calibration(cam_path) if cam_path is not None else None
            axis = read_drill_calibration(drill_path) if drill_path is not None else None
            uncertainty = read_drill_uncertainty(drill_path) if drill_path is not None else None
        except (OSError, ValueError, DrillnavError) as exc:
            raise StartupError(f"calibration: {exc}") from None
        self.camera_device = Webcam(device=device, width=s.camera.width, height=s.camera.height, fps=s.camera.fps, fourcc=s.camera.fourcc, exposure=s.camera.exposure)
        return marker_set, {"camera": camera, "axis_drill": axis, "axis_uncertainty": uncertainty}

    def _active_calibration(self, kind: str) -> Path | None:
        """An installed calibration in ``calibration.folder`` (what a calibration job installed), if any."""
        path = self.settings.calibration.folder / f"{kind}.json"
        return path if path.exists() else None

    def _start_calibration_jobs(self, stack: contextlib.ExitStack) -> None:
        from .calibration_jobs import CalibrationJobs

        s, cal = self.settings, self.settings.calibration.folder
        self.calibration_jobs = stack.enter_context(CalibrationJobs(
            work_dir=cal, grab_frame=self._grab_frame, on_install=self._install_calibration,
            active_camera_path=s.camera.calibration or cal / "camera.json", active_drill_path=s.camera.drill_calibration or cal / "drill.json",
            max_active=s.api.max_jobs_running, max_stored=s.api.max_jobs_stored, expiry_s=s.api.job_expiry_s))

    def _start_api(self, stack: contextlib.ExitStack, api_socket: socket.socket) -> None:
        """uvicorn on the socket bound at start; start-up counts as done only once it says ``started``."""
        import uvicorn

        from .api import create_app, uvicorn_ssl_kwargs

        app = create_app(state=self, settings=self.settings.api, audit=self.audit)
        server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off", **uvicorn_ssl_kwargs(self.settings.api)))
        server.install_signal_handlers = lambda: None  # signals belong to the CLI: uvicorn runs in a thread
        self._server = server
        thread = threading.Thread(target=server.run, kwargs={"sockets": [api_socket]}, name="api", daemon=True)

        def stop_api() -> None:
            server.should_exit = True
            thread.join(timeout=3)

        thread.start()
        stack.callback(stop_api)
        deadline = time.monotonic() + 10
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                raise StartupError(f"REST API did not start on {self.settings.api.host}:{self.settings.api.port}")
            time.sleep(0.01)

    def _ct_tracker(self):
        """The live video-CT mode: from ``[ct] volume`` (and ``plan``), or the twin's own CT; None when off."""
        s = self.settings
        if s.ct.volume is None and not (s.twin and s.twin_scene.ct_voxel_mm):
            return None
        from drillnav.drivers.ct_volume import read_ct

        from .ct_mode import load_plan, plan_entries
        from .ct_tracker import CtTracker

        self.progress("loading the CT ...")
        if s.ct.volume is not None:
            try:
                ct, plan = read_ct(s.ct.volume), (load_plan(s.ct.plan) if s.ct.plan else [])
            except (OSError, ValueError, DrillnavError) as exc:
                raise StartupError(f"ct: {exc}") from None
        else:
            from drillnav.drivers.sim import anatomy
            from drillnav.drivers.sim.ct_phantom import make_pelvis_ct
            from drillnav.schemas.scene_files import plan_to_json

            v = s.twin_scene.ct_voxel_mm
            ct = make_pelvis_ct(seed=s.twin_scene.seed, voxel_mm=(v, v, v))
            plan = plan_entries(plan_to_json(anatomy.CORRIDORS), base=Path.cwd())  # the twin's plan.json, as sim scene writes it
        at = np.asarray(s.ct.at_mm, dtype=np.float64) if s.ct.at_mm is not None else None
        tracker = CtTracker(ct=ct, plan=plan, at_isocentre_mm=at, on_event=self._event)
        self.progress("CT up")
        return tracker

    def _event(self, level: str, message: str) -> None:
        bus.put(self.session, self.prefix, "events", msg.Event(stamp_ns=time.time_ns(), level=level, message=message).to_bytes())

    def _spawn(self, target, name: str) -> None:
        t = threading.Thread(target=target, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def _join_threads(self) -> None:
        self._stop.set()
        deadline = time.monotonic() + 2.0  # daemon threads: the exit does not wait on a wedged device read
        for t in self._threads:
            t.join(timeout=max(0.0, deadline - time.monotonic()))

    def _close_recorders(self) -> None:
        for name in list(self._recorders):
            self.stop_recording(name)

    # -- loops -----------------------------------------------------------------------------
    @property
    def _camera_jpeg_quality(self) -> int:
        """The camera's JPEG on the bus: at the recording's quality (the recorder then keeps it as received), 92 when that is 0."""
        return self.settings.recording.camera_jpeg_quality or 92

    def _camera_loop(self) -> None:
        pub = bus.declare_publisher(self.session, self.prefix, "camera_image")

        def on_frame(frame) -> None:
            self._last_frame_ns = time.monotonic_ns()
            with self._frame_lock:
                self._latest_frame = (frame.stamp_ns, frame.image)
                self._frame_lock.notify_all()
            # The node takes the pixels as captured, then the JPEG goes on the bus (recorder, display) while it tracks
            # them: the encode and a decode are off the capture-to-axis path (~6 ms a frame on 2 cores).
            self.node.take_frame(frame.image, frame.stamp_ns)
            pub.put(msg.compressed_image(frame.image, stamp_ns=frame.stamp_ns, frame_id="drill_camera", fmt="jpeg", quality=self._camera_jpeg_quality))

        def on_event(level: str, message: str) -> None:
            if level == "error":
                self.errors.append(message)
            self._event(level, message)

        self.pump = CameraPump(device=self.camera_device, name=str(self.settings.camera.device) if not self.settings.twin else "twin",
                               on_frame=on_frame, on_event=on_event, stop=self._stop, retry_s=self.settings.camera.retry_s)
        self.pump.run()

    def _dicom_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._take_dicom(self.intake.wait(0.5))
            except Exception as exc:  # noqa: BLE001 - the intake survives what it did not foresee
                self.errors.append(f"DICOM intake: {type(exc).__name__}: {exc}")
                self._event("error", f"DICOM intake: unexpected {type(exc).__name__}: {exc}")

    def _intake_error(self, path: Path, message: str) -> None:
        """A file in the watched folder that cannot be used (not DICOM, unreadable): named in status and events."""
        self.errors.append(message)
        self._event("error", f"fluoroscopy refused: {message}")

    def _take_dicom(self, paths) -> None:
        for path in paths:
            try:
                images = read_fluoro(path)
            except DrillnavError as exc:
                self.errors.append(str(exc))
                self._event("error", f"fluoroscopy refused: {exc}")
                self.intake.failed(path, str(exc))
                self.intake.mark_processed(path)  # refused for good: not offered again after a restart
                continue
            for img in images:
                if not img.polarity_stated:
                    # The file does not say which way its values run: the reading that shows the markers travels on.
                    try:
                        settled = settle_polarity(img, self.node.marker_set)
                    except Exception as exc:  # noqa: BLE001 - one image the detector cannot read must not stop the intake
                        self.errors.append(f"{path}: {type(exc).__name__}: {exc}")
                        self._event("error", f"fluoroscopy refused: {path}: its polarity could not be settled ({type(exc).__name__}: {exc})")
                        continue
                    img = settled.image
                    self._event("warning", f"fluoroscopy {settled.note}")
                # A re-shot of the same view replaces the earlier shot of it in the node.
                name = img.view_name
                stamp = time.time_ns()
                try:
                    shot = msg.FluoroShot.build(img.pixels_log, img.view, stamp_ns=stamp, view_name=name, source_file=img.source_file)
                except ValueError as exc:
                    reason = " ".join(str(exc).split())  # pydantic's report spans lines
                    self.errors.append(f"{path}: {reason}")
                    self._event("error", f"fluoroscopy refused: {path}: {reason}")
                    continue
                # Every shot arrives (blocked, not dropped, when the link is busy): a lost one is a registration missed.
                bus.put(self.session, self.prefix, "fluoro_shot", shot.to_bytes())
                bus.put(self.session, self.prefix, "fluoro_image", msg.compressed_image(to_display(img.pixels_log), stamp_ns=stamp, frame_id=f"carm/{name}", fmt="png"), name)
            self.intake.mark_processed(path)  # published: not offered again after a restart

    # -- calibration jobs ------------------------------------------------------------------
    def _grab_frame(self, timeout_s: float = 2.0) -> tuple[int, Any]:
        """The next camera frame after the call (for live calibration captures)."""
        with self._frame_lock:
            before = self._latest_frame
            if not self._frame_lock.wait_for(lambda: self._latest_frame is not before, timeout=timeout_s):
                raise DrillnavError(f"no camera frame for {timeout_s:.0f} s: is the camera connected?" + (f" ({self.errors[-1]})" if self.errors else ""))
            assert self._latest_frame is not None
            return self._latest_frame

    def _install_calibration(self, kind: str, path) -> None:
        """A calibration installed through the API becomes the node's at once: one new bundle (camera, axis, locator)."""
        if kind == "camera":
            bundle = self.node.install_calibration(camera=read_camera_calibration(path))
        else:
            bundle = self.node.install_calibration(axis_drill=read_drill_calibration(path), axis_uncertainty=read_drill_uncertainty(path))
        self._event("info", f"{kind} calibration installed from {path}" + ("" if bundle is not None else "; still uncalibrated: the other calibration is missing"))
        if bundle is None:
            return
        self._publish_calibration()
        if self.scene_publisher is not None and kind == "camera":
            self.scene_publisher.set_camera(bundle.camera)
        if self.igtl is not None and kind != "camera":
            self.igtl.set_drill_axis(bundle.axis_drill)

    def _publish_calibration(self) -> None:
        """The calibrations in use on ``calibration/active`` (at start and after each install): recordings carry them."""
        from drillnav.schemas.calibration_message import active_calibration_message

        bundle = self.node.calibration
        if bundle is None:
            return
        s, cal = self.settings, self.settings.calibration.folder
        bus.put(self.session, self.prefix, "calibration", active_calibration_message(
            camera=bundle.camera, axis_drill=bundle.axis_drill, axis_uncertainty=bundle.axis_uncertainty, marker_set=self.node.marker_set, stamp_ns=time.time_ns(),
            camera_file=None if s.twin else s.camera.calibration or cal / "camera.json",
            drill_file=None if s.twin else s.camera.drill_calibration or cal / "drill.json"))

    def _publish_audit(self, entry: dict[str, Any]) -> None:
        bus.put(self.session, self.prefix, "audit", msg.AuditEntry(**entry).to_bytes())

    def _start_interop(self, stack: contextlib.ExitStack, *, axis_drill, camera) -> None:
        """What other tools connect to, each from its settings: Foxglove's scene topics and live WebSocket, OpenIGTLink (Slicer), ROS 2."""
        s = self.settings
        self.scene_publisher = self.igtl = None
        try:
            if s.foxglove.scene:
                from .scene_publisher import ScenePublisher

                self.scene_publisher = stack.enter_context(ScenePublisher(session=self.session, prefix=self.prefix, camera=camera))
            if s.foxglove.enabled:
                from .foxglove_bridge import FoxgloveBridge

                stack.enter_context(FoxgloveBridge(session=self.session, prefix=self.prefix, host=s.foxglove.host, port=s.foxglove.port))
                self.progress(f"Foxglove WebSocket up on ws://{s.foxglove.host}:{s.foxglove.port}")
            if s.igtl.enabled:
                from .igtl_server import IgtlServer

                tracker = self.node.ct_tracker
                self.igtl = stack.enter_context(IgtlServer(
                    session=self.session, prefix=self.prefix, axis_drill=axis_drill, host=s.igtl.host, port=s.igtl.port,
                    model_start_mm=s.igtl.model_start_mm, model_length_mm=s.igtl.model_length_mm, model_radius_mm=s.igtl.model_radius_mm,
                    ct_volume=tracker.ct if tracker is not None else None))
                self.progress(f"OpenIGTLink up on {s.igtl.host}:{s.igtl.port}")
            if s.ros2.enabled:
                from .ros2_bridge import Ros2Bridge

                stack.enter_context(Ros2Bridge(session=self.session, prefix=self.prefix, domain_id=s.ros2.domain_id, topic=s.ros2.topic, node=s.ros2.node))
                self.progress(f"ROS 2 stream up on {s.ros2.topic} (domain {s.ros2.domain_id})")
        except OSError as exc:
            raise StartupError(f"interop: cannot listen: {exc.strerror or exc}") from None

    # -- health ----------------------------------------------------------------------------
    def health(self) -> str | None:
        """None when every stream the daemon should produce flows; else the reason (one line). What ``/health`` says."""
        if not self.started:
            return "starting" if self._stack is None else "stopping"
        now = time.monotonic_ns()
        lost = self.pump.lost if self.pump is not None else None
        if lost is not None:  # the pump saw the device go: said at once, not a stall period later
            return f"camera stalled: {lost}"
        if now - self._last_frame_ns > int(self.stall_s * 1e9):
            why = f" ({self.errors[-1]})" if self.errors else ""
            return f"camera stalled: no frame for {(now - self._last_frame_ns) / 1e9:.1f} s{why}"
        return self.wedged()

    def wedged(self) -> str | None:
        """The faults a restart can mend (a dead or stuck thread, a recorder that stopped), else None; what the watchdog reflects.

        A camera that stops is not among them: the pump reopens it by itself, and a restart would only lose the registration.
        """
        reason = self.node.health()
        if reason is not None:
            return reason
        now = time.monotonic_ns()
        for t in self._threads:
            if not t.is_alive():
                return f"daemon thread '{t.name}' is dead"
        for name, rec in list(self._recorders.items()):
            seen, since = self._recorder_seen.get(name, (-1, now))
            if rec.messages != seen:
                self._recorder_seen[name] = (rec.messages, now)
            elif now - since > int(self.stall_s * 1e9):
                return f"recorder '{name}' stalled: nothing written for {(now - since) / 1e9:.1f} s"
        return None

    # -- ServiceState for the API ------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        st, hub = self.node.status().to_dict(), self.display_hub
        st.update({"twin": self.settings.twin, "recordings": list(self._recorders), "device_errors": self.errors[-5:],
                   "recorders": {n: dataclasses.asdict(r.status()) for n, r in list(self._recorders.items())},
                   "topics": {n: key(self.prefix, n, "<view>") if "*" in t.suffix else key(self.prefix, n) for n, t in TOPICS.items()},
                   # Malformed messages the display's subscribers refused (garbage on the camera key meets them, not the node).
                   "display_decode_errors": hub.decode_errors if hub else 0, "display_last_decode_error": hub.last_decode_error if hub else None})
        if self.settings.twin:  # the twin camera renders its loop as it streams: its memory grows until the loop is whole
            st["twin_camera_rendered"] = [self.camera_device.rendered_frames, len(self.camera_device.poses)]
        return st

    def registration(self) -> dict[str, Any] | None:
        axis, axis_ct = self.node.last_axis, self.node.last_axis_ct
        if axis is None:
            return None
        return {**axis.to_dict(), "axis_ct": axis_ct.to_dict()} if axis_ct is not None else axis.to_dict()

    def request_registration(self) -> None:
        self.node.request_registration()

    def start_recording(self, name: str) -> list[str]:
        if name in self._recorders:
            raise KeyError(f"recording '{name}' is already running")
        # The camera loop already encodes at the recording's quality: the recorder keeps its frames as received (one encode, not two).
        rec = Recorder.from_settings(self.settings.recording.model_copy(update={"camera_jpeg_quality": 0}), session=self.session, prefix=self.prefix,
                                     name=name, on_event=self._event, carried_state=self.carried)
        self._recorders[name] = rec
        return [str(p) for p in rec.files]

    def stop_recording(self, name: str) -> list[str]:
        if name not in self._recorders:
            raise KeyError(f"no running recording named '{name}'")
        files = [str(p) for p in self._recorders.pop(name).close()]
        self._recorder_seen.pop(name, None)
        self._finished[name] = files
        return files

    def recordings(self) -> dict[str, list[str]]:
        out = dict(self._finished)
        out.update({n: [str(p) for p in r.files] for n, r in self._recorders.items()})
        return out

    def shoot(self, view: str) -> str:
        if self.carm is None:
            raise RuntimeError("shots on request exist only on the digital twin; a real C-arm sends its images itself")
        return str(self.carm.shoot(view))


def _bind(what: str, host: str, port: int) -> socket.socket:
    """A listening TCP socket, or a :class:`StartupError` naming ``what`` and the address."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise StartupError(f"{what}: cannot resolve host '{host}' ({exc.strerror})") from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(128)
    except OSError as exc:
        sock.close()
        raise StartupError(f"{what}: cannot listen on {host}:{port}: {exc.strerror}") from None
    sock.set_inheritable(True)
    return sock
