"""The daemon: bus, camera, C-arm intake, registration node, recorder and REST API, stopped gracefully."""

from __future__ import annotations

import gc
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import uvicorn

from drillnav.drivers.fluoro_dicom import read_fluoro
from drillnav.drivers.folder_watch import FolderWatcher
from drillnav.registration.errors import DrillnavError
from drillnav.registration.markers import default_marker_set
from drillnav.registration.overlay import to_display
from drillnav.schemas import messages as msg
from drillnav.schemas.calibration import read_camera_calibration, read_drill_calibration
from drillnav.schemas.markers import read_marker_set
from drillnav.schemas.topics import TOPICS, key

from .api import create_app
from .bus import open_session
from .calibration_jobs import CalibrationJobs
from .camera_pump import CameraPump
from .display_hub import DisplayHub
from .node import RegistrationNode
from .recorder import Recorder
from .settings import Settings, SettingsError

__all__ = ["Daemon"]


class Daemon:
    """Owns every running part; ``start()`` then ``stop()`` (or ``run(stop_event)``)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.token = settings.api.token
        self.prefix = settings.zenoh.prefix
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._recorders: dict[str, Recorder] = {}
        self._finished: dict[str, list[str]] = {}
        self.errors: list[str] = []
        self.carm = None
        self.calibration_jobs: CalibrationJobs | None = None
        self._frame_lock = threading.Condition()
        self._latest_frame: tuple[int, Any] | None = None

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> None:
        s = self.settings
        self.session = open_session(mode=s.zenoh.mode, listen=s.zenoh.listen, connect=s.zenoh.connect, multicast_scouting=s.zenoh.multicast_scouting)
        s.dicom.watch_folder.mkdir(parents=True, exist_ok=True)
        if s.twin:
            from drillnav.drivers.sim.devices import TwinCArm, TwinDrillCamera
            from drillnav.drivers.sim.scene import make_scene

            scene = make_scene(seed=s.twin_scene.seed, n_markers=s.twin_scene.markers, views=s.twin_scene.views, render=False)
            marker_set, camera, axis = scene.marker_set, scene.calibrated_camera, scene.calibrated_axis_drill
            self.camera_device = TwinDrillCamera(scene=scene, fps=s.camera.fps, seed=s.twin_scene.seed)
            send_to = (s.dicom.scp_host, s.dicom.scp_port, s.dicom.ae_title) if s.dicom.scp_enabled else None
            self.carm = TwinCArm(scene=scene, folder=s.dicom.watch_folder / ".twin", seed=s.twin_scene.seed, send_to=send_to)
        else:
            from drillnav.drivers.webcam import Webcam

            if s.camera.calibration is None or s.camera.drill_calibration is None:
                raise SettingsError("camera.calibration and camera.drill_calibration must name camera.json and drill.json (run the calibrations first)")
            marker_set = read_marker_set(s.markers_file) if s.markers_file else default_marker_set()
            camera, axis = read_camera_calibration(s.camera.calibration), read_drill_calibration(s.camera.drill_calibration)
            self.camera_device = Webcam(device=s.camera.device, width=s.camera.width, height=s.camera.height, fps=s.camera.fps,
                                        fourcc=s.camera.fourcc, exposure=s.camera.exposure)
        ct_tracker = self._ct_tracker()
        self.node = RegistrationNode(session=self.session, prefix=self.prefix, marker_set=marker_set, camera=camera, axis_drill=axis, ct_tracker=ct_tracker)
        # -- display (service/display_hub.py): the browser's streams, from this session --
        self.display_hub = DisplayHub(session=self.session, prefix=self.prefix, plan=[e.trajectory for e in ct_tracker.plan] if ct_tracker else (),
                                      ct=ct_tracker.ct if ct_tracker else None).__enter__()
        # -- end display --
        cal = s.calibration.folder
        self.calibration_jobs = CalibrationJobs(
            work_dir=cal, grab_frame=self._grab_frame, on_install=self._install_calibration,
            active_camera_path=s.camera.calibration or cal / "camera.json", active_drill_path=s.camera.drill_calibration or cal / "drill.json")
        self.watcher = FolderWatcher(folder=s.dicom.watch_folder)
        self.scp = None
        if s.dicom.scp_enabled:
            from drillnav.drivers.dicom_scp import StoreScp

            # Received images land in the watched folder, fsynced before they are acknowledged.
            self.scp = StoreScp(ae_title=s.dicom.ae_title, port=s.dicom.scp_port, host=s.dicom.scp_host, storage_dir=s.dicom.watch_folder, allowed_calling_aes=s.dicom.allowed_calling_aes).__enter__()
        if s.recording.record_on_start:
            self.start_recording("session")
        self._spawn(self._camera_loop, "camera")
        self._spawn(self._dicom_loop, "dicom")
        self._server = uvicorn.Server(uvicorn.Config(create_app(state=self), host=s.api.host, port=s.api.port, log_level="warning"))
        self._spawn(self._server.run, "api")
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

    def _ct_tracker(self):
        """The live video-CT mode: from ``[ct] volume`` (and ``plan``), or the twin's own CT; None when off."""
        from drillnav.drivers.ct_volume import read_ct

        from .ct_mode import load_plan, plan_entries
        from .ct_tracker import CtTracker

        s = self.settings
        if s.ct.volume is not None:
            ct, plan = read_ct(s.ct.volume), (load_plan(s.ct.plan) if s.ct.plan else [])
        elif s.twin and s.twin_scene.ct_voxel_mm:
            from drillnav.drivers.sim import anatomy
            from drillnav.drivers.sim.ct_phantom import make_pelvis_ct
            from drillnav.schemas.scene_files import plan_to_json

            v = s.twin_scene.ct_voxel_mm
            ct = make_pelvis_ct(seed=s.twin_scene.seed, voxel_mm=(v, v, v))
            plan = plan_entries(plan_to_json(anatomy.CORRIDORS), base=Path.cwd())  # the twin's plan.json, as sim scene writes it
        else:
            return None
        at = np.asarray(s.ct.at_mm, dtype=np.float64) if s.ct.at_mm is not None else None
        return CtTracker(ct=ct, plan=plan, at_isocentre_mm=at, on_event=self._event)

    def _event(self, level: str, message: str) -> None:
        self.session.put(key(self.prefix, "events"), msg.encode_json({"stamp_ns": time.time_ns(), "level": level, "message": message}))

    def _spawn(self, target, name: str) -> None:
        t = threading.Thread(target=target, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        if hasattr(self, "_server"):
            self._server.should_exit = True
        for t in self._threads:
            t.join(timeout=5)
        if getattr(self, "scp", None) is not None:
            self.scp.__exit__(None, None, None)
        if self.calibration_jobs is not None:
            self.calibration_jobs.close()
        if hasattr(self, "node"):
            self.node.close()
        if hasattr(self, "display_hub"):
            self.display_hub.__exit__(None, None, None)
        for name in list(self._recorders):
            self.stop_recording(name)
        if hasattr(self, "session"):
            self.session.close()

    def run(self, stop_event: threading.Event) -> None:
        self.start()
        try:
            stop_event.wait()
        finally:
            self.stop()

    # -- loops -----------------------------------------------------------------------------
    def _camera_loop(self) -> None:
        pub = self.session.declare_publisher(key(self.prefix, "camera_image"))

        def on_frame(frame) -> None:
            with self._frame_lock:
                self._latest_frame = (frame.stamp_ns, frame.image)
                self._frame_lock.notify_all()
            pub.put(msg.compressed_image(frame.image, stamp_ns=frame.stamp_ns, frame_id="drill_camera", fmt="jpeg", quality=92))

        def on_event(level: str, message: str) -> None:
            if level == "error":
                self.errors.append(message)
            self._event(level, message)

        CameraPump(device=self.camera_device, name=str(self.settings.camera.device) if not self.settings.twin else "twin",
                   on_frame=on_frame, on_event=on_event, stop=self._stop, retry_s=self.settings.camera.retry_s).run()

    def _dicom_loop(self) -> None:
        while not self._stop.is_set():
            for path in self.watcher.wait(0.5):
                try:
                    images = read_fluoro(path)
                except DrillnavError as exc:
                    self.errors.append(str(exc))
                    self._event("error", f"fluoroscopy refused: {exc}")
                    continue
                for img in images:
                    # A re-shot of the same view replaces the earlier shot of it in the node.
                    name = img.view_name
                    stamp = time.time_ns()
                    self.session.put(key(self.prefix, "fluoro_shot"), msg.fluoro_shot(img.pixels_log, img.view, stamp_ns=stamp, view_name=name, source_file=img.source_file))
                    self.session.put(key(self.prefix, "fluoro_image", name), msg.compressed_image(to_display(img.pixels_log), stamp_ns=stamp, frame_id=f"carm/{name}", fmt="png"))

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
        """A calibration installed through the API becomes the node's at once."""
        if kind == "camera":
            self.node.camera = read_camera_calibration(path)
        else:
            self.node.axis_drill = read_drill_calibration(path)
        self._event("info", f"{kind} calibration installed from {path}")

    # -- ServiceState for the API ------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        st = self.node.status()
        st.update({"twin": self.settings.twin, "recordings": list(self._recorders), "device_errors": self.errors[-5:],
                   "topics": {n: key(self.prefix, n, "<view>") if "*" in t.suffix else key(self.prefix, n) for n, t in TOPICS.items()}})
        return st

    def registration(self) -> dict[str, Any] | None:
        if self.node.last_axis is None:
            return None
        return {**self.node.last_axis, "axis_ct": self.node.last_axis_ct} if self.node.last_axis_ct is not None else self.node.last_axis

    def request_registration(self) -> None:
        self.node.request_registration()

    def start_recording(self, name: str) -> list[str]:
        if name in self._recorders:
            raise KeyError(f"recording '{name}' is already running")
        rec = Recorder(session=self.session, prefix=self.prefix, folder=self.settings.recording.folder, name=name, rotate_bytes=self.settings.recording.rotate_mb * 1024 * 1024,
                       rotate_seconds=self.settings.recording.rotate_minutes * 60.0)
        self._recorders[name] = rec
        return [str(p) for p in rec.files]

    def stop_recording(self, name: str) -> list[str]:
        if name not in self._recorders:
            raise KeyError(f"no running recording named '{name}'")
        files = [str(p) for p in self._recorders.pop(name).close()]
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


