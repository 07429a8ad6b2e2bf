"""The digital twin as devices: a drill camera moving freehand at 30 frames/s and a C-arm that shoots on request.

Rendering a frame through the true lens costs ~0.3-0.6 s of CPU (the ray
undistortion of every marker's footprint), so the camera renders one loop of a
smooth freehand path as it streams: a render thread, started when the camera is
opened, renders the loop's frames in order (so each frame's content, noise
included, is what rendering the loop up front gave) and keeps them; ``read``
serves them at the frame rate, stamped as each is served. Until the whole loop
is rendered, a frame whose successor is not rendered yet is served again (the
drill seems to pause between renders), so the stream runs at the frame rate
from its first frame; from the second pass on, every frame is a new pose.
"""

from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from drillnav.drivers.sim import anatomy
from drillnav.drivers.sim.dicom_io import write_xa
from drillnav.drivers.sim.scene import Scene, render_fluoro
from drillnav.drivers.webcam import CameraUnavailable
from drillnav.registration.transforms import make_transform
from drillnav.schemas.projection import write_projection

__all__ = ["CameraFrame", "TwinDrillCamera", "TwinCArm", "freehand_loop"]


RENDER_NICE = 10  # the camera's render thread's nice value (Linux)


@dataclass(frozen=True, kw_only=True)
class CameraFrame:
    image: NDArray[np.uint8]
    stamp_ns: int
    frame_id: int
    carm_from_drill: NDArray[np.float64] | None = None  # truth, twin only


def freehand_loop(scene: Scene, rng: np.random.Generator, *, loop_frames: int, keyposes: int, aim_off_mm: float = 0.0) -> list[NDArray[np.float64]]:
    """``loop_frames`` poses ``carm_from_drill`` (4, 4) along a closed path through ``keyposes`` random drill poses
    aimed at the corridor (translation interpolated linearly, rotation by slerp); draws the key poses from ``rng``.

    ``aim_off_mm``: every pose moved this far sideways, square to the corridor (a surgeon aiming off the plan: the
    video-CT verdict is then a breach); 0 draws exactly the poses it drew before the option existed.
    """
    keys = [scene.drill_pose_towards(rng, offset_mm=4.0, tilt_deg=4.0) for _ in range(keyposes)]
    if aim_off_mm:
        along = scene.carm_from_ct[:3, :3] @ anatomy.corridor_direction(scene.corridor)
        side = np.cross(along, [0.0, 0.0, 1.0] if abs(along[2]) < 0.9 else [1.0, 0.0, 0.0])
        shift = aim_off_mm * side / np.linalg.norm(side)
        keys = [make_transform(k[:3, :3], k[:3, 3] + shift) for k in keys]
    keys.append(keys[0])
    times = np.linspace(0, 1, len(keys))
    slerp = Slerp(times, Rotation.from_matrix([k[:3, :3] for k in keys]))
    t = np.linspace(0, 1, loop_frames, endpoint=False)
    trans = np.stack([np.interp(t, times, [k[i, 3] for k in keys]) for i in range(3)], axis=1)
    return [make_transform(r, p) for r, p in zip(slerp(t).as_matrix(), trans)]


class TwinDrillCamera:
    """Context manager yielding frames at ``fps`` along a looping freehand path towards the corridor.

    ``loop_frames`` poses along a closed path through ``keyposes`` random drill
    poses; frame ``k`` of the loop is rendered once, by the camera's own render
    thread, and served again on every later pass.

    ``unplug_every_s``: the cable is pulled ``unplug_every_s`` after the camera
    was first opened and every ``unplug_every_s`` after that, for ``unplug_s``
    each time (None: only ``unplug()`` pulls it).
    """

    def __init__(self, *, scene: Scene, fps: float = 30.0, loop_frames: int = 90, keyposes: int = 4, seed: int = 0,
                 unplug_every_s: float | None = None, unplug_s: float = 3.0, aim_off_mm: float = 0.0) -> None:
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        if loop_frames < 1:
            raise ValueError(f"loop_frames must be >= 1, got {loop_frames}")
        if unplug_every_s is not None and not 0 < unplug_s < unplug_every_s:
            raise ValueError(f"unplug_s must be positive and shorter than unplug_every_s ({unplug_every_s}), got {unplug_s}")
        self.unplug_every_s, self.unplug_s = unplug_every_s, unplug_s
        self._first_open = None  # monotonic s of the first open: the schedule's origin
        self._pulled = False  # unplug() without plug()
        rng = np.random.default_rng(seed)
        self.poses = freehand_loop(scene, rng, loop_frames=loop_frames, keyposes=keyposes, aim_off_mm=aim_off_mm)
        self.period_s = 1.0 / fps
        self._scene = scene
        # The same generator, drawn in loop order after the key poses, as when the loop was rendered up front.
        self._render_rng = rng
        self._frames: list[NDArray[np.uint8]] = []
        self._rendered = threading.Condition()
        self._render_error: BaseException | None = None
        self._render_stop = threading.Event()
        self._render_thread: threading.Thread | None = None
        self._n = 0
        self._k = -1  # the loop frame served last
        self._next = 0.0
        self._open = False

    @property
    def rendered_frames(self) -> int:
        """Frames of the loop rendered so far (``len(poses)`` once the loop is complete)."""
        with self._rendered:
            return len(self._frames)

    def unplug(self) -> None:
        """Pull the cable: the next ``read`` raises :class:`CameraUnavailable`, and so does opening, until ``plug()``."""
        self._pulled = True

    def plug(self) -> None:
        self._pulled = False

    @property
    def plugged(self) -> bool:
        """False while pulled by ``unplug()`` or inside a scheduled unplug window."""
        if self._pulled:
            return False
        if self.unplug_every_s is None or self._first_open is None:
            return True
        t = time.monotonic() - self._first_open
        k = math.floor(t / self.unplug_every_s)
        return k < 1 or t - k * self.unplug_every_s >= self.unplug_s

    def __enter__(self) -> "TwinDrillCamera":
        if not self.plugged:
            # What cv2.VideoCapture on a missing /dev/videoN comes to in the webcam driver.
            raise CameraUnavailable("camera twin cannot be opened (unplugged)")
        if self._first_open is None:
            self._first_open = time.monotonic()
        self._open = True
        self._next = time.monotonic()
        if len(self._frames) < len(self.poses) and self._render_error is None:
            self._render_stop.clear()
            thread = threading.Thread(target=self._render_loop, name="twin-camera-render", daemon=True)
            thread.start()  # before it is kept: __exit__ (on another thread, at shutdown) must never join an unstarted one
            self._render_thread = thread
        return self

    def __exit__(self, *exc) -> None:
        self._open = False
        self._render_stop.set()
        with self._rendered:
            self._rendered.notify_all()
        if self._render_thread is not None:
            # A render in progress finishes (its frame is kept); the next open resumes after it.
            self._render_thread.join()
            self._render_thread = None

    def _render_loop(self) -> None:
        try:
            # The twin's rendering is scaffolding: the product's own work (the node, the CT worker at nice 10) goes first.
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), RENDER_NICE)  # Linux: this thread alone
        except (AttributeError, OSError):
            pass  # no per-thread nice here: it renders on equal terms
        try:
            while not self._render_stop.is_set() and len(self._frames) < len(self.poses):
                image = self._scene.render_camera(self._render_rng, carm_from_drill=self.poses[len(self._frames)])
                with self._rendered:
                    self._frames.append(image)
                    self._rendered.notify_all()
        except BaseException as exc:  # a reader must not wait for a frame that will never come
            with self._rendered:
                self._render_error = exc
                self._rendered.notify_all()

    def read(self) -> CameraFrame:
        """Block until the next frame is due and return it, stamped now: the loop's next frame once it is rendered,
        the one served last again until then (the very first read waits for the first render)."""
        if not self._open:
            raise RuntimeError("the twin camera is not open")
        self._check_plugged()
        with self._rendered:
            self._rendered.wait_for(lambda: self._frames or self._render_error is not None or not self._open)
            if self._render_error is not None:
                raise CameraUnavailable(f"the twin camera stopped rendering: {type(self._render_error).__name__}: {self._render_error}")
            if not self._open:
                raise RuntimeError("the twin camera was closed while a frame was awaited")
        self._next += self.period_s
        delay = self._next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            self._next = time.monotonic()
        self._check_plugged()  # pulled while the frame was awaited: no frame, as from a real camera
        with self._rendered:  # chosen when due, so a frame rendered meanwhile is served at once
            following = (self._k + 1) % len(self.poses)
            if following < len(self._frames):
                self._k = following
            k = self._k
            image = self._frames[k]
        self._n += 1
        return CameraFrame(image=image, stamp_ns=time.time_ns(), frame_id=self._n, carm_from_drill=self.poses[k])


    def _check_plugged(self) -> None:
        if not self.plugged:
            raise CameraUnavailable("camera twin stopped delivering frames (unplugged)")


class TwinCArm:
    """Takes a shot of a named view and writes it as XA DICOM (+ projection JSON) into ``folder``."""

    def __init__(self, *, scene: Scene, folder: Path, seed: int = 0, send_to: tuple[str, int, str] | None = None) -> None:
        """``send_to`` = (host, port, called AE): send each shot by DICOM C-STORE instead of dropping it in ``folder``."""
        self.scene, self.folder, self.send_to = scene, Path(folder), send_to
        self.folder.mkdir(parents=True, exist_ok=True)
        self._rng = np.random.default_rng([seed, 7])
        self._n = 0

    def shoot(self, view_name: str) -> Path:
        if view_name not in self.scene.views:
            raise ValueError(f"unknown view '{view_name}': the twin C-arm has {', '.join(self.scene.views)}")
        self._n += 1
        image = render_fluoro(self.scene, view_name, self._rng)
        a, b = self.scene.view_angles[view_name]
        tmp = self.folder / f".{view_name}-{self._n}.dcm.part"
        carm = self.scene.carm
        write_xa(tmp, image, primary_deg=a, secondary_deg=b, source_to_detector_mm=carm["source_to_detector_mm"],
                 source_to_isocenter_mm=carm["source_to_isocenter_mm"], pixel_spacing_mm=carm["pixel_spacing_mm"],
                 study_uid="1.2.826.0.1.3680043.8.498.1", series_uid="1.2.826.0.1.3680043.8.498.2", instance_number=self._n,
                 image_intensifier=self.scene.degradations.ii_distortion)
        final = self.folder / f"{view_name}-{self._n:04d}.dcm"
        if self.send_to is not None:
            from drillnav.drivers.dicom_scp import send_files

            host, port, called = self.send_to
            try:
                statuses = send_files(host=host, port=port, called_ae=called, paths=[tmp], calling_ae="TWIN-CARM")
            finally:
                tmp.unlink()
            if statuses != [0]:
                raise RuntimeError(f"the C-STORE of shot '{view_name}' failed with status {statuses}")
            return final
        write_projection(final.with_suffix(".json"), self.scene.views[view_name])
        tmp.rename(final)  # appears whole, never half-written
        return final
