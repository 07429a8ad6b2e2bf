"""Foxglove: the scene converter, and the same scene in a recording (real Recorder) and live (real foxglove-sdk server).

The live side is read by a plain WebSocket client speaking the Foxglove WebSocket protocol
(advertise, subscribe, binary messageData) written here from the protocol's
specification; the recording by the ``mcap`` reader, each message decoded with
the protobuf classes built from the schema the file itself carries, and
compared with ``foxglove_schemas_protobuf``'s.
"""

import json
import struct
import threading
import time

import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from scipy.spatial.transform import Rotation
from websockets.sync.client import connect

from conftest import free_endpoint, free_port
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.camera import PinholeCamera
from drillnav.registration.carm import CArmView
from drillnav.registration.line import Line3D
from drillnav.schemas import foxglove_scene as fox
from drillnav.schemas.protobuf_types import PROTOBUF_TYPES
from drillnav.service.bus import open_session
from drillnav.service.foxglove_bridge import FoxgloveBridge
from drillnav.service.node import RegistrationNode
from drillnav.service.recorder import Recorder
from drillnav.service.scene_publisher import ScenePublisher
from twin_replay import play_at_camera_rate

NEEDED = {"foxglove.FrameTransform", "foxglove.SceneUpdate", "foxglove.CameraCalibration", "foxglove.ImageAnnotations"}


def carm_from_child(tf: FrameTransform) -> np.ndarray:
    """Back to drillnav's 4x4 (mm) from Foxglove's (m, x-y-z-w quaternion)."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]).as_matrix()
    m[:3, 3] = np.array([tf.translation.x, tf.translation.y, tf.translation.z]) * 1000.0
    return m


def projection_error(cal: CameraCalibration, tf: FrameTransform, view: CArmView) -> float:
    """How far Foxglove's P, applied through the frame's transform, is from the view's P (both scaled to unit norm)."""
    p_fox = np.array(cal.P).reshape(3, 4)
    p = p_fox @ np.linalg.inv(carm_from_child(tf))
    a, b = p / np.linalg.norm(p), view.projection_matrix / np.linalg.norm(view.projection_matrix)
    return float(np.abs(a - b * np.sign(a.ravel() @ b.ravel())).max())


@pytest.mark.parametrize("primary, secondary, mirrored", [(0, 0, False), (35, -20, False), (-60, 25, True)])
def test_view_calibration_reproduces_the_projection(primary, secondary, mirrored):
    view = CArmView.from_positioner(primary_deg=primary, secondary_deg=secondary, source_to_detector_mm=1164, source_to_isocenter_mm=624,
                                    pixel_spacing_mm=(0.304, 0.304), rows=976, columns=976, principal_point_px=(480.2, 491.7))
    if mirrored:  # a detector stored left-right flipped: u' = (columns - 1) - u
        flip = np.array([[-1, 0, 975], [0, 1, 0], [0, 0, 1.0]])
        view = CArmView(projection_matrix=flip @ view.projection_matrix, rows=976, columns=976, pixel_spacing_mm=(0.304, 0.304))
    cal, carm_from_source = fox.view_calibration(view, view_name="inlet", stamp_ns=123)
    tf = fox.frame_transform(fox.FRAME_CARM, fox.view_frame("inlet"), carm_from_source, stamp_ns=123)
    assert projection_error(cal, tf, view) < 1e-6
    assert view.depth_mm(np.zeros((1, 3)))[0] == pytest.approx(624.0)  # the isocentre in front of the source, mirrored or not
    assert cal.frame_id == tf.child_frame_id == "carm/inlet" and (cal.width, cal.height) == (976, 976)
    # A point in C projects to the same pixel through Foxglove's model as through the view's.
    x = np.array([12.0, -30.0, 45.0, 1.0])
    h = np.array(cal.P).reshape(3, 4) @ np.linalg.inv(carm_from_child(tf)) @ x
    assert np.allclose(h[:2] / h[2], view.project(x[:3].reshape(1, 3))[0], atol=1e-6)


def test_converter_checks_and_units():
    with pytest.raises(ValueError, match="rigid"):
        fox.frame_transform("a", "b", np.diag([2.0, 1, 1, 1]), stamp_ns=0)
    with pytest.raises(ValueError, match="level"):
        fox.event_log("loud", "x", stamp_ns=0)
    with pytest.raises(ValueError, match="predicted errors"):
        fox.axis_scene(Line3D(point_mm=[0, 0, 0], direction=[0, 0, 1]), angle_deg=-1, position_mm=0, stamp_ns=0)
    axis = Line3D(point_mm=[10, 20, 30], direction=[0, 0.6, 0.8])
    scene = fox.axis_scene(axis, angle_deg=1.0, position_mm=0.5, stamp_ns=5_000_000_123)
    arrow = scene.entities[0].arrows[0]
    start = np.array([arrow.pose.position.x, arrow.pose.position.y, arrow.pose.position.z]) * 1000
    assert np.allclose(start, axis.at(-fox.AXIS_BEHIND_MM))  # metres in Foxglove, mm in drillnav
    q = arrow.pose.orientation
    assert np.allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).apply([1, 0, 0]), axis.direction)
    assert scene.entities[0].timestamp.seconds == 5 and scene.entities[0].timestamp.nanos == 123


def test_an_intensifier_views_annotations_lie_where_it_shows_the_axis():
    """With the view's estimated distortion (DrillAxis.detector_distortion_px) the axis strip and the markers are
    placed on the distorted image, not the ideal projection; a flat panel's are the projection itself."""
    from drillnav.registration.carm import intensifier_shift_px

    view = CArmView.from_positioner(primary_deg=20, secondary_deg=-10, source_to_detector_mm=1164, source_to_isocenter_mm=624,
                                    pixel_spacing_mm=(0.304, 0.304), rows=976, columns=976)
    axis = Line3D(point_mm=[40.0, -35.0, 8.0], direction=[0.6, 0.3, 0.74])
    k = np.array([8.0, 3.0])
    marker = np.array([[60.0, 50.0, 10.0]])
    flat = fox.view_annotations(view, stamp_ns=1, axis_carm=axis, markers_carm_mm={3: marker[0]})
    bent = fox.view_annotations(view, stamp_ns=1, axis_carm=axis, markers_carm_mm={3: marker[0]}, distortion_px=k)
    ideal = view.project(axis.at(np.linspace(-fox.AXIS_BEHIND_MM, fox.AXIS_AHEAD_MM, fox.STRIP_POINTS)))
    strip = np.array([[p.x, p.y] for p in bent.points[0].points])
    assert np.allclose(strip, ideal + intensifier_shift_px(ideal, view.center_px, view.corner_radius_px, k), atol=1e-9)
    assert np.abs(strip - ideal).max() > 1.0  # moved: this axis runs out towards the field's edge
    assert np.allclose([[p.x, p.y] for p in flat.points[0].points], ideal[[0, -1]], atol=1e-9)
    uv = view.project(marker)
    for ann, want in ((flat, uv), (bent, uv + intensifier_shift_px(uv, view.center_px, view.corner_radius_px, k))):
        dot = ann.points[-1].points[0]
        assert np.allclose([dot.x, dot.y], want[0], atol=1e-9)


class FoxgloveWsClient:
    """Subscribes to every channel it is told about and keeps (topic, schema name, payload) of each message."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.channels: dict[int, dict] = {}
        self.subscriptions: dict[int, int] = {}
        self.messages: list[tuple[str, str, bytes]] = []
        self.server_info: dict | None = None
        self.subprotocol: str | None = None
        self.statuses: list[dict] = []
        self._stop, self._ready = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        assert self._ready.wait(5), "no Foxglove WebSocket connection"

    def _run(self):
        # foxglove-sdk's server speaks the protocol under its new name, foxglove.sdk.v1, the same ops as
        # foxglove.websocket.v1 (https://github.com/orgs/foxglove/discussions/1131); the client offers both.
        with connect(self.url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], open_timeout=5, max_size=None) as ws:
            self.subprotocol = ws.subprotocol
            self._ready.set()
            while not self._stop.is_set():
                try:
                    frame = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                except Exception:
                    return
                self._handle(ws, frame)

    def _handle(self, ws, frame):
        if isinstance(frame, str):
            doc = json.loads(frame)
            if doc["op"] == "serverInfo":
                self.server_info = doc
            elif doc["op"] == "status":
                self.statuses.append(doc)
                # foxglove-sdk 0.30 may refuse the first subscribe to a channel it advertised a moment before
                # (docs/foxglove.md); a client asks again, as it would after any refused subscription.
                if doc["message"].startswith("Unknown channel ID: "):
                    channel_id = int(doc["message"].rsplit(" ", 1)[1])
                    retry = [sid for sid, cid in self.subscriptions.items() if cid == channel_id]
                    time.sleep(0.02)
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": sid, "channelId": channel_id} for sid in retry]}))
            elif doc["op"] == "advertise":
                subs = []
                for ch in doc["channels"]:
                    self.channels[ch["id"]] = ch
                    sub_id = len(self.subscriptions) + 1
                    self.subscriptions[sub_id] = ch["id"]
                    subs.append({"id": sub_id, "channelId": ch["id"]})
                ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        elif frame[0] == 0x01:  # messageData: opcode, subscription id (u32), log time (u64), payload
            sub_id, _ = struct.unpack_from("<IQ", frame, 1)
            ch = self.channels[self.subscriptions[sub_id]]
            self.messages.append((ch["topic"], ch["schemaName"], bytes(frame[13:])))

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2)


def dynamic_classes(schema_data: bytes) -> descriptor_pool.DescriptorPool:
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return pool


def check_scene(messages, views: dict[str, CArmView], where: str) -> None:
    """messages: (topic, schema name, decoded message). Every needed schema is there, and each view's calibration projects as the view."""
    names = {s for _, s, _ in messages}
    assert NEEDED <= names, f"{where}: missing {NEEDED - names}"
    tfs = {m.child_frame_id: m for _, s, m in messages if s == "foxglove.FrameTransform"}
    assert {"drill_camera", "carm/inlet", "carm/outlet"} <= set(tfs), f"{where}: frames {sorted(tfs)}"
    assert any(k.startswith("marker/") for k in tfs)
    cals = {m.frame_id: m for _, s, m in messages if s == "foxglove.CameraCalibration"}
    for name, view in views.items():
        err = projection_error(cals[fox.view_frame(name)], tfs[fox.view_frame(name)], view)
        assert err < 1e-6, f"{where}: view {name} projects {err:.2e} off"
    assert "drill_camera" in cals and cals["drill_camera"].distortion_model == "plumb_bob"
    entities = {e.id for _, s, m in messages if s == "foxglove.SceneUpdate" for e in m.entities}
    assert {"drill_axis", "markers"} <= entities
    anns = [m for t, s, m in messages if s == "foxglove.ImageAnnotations"]
    assert anns and all(len(a.points) >= 1 for a in anns)
    assert {t.rsplit("/", 1)[1] for t, s, _ in messages if s == "foxglove.ImageAnnotations"} == set(views)


def test_recording_and_live_websocket_carry_the_scene(tmp_path):
    scene = make_scene(seed=21, render=False)
    ep, ws_port = free_endpoint(), free_port()
    client = None
    with open_session(listen=[ep]) as player, open_session(connect=[ep]) as s:
        node = RegistrationNode(session=s, prefix="drillnav", marker_set=scene.marker_set, camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill).__enter__()
        recorder = Recorder(session=s, prefix="drillnav", folder=tmp_path, name="fox")
        try:
            with FoxgloveBridge(session=s, prefix="drillnav", port=ws_port) as bridge, \
                    ScenePublisher(session=s, prefix="drillnav", camera=scene.calibrated_camera, republish_period_s=0.5) as scene_pub:
                client = FoxgloveWsClient(f"ws://127.0.0.1:{ws_port}")
                time.sleep(0.3)
                play_at_camera_rate(player, node)
                time.sleep(1.2)  # one republish of the latched scene, and the annotations' period
                # A camera calibration installed while running replaces the drill camera's model.
                k = scene.calibrated_camera.camera_matrix.copy()
                k[0, 0] += 11.0
                scene_pub.set_camera(PinholeCamera(width=scene.calibrated_camera.width, height=scene.calibrated_camera.height, camera_matrix=k,
                                                   distortion=scene.calibrated_camera.distortion))
                time.sleep(0.3)
                views = {n: sh.view for n, sh in node.shots.items()}
                assert bridge.forwarded > 0
        finally:
            if client is not None:
                client.close()
            files = recorder.close()
            node.close()
    assert client.server_info is not None and client.server_info["name"] == "drillnav" and client.subprotocol == "foxglove.sdk.v1"
    print("refused subscriptions (retried):", [d["message"] for d in client.statuses])
    live = [(t, s, PROTOBUF_TYPES[s].FromString(p)) for t, s, p in client.messages if s in PROTOBUF_TYPES]
    check_scene(live, views, "live")
    fx = [m.K[0] for _, s, m in live if s == "foxglove.CameraCalibration" and m.frame_id == "drill_camera"]
    assert fx[0] == scene.calibrated_camera.camera_matrix[0, 0] and fx[-1] == fx[0] + 11.0
    print(f"live: {len(client.messages)} messages on {len(client.channels)} channels")

    recorded, counts = [], {}
    for f in files:
        with open(f, "rb") as fp:
            for schema, channel, message in make_reader(fp).iter_messages():
                counts[schema.name] = counts.get(schema.name, 0) + 1
                if schema.encoding != "protobuf":
                    continue
                pool = dynamic_classes(schema.data)  # the file's own schema, independent of drillnav's classes
                dyn = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name)).FromString(message.data)
                known = PROTOBUF_TYPES[schema.name].FromString(message.data)
                assert dyn.SerializeToString(deterministic=True) == known.SerializeToString(deterministic=True)
                recorded.append((channel.topic, schema.name, known))
    check_scene(recorded, views, "recording")
    print("recording:", counts)
