"""USB webcam through V4L2/OpenCV: frames stamped at capture, typed errors, reconnection after unplug."""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from drillnav.registration.errors import DrillnavError

__all__ = ["CameraUnavailable", "Webcam", "WebcamFrame"]


class CameraUnavailable(DrillnavError):
    """The camera cannot be opened or stopped delivering frames; names the device."""


@dataclass(frozen=True, kw_only=True)
class WebcamFrame:
    image: NDArray[np.uint8]
    stamp_ns: int
    frame_id: int


class Webcam:
    """``with Webcam(device="/dev/video0", width=1280, height=720, fps=30, fourcc="MJPG") as cam: cam.read()``."""

    def __init__(self, *, device: str | int = "/dev/video0", width: int = 1280, height: int = 720, fps: float = 30.0, fourcc: str = "MJPG", exposure: float | None = None, reconnect_attempts: int = 3, reconnect_interval_s: float = 0.5) -> None:
        if fourcc not in ("MJPG", "YUYV"):
            raise ValueError(f"fourcc must be MJPG or YUYV, got {fourcc}")
        self.device, self.width, self.height, self.fps, self.fourcc, self.exposure = device, width, height, fps, fourcc, exposure
        self.reconnect_attempts, self.reconnect_interval_s = reconnect_attempts, reconnect_interval_s
        self._cap: cv2.VideoCapture | None = None
        self._n = 0

    def _open(self) -> None:
        dev = int(self.device) if isinstance(self.device, str) and self.device.isdigit() else self.device
        backend = cv2.CAP_V4L2 if isinstance(dev, int) or str(dev).startswith("/dev/") else cv2.CAP_ANY
        cap = cv2.VideoCapture(dev, backend)
        if not cap.isOpened():
            cap.release()
            raise CameraUnavailable(f"camera {self.device} cannot be opened (unplugged, busy, or no permission)")
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*self.fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        cap.set(cv2.CAP_PROP_FPS, self.fps)
        if self.exposure is not None:
            cap.set(cv2.CAP_PROP_EXPOSURE, self.exposure)
        self._cap = cap

    def __enter__(self) -> "Webcam":
        self._open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def read(self) -> WebcamFrame:
        """Next frame; after a failed read, reconnects up to ``reconnect_attempts`` times, then raises."""
        for attempt in range(self.reconnect_attempts + 1):
            if self._cap is not None:
                ok, image = self._cap.read()
                stamp = time.time_ns()
                if ok and image is not None:
                    self._n += 1
                    return WebcamFrame(image=image, stamp_ns=stamp, frame_id=self._n)
            self.close()
            if attempt < self.reconnect_attempts:
                time.sleep(self.reconnect_interval_s)
                try:
                    self._open()
                except CameraUnavailable:
                    continue
        raise CameraUnavailable(f"camera {self.device} stopped delivering frames (unplugged?) and did not come back after {self.reconnect_attempts} attempts")
