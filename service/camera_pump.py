"""The camera loop: frames from a camera device onto the bus, through unplug and re-plug.

A camera that cannot be opened, or stops delivering frames past its own
reconnection attempts, is reported once (an error event and ``errors``) and
then reopened every ``retry_s`` until it is back, which is reported too. The
loop never ends on a device error, so re-plugging the camera, however late,
brings the stream back without restarting the daemon.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol

from drillnav.registration.errors import DrillnavError

__all__ = ["CameraPump", "CameraDevice"]


class CameraDevice(Protocol):
    """What the pump needs of a camera (the webcam driver and the twin's camera)."""

    def __enter__(self) -> Any: ...

    def __exit__(self, *exc: object) -> None: ...


class CameraPump:
    """Runs ``on_frame(frame)`` for every frame of ``device`` until ``stop`` is set; ``on_event(level, message)`` for losses."""

    def __init__(self, *, device: CameraDevice, name: str, on_frame: Callable[[Any], None], on_event: Callable[[str, str], None],
                 stop: threading.Event, retry_s: float = 1.0) -> None:
        if retry_s <= 0:
            raise ValueError("retry_s must be positive")
        self.device, self.name, self.on_frame, self.on_event = device, name, on_frame, on_event
        self.stop, self.retry_s = stop, retry_s
        self.errors: list[str] = []
        self.connected = False
        self.losses = 0
        self.lost: str | None = None  # while the camera is lost: why (what /health says at once, not after a stall)

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                with self.device as cam:
                    self.connected = True
                    if self.lost is not None:
                        self.lost = None
                        self.on_event("info", f"camera {self.name} is back")
                    while not self.stop.is_set():
                        try:
                            frame = cam.read()
                        except DrillnavError as exc:
                            self._lose(exc)  # said before the device is closed: closing it can take a while
                            raise
                        self.on_frame(frame)
            except DrillnavError as exc:
                self._lose(exc)
                self.stop.wait(self.retry_s)

    def _lose(self, exc: DrillnavError) -> None:
        """Report a loss once (not once per failed reopen)."""
        self.connected = False
        if self.lost is None:
            self.losses += 1
            self.lost = f"{exc}; retrying every {self.retry_s:g} s"
            self.errors.append(self.lost)
            self.on_event("error", self.lost)
