"""OpenIGTLink server: 3D Slicer's OpenIGTLinkIF connects to drillnav as to a PlusServer.

It subscribes to the node's zenoh outputs and sends, to every connected client:

- ``TRANSFORM DrillToCArm`` for each drill axis (camera rate), stamped with the camera frame's capture stamp;
- in video-CT mode ``TRANSFORM DrillToCT`` and ``CTToCArm`` for each axis in V;
- ``IMAGE Fluoro-<view>`` for each new fluoroscopy shot, on its detector plane;
- ``STRING RegistrationState`` (from each status message) and ``STRING Alert`` (warning and error events);
- ``POLYDATA DrillModel`` once per connection: a cylinder along the calibrated drill axis in D;
- ``IMAGE CT`` once per connection when a CT is given (video-CT mode), in RAS.

Transforms are in Slicer's RAS world (see :mod:`drillnav.schemas.igtl`). The
protocol bytes are pyigtl's; the server is our own because pyigtl's
``OpenIGTLinkServer`` installs process-wide SIGTERM/SIGINT handlers in its
constructor (which fails off the main thread and would take over the daemon's),
serves one client at a time and queues every message for a slow client.
Here each client has a newest-per-device queue: a slow client gets the latest
pose, never a backlog. The model, the last image per view, the state and the
last ``CTToCArm`` are latched and sent to a client as it connects, so a Slicer
that reconnects has the whole scene again.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pyigtl
import zenoh

from drillnav.registration.line import Line3D
from drillnav.registration.transforms import invert
from drillnav.registration.volume import Volume
from drillnav.schemas import igtl
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key

__all__ = ["IgtlServer", "IgtlCounters"]

_KEEP_DRILL_POSES = 16  # carm_from_drill by capture stamp, to pair with the CT axis of the same frame


@dataclass
class IgtlCounters:
    clients_connected: int = 0
    messages_sent: int = 0
    transforms_sent: int = 0
    images_sent: int = 0
    decode_errors: int = 0
    send_errors: int = 0


class _Client:
    """One connection: a newest-per-device outbox drained by a sender thread; a reader drains what Slicer sends."""

    def __init__(self, sock: socket.socket, address, on_close: Callable[["_Client"], None]) -> None:
        self.sock, self.address, self._on_close = sock, address, on_close
        self._outbox: OrderedDict[str, bytes] = OrderedDict()
        self._cond = threading.Condition()
        self._closed = False
        self._threads = [threading.Thread(target=self._send_loop, name=f"igtl-send-{address[1]}", daemon=True),
                         threading.Thread(target=self._read_loop, name=f"igtl-read-{address[1]}", daemon=True)]

    def start(self) -> None:
        for t in self._threads:
            t.start()

    def offer(self, device: str, data: bytes) -> None:
        with self._cond:
            self._outbox.pop(device, None)  # a newer message replaces an unsent one and goes to the back
            self._outbox[device] = data
            self._cond.notify()

    def _send_loop(self) -> None:
        while True:
            with self._cond:
                while not self._outbox and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                _, data = self._outbox.popitem(last=False)
            try:
                self.sock.sendall(data)
            except OSError:
                self.close()
                return

    def _read_loop(self) -> None:
        # Slicer sends its own messages (status, GET_ queries); drillnav does not act on them, but must read
        # them so the socket never fills, and an empty read is how a disconnect shows.
        while True:
            try:
                if not self.sock.recv(65536):
                    break
            except OSError:
                break
        self.close()

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        self._on_close(self)


class IgtlServer:
    """Serves OpenIGTLink on ``host:port``; a context manager (listening and subscriptions start in ``__enter__``).

    Parameters
    ----------
    session, prefix : the zenoh session and key prefix of the node's outputs.
    axis_drill : the calibrated drill axis in D (mm), for the drill model.
    model_start_mm, model_length_mm, model_radius_mm : the cylinder along that axis (from its point).
    ct_volume : the preoperative CT (video-CT mode), sent once to each client as it connects.
    """

    def __init__(self, *, session: zenoh.Session, prefix: str, axis_drill: Line3D | None, host: str = "127.0.0.1", port: int = 18944,
                 model_start_mm: float = 60.0, model_length_mm: float = 200.0, model_radius_mm: float = 1.5, ct_volume: Volume | None = None) -> None:
        if not 0 < port < 65536:
            raise ValueError(f"OpenIGTLink port must be 1..65535, got {port}")
        self.session, self.prefix, self.host, self.port = session, prefix, host, port
        self._model_mm = (model_start_mm, model_length_mm, model_radius_mm)
        # None: not calibrated yet (real devices start so); the model goes out when the drill calibration is installed.
        self._model = igtl.drill_model_message(axis_drill, start_mm=model_start_mm, length_mm=model_length_mm, radius_mm=model_radius_mm, stamp_ns=0) if axis_drill is not None else None
        self._ct_volume = ct_volume
        self.counters = IgtlCounters()
        self._lock = threading.Lock()
        self._clients: list[_Client] = []
        self._latched: dict[str, bytes] = {}
        self._drill_poses: OrderedDict[int, np.ndarray] = OrderedDict()
        self._listener: socket.socket | None = None
        self._subs: list = []
        self._accept_thread: threading.Thread | None = None

    # -- lifecycle ------------------------------------------------------------------------
    def __enter__(self) -> "IgtlServer":
        self._listener = socket.create_server((self.host, self.port), reuse_port=False)
        if self._model is not None:
            self._latched[igtl.DEVICE_DRILL_MODEL] = self._model.pack()
        if self._ct_volume is not None:
            self._latched[igtl.DEVICE_CT] = igtl.ct_image_message(self._ct_volume, stamp_ns=time.time_ns()).pack()
        self._accept_thread = threading.Thread(target=self._accept_loop, name="igtl-accept", daemon=True)
        self._accept_thread.start()
        try:
            p = self.prefix
            self._subs = [self.session.declare_subscriber(key(p, "axis_carm"), self._on_axis_carm),
                          self.session.declare_subscriber(key(p, "axis_ct"), self._on_axis_ct),
                          self.session.declare_subscriber(key(p, "fluoro_shot"), self._on_shot),
                          self.session.declare_subscriber(key(p, "status"), self._on_status),
                          self.session.declare_subscriber(key(p, "events"), self._on_event)]
        except Exception:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs = []
        if self._listener is not None:
            # shutdown wakes the blocked accept(); close alone does not on Linux.
            try:
                self._listener.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._listener.close()
            self._listener = None
        if self._accept_thread is not None:
            self._accept_thread.join(timeout=5)
            self._accept_thread = None
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            c.close()

    def set_drill_axis(self, axis_drill: Line3D) -> None:
        """A new drill calibration (installed over REST): every client gets the new model at once, later ones as they connect."""
        start, length, radius = self._model_mm
        self._model = igtl.drill_model_message(axis_drill, start_mm=start, length_mm=length, radius_mm=radius, stamp_ns=time.time_ns())
        self._send(self._model, latch=True)

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    # -- connections ----------------------------------------------------------------------
    def _accept_loop(self) -> None:
        listener = self._listener
        while True:
            try:
                sock, address = listener.accept()
            except OSError:
                return  # closed
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # a pose is small and late is stale
            client = _Client(sock, address, self._forget)
            with self._lock:
                self._clients.append(client)
                self.counters.clients_connected += 1
                latched = dict(self._latched)
            for device, data in latched.items():
                client.offer(device, data)
            client.start()

    def _forget(self, client: _Client) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)

    def _send(self, message: pyigtl.MessageBase, *, latch: bool = False) -> None:
        data = message.pack()
        with self._lock:
            if latch:
                self._latched[message.device_name] = data
            clients = list(self._clients)
            self.counters.messages_sent += len(clients)
            if message.message_type == "TRANSFORM":
                self.counters.transforms_sent += len(clients)
            elif message.message_type == "IMAGE":
                self.counters.images_sent += len(clients)
        for c in clients:
            c.offer(message.device_name, data)

    # -- zenoh inputs (a bad message is counted and skipped; the subscriber goes on) -------
    def _decoded(self, sample: zenoh.Sample) -> dict | None:
        try:
            return msg.decode_json(sample.payload.to_bytes())
        except ValueError:
            self.counters.decode_errors += 1
            return None

    def _on_axis_carm(self, sample: zenoh.Sample) -> None:
        if (doc := self._decoded(sample)) is None:
            return
        try:
            carm_from_drill = np.asarray(doc["carm_from_drill"], dtype=np.float64)
            stamp = int(doc["source_frame_stamp_ns"])
            m = igtl.transform_message(igtl.DEVICE_DRILL_TO_CARM, igtl.ras_transform(carm_from_drill, source_is_patient=False), stamp_ns=stamp)
        except (TypeError, KeyError, ValueError):
            self.counters.decode_errors += 1
            return
        with self._lock:
            self._drill_poses[stamp] = carm_from_drill
            while len(self._drill_poses) > _KEEP_DRILL_POSES:
                self._drill_poses.popitem(last=False)
        self._send(m)

    def _on_axis_ct(self, sample: zenoh.Sample) -> None:
        if (doc := self._decoded(sample)) is None:
            return
        try:
            carm_from_ct = np.asarray(doc["carm_from_ct"], dtype=np.float64)
            stamp = int(doc["source_frame_stamp_ns"])
            ct_to_carm = igtl.transform_message(igtl.DEVICE_CT_TO_CARM, igtl.ras_transform(carm_from_ct, source_is_patient=True), stamp_ns=stamp)
        except (TypeError, KeyError, ValueError):
            self.counters.decode_errors += 1
            return
        self._send(ct_to_carm, latch=True)
        with self._lock:
            carm_from_drill = self._drill_poses.get(stamp)
        if carm_from_drill is not None:  # the C-arm axis of the same camera frame
            ct_from_drill = invert(carm_from_ct) @ carm_from_drill
            self._send(igtl.transform_message(igtl.DEVICE_DRILL_TO_CT, igtl.ras_transform(ct_from_drill, source_is_patient=False), stamp_ns=stamp))

    def _on_shot(self, sample: zenoh.Sample) -> None:
        try:
            shot = msg.FluoroShot.from_bytes(sample.payload.to_bytes())
            image, view, stamp, name = shot.image_log, shot.carm_view, shot.stamp_ns, shot.view
            m = igtl.fluoro_image_message(image, view, device=f"Fluoro-{name}"[:20], stamp_ns=stamp)
        except ValueError:
            self.counters.decode_errors += 1
            return
        self._send(m, latch=True)

    def _on_status(self, sample: zenoh.Sample) -> None:
        if (doc := self._decoded(sample)) is None:
            return
        if "state" not in doc:
            self.counters.decode_errors += 1
            return
        text = f"{doc['state']} (registration {doc.get('registration_id', 0)}, views {','.join(doc.get('views', []))})"
        self._send(igtl.string_message(igtl.DEVICE_STATE, text, stamp_ns=int(doc.get("stamp_ns", 0))), latch=True)

    def _on_event(self, sample: zenoh.Sample) -> None:
        doc = self._decoded(sample)
        if doc is None or doc.get("level") not in ("warning", "error"):
            return
        self._send(igtl.string_message(igtl.DEVICE_ALERT, f"{doc['level']}: {doc.get('message', '')}", stamp_ns=int(doc.get("stamp_ns", 0))))
