"""The display hub: the daemon's streams, fanned out to every browser showing the surgeon's display.

It subscribes (in the daemon's own zenoh session) to the axis in C and in the
CT, the fluoroscopy shots and their display images, the camera, the status,
the events and the marker registrations, and hands each WebSocket client the
newest message of each stream. A slow browser never builds a backlog: a
client holds one pending message per stream (the newest replaces the older,
as the node's frame queue does), except events, which are few and all kept.
Nothing is decoded to pixels here: the axis JSON is passed through as it
came, images travel as the JPEG/PNG bytes the daemon already made.

The CT (video-CT mode) goes to the browser once, as an 8-bit windowed volume
(:meth:`DisplayHub.ct_volume`), and is resliced there at camera rate: see
``docs/display.md`` for why.
"""

from __future__ import annotations

import asyncio
import base64
import json
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import zenoh
from numpy.typing import NDArray
from scipy import ndimage

from drillnav.registration.ct_views import PlannedTrajectory
from drillnav.registration.volume import Volume
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key

__all__ = ["DisplayHub", "DisplayClient", "CtVolumeForDisplay"]

MAX_VIEWS = 4
CT_MAX_VOXELS_PER_AXIS = 256   # the volume a browser reslices: <= 16 MB at 8 bits
CT_WINDOW_HU = (400.0, 1800.0)  # level, width: bone, as the CLI's CT views
RECENT_FRAMES = 30          # camera frames held (about 1 s) for the preview that waits for the node's tags
TAGS_WAIT_NS = 500_000_000  # no tags from the node for this long: previews go out without them (the node tracks nothing)
_AXIS_KEYS = ("point_mm", "direction", "predicted_error", "source_frame_stamp_ns")


@dataclass(frozen=True, kw_only=True)
class CtVolumeForDisplay:
    """An 8-bit windowed CT for the browser: ``data`` (k, j, i) C-order bytes; ``patient_from_voxel`` (4, 4), LPS mm."""

    data: bytes
    shape: tuple[int, int, int]
    patient_from_voxel: NDArray[np.float64]
    window_hu: tuple[float, float]

    def meta(self) -> dict[str, Any]:
        return {"shape": list(self.shape), "patient_from_voxel": self.patient_from_voxel.tolist(), "window_hu": list(self.window_hu)}


def ct_for_display(ct: Volume, *, max_voxels_per_axis: int = CT_MAX_VOXELS_PER_AXIS, window_hu: tuple[float, float] = CT_WINDOW_HU) -> CtVolumeForDisplay:
    """Window to 8 bits and stride down so no axis exceeds ``max_voxels_per_axis`` (a diagnostic CT is 512 x 512 x N)."""
    step = [max(1, int(np.ceil(n / max_voxels_per_axis))) for n in ct.shape]
    data = np.asarray(ct.data, dtype=np.float32)
    if any(s > 1 for s in step):
        # Averaging before striding keeps thin cortex visible instead of aliasing it away.
        data = ndimage.uniform_filter(data, size=step, mode="nearest")[:: step[0], :: step[1], :: step[2]]
    level, width = window_hu
    u8 = np.clip((data - (level - width / 2)) / width * 255.0, 0, 255).astype(np.uint8)
    # Voxel (i, j, k) of the strided volume is voxel (i*si, j*sj, k*sk) of the original (data is [k, j, i]).
    scale = np.diag([step[2], step[1], step[0], 1.0])
    return CtVolumeForDisplay(data=np.ascontiguousarray(u8).tobytes(), shape=tuple(int(n) for n in u8.shape),
                              patient_from_voxel=ct.patient_from_voxel @ scale, window_hu=(float(level), float(width)))


@dataclass(eq=False)
class DisplayClient:
    """One browser: the newest pending message per stream, woken on its own event loop."""

    loop: asyncio.AbstractEventLoop
    pending: dict[str, str] = field(default_factory=dict)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    dropped: int = 0

    def offer(self, stream: str, text: str) -> None:
        """On the client's loop only (the hub calls it through ``call_soon_threadsafe``)."""
        if stream in self.pending:
            self.dropped += 1
        self.pending[stream] = text
        self.wake.set()

    async def next_batch(self) -> list[str]:
        await self.wake.wait()
        self.wake.clear()
        batch, self.pending = list(self.pending.values()), {}
        return batch


PREVIEW_QUALITY = 85


def preview_jpeg(data: bytes) -> bytes:
    """A camera frame (JPEG or PNG) as the page's preview: a quarter of its width, JPEG.

    The page shows the preview 320 px wide; the full frame (1280x720, ~200 kB, ~270 kB as base64 in JSON) cost the
    browser's main thread a JSON parse and a base64 decode five times a second, on the thread that draws the axis.
    The JPEG decoder scales by 4 in its DCT (``IMREAD_REDUCED_COLOR_4``): about a millisecond, not a full decode.
    """
    small = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_COLOR_4)
    if small is None or small.size == 0:
        raise ValueError("camera frame: no decodable image data for the preview")
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, PREVIEW_QUALITY])
    if not ok:
        raise ValueError("camera frame: the preview could not be encoded")
    return buf.tobytes()


class DisplayHub:
    """Context manager: subscribes on ``__enter__``, undeclares on ``__exit__``.

    ``plan`` is the planned trajectories in the CT frame (drawn on the
    fluoroscopy views through ``carm_from_ct`` once the CT is registered, and
    in the CT views); ``ct`` the preoperative CT (video-CT mode) or None.
    """

    def __init__(self, *, session: zenoh.Session, prefix: str, plan: Sequence[PlannedTrajectory] = (), ct: Volume | None = None,
                 camera_preview_hz: float = 5.0) -> None:
        if camera_preview_hz <= 0:
            raise ValueError(f"camera_preview_hz must be positive, got {camera_preview_hz}")
        self.session, self.prefix = session, prefix
        self.plan = tuple(plan)
        self.ct = ct
        self.camera_period_ns = int(1e9 / camera_preview_hz)
        self._lock = threading.Lock()
        self._clients: set[DisplayClient] = set()
        self._latest: dict[str, str] = {}            # stream -> newest message, for a browser that connects later
        self._shots: dict[str, dict[str, Any]] = {}  # view -> {stamp_ns, projection} from fluoro/shot
        self._images: dict[str, tuple[int, bytes]] = {}  # view -> (stamp_ns, PNG) from fluoro/<view>/image
        self._events: deque[str] = deque(maxlen=20)
        self._event_n = 0
        self._last_camera_ns = 0
        self._recent_frames: dict[int, tuple[str, bytes]] = {}  # capture stamp -> (format, the camera frame), the last RECENT_FRAMES: a preview waits for its tags
        self._last_tags_ns = 0  # monotonic: when the node last sent tags (0: never)
        self._ct_display: CtVolumeForDisplay | None = None
        self._subs: list[Any] = []
        self.decode_errors = 0
        self.last_decode_error: str | None = None

    # -- lifecycle --------------------------------------------------------------------------
    def __enter__(self) -> "DisplayHub":
        k = lambda name, view=None: key(self.prefix, name, view)  # noqa: E731
        handlers = [(k("axis_carm"), self._on_axis), (k("axis_ct"), self._on_axis_ct), (k("fluoro_shot"), self._on_shot),
                    (k("fluoro_image", "*"), self._on_view_image), (k("camera_image"), self._on_camera), (k("status"), self._on_status),
                    (k("events"), self._on_event), (k("fluoro_markers"), self._on_markers),
                    (k("camera_markers"), self._on_camera_tags)]
        for key_expr, handler in handlers:
            self._subs.append(self.session.declare_subscriber(key_expr, self._guarded(handler)))
        return self

    def __exit__(self, *exc: object) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs.clear()

    def _guarded(self, handler):
        """A malformed message is counted and reported, and the subscriber goes on (a boundary validates, a worker survives)."""

        def run(sample: zenoh.Sample) -> None:
            try:
                handler(sample)
            except (ValueError, KeyError, TypeError) as exc:  # json's and UTF-8's decode errors are ValueErrors
                self.decode_errors += 1
                self.last_decode_error = f"{sample.key_expr}: {exc}"

        return run

    # -- clients ----------------------------------------------------------------------------
    def attach(self) -> DisplayClient:
        """A new client on the running event loop, primed with the newest message of every stream."""
        client = DisplayClient(loop=asyncio.get_running_loop())
        with self._lock:
            self._clients.add(client)
            client.offer("hello", self.hello())
            for stream, text in self._latest.items():
                client.offer(stream, text)
            for text in self._events:
                self._event_n += 1
                client.offer(f"event:{self._event_n}", text)
        return client

    def detach(self, client: DisplayClient) -> None:
        with self._lock:
            self._clients.discard(client)

    @property
    def clients(self) -> int:
        return len(self._clients)

    def hello(self) -> str:
        return json.dumps({"type": "hello", "server_ns": time.time_ns(), "prefix": self.prefix, "ct": self.ct is not None,
                           "plan": [{"name": t.name, "entry_mm": np.asarray(t.entry_mm, float).tolist(), "target_mm": np.asarray(t.target_mm, float).tolist(),
                                     "radius_mm": float(t.radius_mm)} for t in self.plan]})

    def _send(self, stream: str, text: str, *, keep: bool = True) -> None:
        with self._lock:
            if keep:
                self._latest[stream] = text
            clients = list(self._clients)
        for c in clients:
            try:
                c.loop.call_soon_threadsafe(c.offer, stream, text)
            except RuntimeError:  # its loop closed under us: the route detaches it
                pass

    # -- streams ----------------------------------------------------------------------------
    @staticmethod
    def _raw_json(sample: zenoh.Sample, *required: str) -> str:
        """The message's JSON text, checked to be an object with ``required`` keys (the browser gets only what parses)."""
        text = sample.payload.to_bytes().decode()
        doc = json.loads(text)
        if not isinstance(doc, dict):
            raise ValueError("expected a JSON object")
        missing = [k for k in required if k not in doc]
        if missing:
            raise ValueError(f"missing {', '.join(missing)}")
        return text

    def _on_axis(self, sample: zenoh.Sample) -> None:
        # Passed through undecoded: the browser parses it anyway, and this runs at camera rate.
        self._send("axis", f'{{"type":"axis","recv_ns":{time.time_ns()},"data":{self._raw_json(sample, *_AXIS_KEYS)}}}')

    def _on_axis_ct(self, sample: zenoh.Sample) -> None:
        self._send("axis_ct", f'{{"type":"axis_ct","recv_ns":{time.time_ns()},"data":{self._raw_json(sample, *_AXIS_KEYS)}}}')

    def _on_status(self, sample: zenoh.Sample) -> None:
        self._send("status", f'{{"type":"status","server_ns":{time.time_ns()},"data":{self._raw_json(sample)}}}')

    def _on_markers(self, sample: zenoh.Sample) -> None:
        self._send("markers", f'{{"type":"markers","data":{self._raw_json(sample)}}}')

    def _on_event(self, sample: zenoh.Sample) -> None:
        text = f'{{"type":"event","data":{self._raw_json(sample)}}}'
        with self._lock:
            self._events.append(text)
            self._event_n += 1
            n = self._event_n
        self._send(f"event:{n}", text, keep=False)

    def _on_camera(self, sample: zenoh.Sample) -> None:
        img = msg.parse_compressed_image(sample.payload.to_bytes())  # ValueError for garbage: counted by _guarded
        stamp = img.timestamp.seconds * 1_000_000_000 + img.timestamp.nanos
        now = time.monotonic_ns()
        with self._lock:
            self._recent_frames[stamp] = (img.format, img.data)
            while len(self._recent_frames) > RECENT_FRAMES:
                del self._recent_frames[next(iter(self._recent_frames))]
            # While the node tracks, a preview goes out with its tags (_on_camera_tags); without tags, the frame alone.
            tracking = self._last_tags_ns and now - self._last_tags_ns < TAGS_WAIT_NS
            if tracking or now - self._last_camera_ns < self.camera_period_ns:
                return
            self._last_camera_ns = now
        self._send_preview(stamp, img.format, img.data, None)

    def _on_camera_tags(self, sample: zenoh.Sample) -> None:
        # A preview is the frame the tags were found in, sent with them: outlines that never belong to another frame,
        # at the node's pace (a frame the node dropped has no tags and is never a preview while it tracks).
        text = self._raw_json(sample, "stamp_ns", "image_size", "markers")
        stamp = json.loads(text)["stamp_ns"]
        now = time.monotonic_ns()
        with self._lock:
            self._last_tags_ns = now
            frame = self._recent_frames.get(stamp)
            if frame is None or now - self._last_camera_ns < self.camera_period_ns:
                return  # a preview a few times a second, not every tracked frame
            self._last_camera_ns = now
        self._send_preview(stamp, frame[0], frame[1], text)

    def _send_preview(self, stamp: int, fmt: str, data: bytes, tags_json: str | None) -> None:
        small = preview_jpeg(data)
        self._send("camera", f'{{"type":"camera","stamp_ns":{stamp},"format":"jpeg","data_base64":"{base64.b64encode(small).decode()}",'
                             f'"tags":{tags_json or "null"}}}')

    def _on_shot(self, sample: zenoh.Sample) -> None:
        doc = json.loads(sample.payload.to_bytes())
        view = str(doc["view"])
        with self._lock:
            self._shots[view] = {"stamp_ns": int(doc["stamp_ns"]), "projection": doc["projection"]}
        self._maybe_view(view)

    def _on_view_image(self, sample: zenoh.Sample) -> None:
        view = str(sample.key_expr).split("/")[-2]
        img = msg.parse_compressed_image(sample.payload.to_bytes())
        stamp = img.timestamp.seconds * 1_000_000_000 + img.timestamp.nanos
        with self._lock:
            self._images[view] = (stamp, bytes(img.data))
        self._maybe_view(view)

    def _maybe_view(self, view: str) -> None:
        """A view goes out once its projection (fluoro/shot) and its display image of the same stamp have both arrived."""
        with self._lock:
            shot, image = self._shots.get(view), self._images.get(view)
            if shot is None or image is None or image[0] != shot["stamp_ns"]:
                return
            # Up to MAX_VIEWS views, the most recently shot; an older view leaves the display.
            newest = sorted(self._shots, key=lambda v: self._shots[v]["stamp_ns"], reverse=True)[:MAX_VIEWS]
            for old in [v for v in self._shots if v not in newest]:
                self._shots.pop(old, None)
                self._images.pop(old, None)
                self._latest.pop(f"view:{old}", None)
            names = sorted(newest)
        text = json.dumps({"type": "view", "name": view, "stamp_ns": shot["stamp_ns"], "projection": shot["projection"],
                           "png_base64": base64.b64encode(image[1]).decode(), "views": names})
        self._send(f"view:{view}", text)

    # -- CT ---------------------------------------------------------------------------------
    def ct_volume(self) -> CtVolumeForDisplay | None:
        """The browser's CT, built on first request (seconds for a full CT; the twin's in ~50 ms)."""
        if self.ct is None:
            return None
        with self._lock:
            if self._ct_display is None:
                self._ct_display = ct_for_display(self.ct)
            return self._ct_display
