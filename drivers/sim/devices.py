"""The digital twin as devices: a drill camera moving freehand at 30 frames/s and a C-arm that shoots on request.

Rendering a frame through the true lens costs ~50 ms on one core, so the
camera pre-renders one loop of a smooth freehand path at start-up and then
serves it at the frame rate with capture stamps taken as each frame is served.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from drillnav.drivers.sim.dicom_io import write_xa
from drillnav.drivers.sim.scene import PAPER_CARM, Scene, render_fluoro
from drillnav.registration.transforms import make_transform
from drillnav.schemas.projection import write_projection

__all__ = ["CameraFrame", "TwinDrillCamera", "TwinCArm"]


@dataclass(frozen=True, kw_only=True)
class CameraFrame:
    image: NDArray[np.uint8]
    stamp_ns: int
    frame_id: int
    carm_from_drill: NDArray[np.float64] | None = None  # truth, twin only


class TwinDrillCamera:
    """Context manager yielding frames at ``fps`` along a looping freehand path towards the corridor."""

    def __init__(self, *, scene: Scene, fps: float = 30.0, loop_frames: int = 90, keyposes: int = 4, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        keys = [scene.drill_pose_towards(rng, offset_mm=4.0, tilt_deg=4.0) for _ in range(keyposes)]
        keys.append(keys[0])
        times = np.linspace(0, 1, len(keys))
        slerp = Slerp(times, Rotation.from_matrix([k[:3, :3] for k in keys]))
        t = np.linspace(0, 1, loop_frames, endpoint=False)
        trans = np.stack([np.interp(t, times, [k[i, 3] for k in keys]) for i in range(3)], axis=1)
        rots = slerp(t).as_matrix()
        self.poses = [make_transform(r, p) for r, p in zip(rots, trans)]
        self.frames = [scene.render_camera(rng, carm_from_drill=p) for p in self.poses]
        self.period_s = 1.0 / fps
        self._n = 0
        self._next = 0.0
        self._open = False

    def __enter__(self) -> "TwinDrillCamera":
        self._open = True
        self._next = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        self._open = False

    def read(self) -> CameraFrame:
        """Block until the next frame is due and return it, stamped now."""
        if not self._open:
            raise RuntimeError("the twin camera is not open")
        self._next += self.period_s
        delay = self._next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            self._next = time.monotonic()
        k = self._n % len(self.frames)
        self._n += 1
        return CameraFrame(image=self.frames[k], stamp_ns=time.time_ns(), frame_id=self._n, carm_from_drill=self.poses[k])


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
        write_xa(tmp, image, primary_deg=a, secondary_deg=b, source_to_detector_mm=PAPER_CARM["source_to_detector_mm"],
                 source_to_isocenter_mm=PAPER_CARM["source_to_isocenter_mm"], pixel_spacing_mm=PAPER_CARM["pixel_spacing_mm"],
                 study_uid="1.2.826.0.1.3680043.8.498.1", series_uid="1.2.826.0.1.3680043.8.498.2", instance_number=self._n)
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
