"""OpenIGTLink: a real node fed by the twin recording, the server on a free port, and an independent client.

The client below parses the protocol from its specification (58-byte header,
big-endian, CRC-64 ECMA-182 over the body) with struct alone: it shares no code
with the server's encoder (pyigtl).
"""

import socket
import struct
import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import free_endpoint, free_port
from twin_replay import play_at_camera_rate
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.carm import CArmView
from drillnav.registration.line import Line3D
from drillnav.registration.volume import Volume
from drillnav.schemas import igtl
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.igtl_server import IgtlServer
from drillnav.service.node import RegistrationNode

HEADER = struct.Struct(">H12s20sIIQQ")
_ECMA182 = 0x42F0E1EBA9EA3693


def crc64(data: bytes) -> int:
    crc = 0
    for byte in data:
        crc ^= byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ _ECMA182) & 0xFFFFFFFFFFFFFFFF if crc & (1 << 63) else (crc << 1) & 0xFFFFFFFFFFFFFFFF
    return crc


class RawClient:
    """Connects, reconnects after the server goes away, and keeps every message as (arrival_s, type, device, stamp_ns, body)."""

    def __init__(self, port: int) -> None:
        self.port, self.messages, self.connections = port, [], 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _recv(self, sock, n):
        buf = b""
        while len(buf) < n:
            chunk = sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("closed")
            buf += chunk
        return buf

    def _run(self):
        while not self._stop.is_set():
            try:
                sock = socket.create_connection(("127.0.0.1", self.port), timeout=0.5)
            except OSError:
                time.sleep(0.05)
                continue
            self.connections += 1
            sock.settimeout(None)
            try:
                while not self._stop.is_set():
                    version, mtype, device, sec, frac, size, crc = HEADER.unpack(self._recv(sock, HEADER.size))
                    body = self._recv(sock, size)
                    mtype, device = mtype.rstrip(b"\0").decode(), device.rstrip(b"\0").decode()
                    if mtype == "TRANSFORM":
                        assert crc64(body) == crc, "CRC-64 of a TRANSFORM body"
                    stamp_ns = sec * 1_000_000_000 + round(frac * 1e9 / 2**32)
                    self.messages.append((time.monotonic(), mtype, device, stamp_ns, body))
            except (ConnectionError, OSError):
                pass
            finally:
                sock.close()

    def of(self, device):
        return [m for m in list(self.messages) if m[2] == device]

    def wait_for(self, device, count=1, timeout=10.0):
        deadline = time.monotonic() + timeout
        while len(self.of(device)) < count and time.monotonic() < deadline:
            time.sleep(0.02)
        return self.of(device)

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2)


def image_header(body: bytes):
    """IMAGE body: version, components, scalar type, endian, coordinates, size i j k, t s n c (12 float), sub-volume (6 uint16); then voxels."""
    return struct.unpack(">HBBBBHHH12f6H", body[:72]), body[72:]


def transform_matrix(body: bytes) -> np.ndarray:
    v = struct.unpack(">12f", body)  # R11 R21 R31 R12 R22 R32 R13 R23 R33 TX TY TZ
    m = np.eye(4)
    m[:3, :3] = np.array(v[:9]).reshape(3, 3).T
    m[:3, 3] = v[9:]
    return m


def test_ras_conversion_and_image_geometry():
    lps = np.array([[1, 0, 0, 10.0], [0, 0, -1, -20], [0, 1, 0, 30], [0, 0, 0, 1]])
    ras = igtl.ras_transform(lps, source_is_patient=False)
    # A drill-frame point lands at the same patient point, with L and P flipped to R and A.
    x = np.array([1.0, 2, 3, 1])
    assert np.allclose(ras @ x, (lps @ x) * [-1, -1, 1, 1])
    both = igtl.ras_transform(lps, source_is_patient=True)
    assert np.allclose(both @ (x * [-1, -1, 1, 1]), (lps @ x) * [-1, -1, 1, 1])
    with pytest.raises(ValueError, match="4x4"):
        igtl.ras_transform(np.eye(3), source_is_patient=False)
    view = CArmView.from_positioner(primary_deg=20, secondary_deg=-10, source_to_detector_mm=1164, source_to_isocenter_mm=624,
                                    pixel_spacing_mm=(0.304, 0.304), rows=976, columns=976)
    lps_from_ijk = igtl.fluoro_image_lps_from_ijk(view)
    for u, v in [(0, 0), (975, 0), (300.5, 700)]:
        p = lps_from_ijk @ [u, v, 0, 1]
        h = view.projection_matrix @ p
        assert np.allclose(h[:2] / h[2], [u, v], atol=1e-6)  # each pixel's detector point projects back onto it
        assert abs(np.linalg.norm(p[:3] - view.source_position_mm) - 1164) < 300  # on the detector, beyond the isocentre
    centre = lps_from_ijk @ [487.5, 487.5, 0, 1]
    assert abs(np.linalg.norm(centre[:3] - view.source_position_mm) - 1164) < 1e-6


def test_drill_cylinder_lies_along_the_axis():
    axis = Line3D(point_mm=[0, 45, 0], direction=[0, -0.2, 1])
    points, cells = igtl.drill_cylinder(axis, start_mm=60, length_mm=200, radius_mm=1.5, sides=12)
    rim = points[:24]
    assert np.allclose(axis.distance_to_point(rim.astype(float)), 1.5, atol=1e-4)
    s = (points.astype(float) - axis.point_mm) @ axis.direction
    assert s.min() == pytest.approx(60, abs=1e-3) and s.max() == pytest.approx(260, abs=1e-3)
    assert cells.max() < len(points)
    with pytest.raises(ValueError, match="radius"):
        igtl.drill_cylinder(axis, start_mm=0, length_mm=10, radius_mm=0)


def test_slicer_client_gets_drill_pose_image_and_reconnects():
    scene = make_scene(seed=21, render=False)
    port, ep = free_port(), free_endpoint()
    axes = []
    client = None
    with open_session(listen=[ep]) as player, open_session(connect=[ep]) as node_session:
        node = RegistrationNode(session=node_session, prefix="drillnav", marker_set=scene.marker_set, camera=scene.calibrated_camera,
                                axis_drill=scene.calibrated_axis_drill).__enter__()
        try:
            axis_arrivals = []
            node_session.declare_subscriber(key("drillnav", "axis_carm"), lambda s: (axes.append(msg.decode_json(s.payload.to_bytes())), axis_arrivals.append(time.monotonic())))
            server = IgtlServer(session=node_session, prefix="drillnav", axis_drill=scene.calibrated_axis_drill, port=port)
            with server:
                client = RawClient(port)
                assert client.wait_for(igtl.DEVICE_DRILL_MODEL), "the drill model is sent as a client connects"
                time.sleep(0.3)
                play_at_camera_rate(player, node)

                def newest_arrived():
                    poses = client.of(igtl.DEVICE_DRILL_TO_CARM)
                    return bool(poses and axes) and abs(poses[-1][3] - axes[-1]["source_frame_stamp_ns"]) < 1000
                # The node may still be tracking the last frame when the player returns: wait until its axes have
                # stopped coming (one second without a new one) and the newest of them has reached the client.
                deadline, seen, quiet_since = time.monotonic() + 30, -1, time.monotonic()
                while time.monotonic() < deadline:
                    if len(axes) != seen:
                        seen, quiet_since = len(axes), time.monotonic()
                    elif time.monotonic() - quiet_since > 1.0 and newest_arrived():
                        break
                    time.sleep(0.05)
                images = client.wait_for("Fluoro-inlet") + client.wait_for("Fluoro-outlet")
            got = client.of(igtl.DEVICE_DRILL_TO_CARM)
            assert len(axes) >= 10, f"the node published only {len(axes)} axes ({node.status()})"
            # One per axis, except that a pose not yet sent when the next arrives is replaced by it (newest wins):
            # on a starved machine a few are superseded, never delayed; the last one always arrives.
            assert len(got) >= len(axes) - 3, f"{len(got)} DrillToCArm for {len(axes)} axes"
            assert newest_arrived(), "the newest pose arrives"
            stamps = np.array([a["source_frame_stamp_ns"] for a in axes])
            for _, _, _, stamp_ns, body in got:
                # Stamped with the camera frame's capture stamp; pyigtl carries it as float seconds (~0.24 us grain).
                nearest = int(np.argmin(np.abs(stamps - stamp_ns)))
                assert abs(int(stamps[nearest]) - stamp_ns) < 1000
                a = axes[nearest]
                carm_from_drill = np.asarray(a["carm_from_drill"])
                m = transform_matrix(body)
                assert np.allclose(m, np.diag([-1, -1, 1, 1]) @ carm_from_drill, atol=1e-3)
                # The published axis, carried by the received transform, is the axis in RAS.
                axis_ras = scene.calibrated_axis_drill.transformed(m)
                assert np.allclose(axis_ras.direction, np.asarray(a["direction"]) * [-1, -1, 1], atol=1e-5)
                assert axis_ras.distance_to_point(np.asarray(a["point_mm"]) * [-1, -1, 1]) < 1e-3
            arrivals = np.array([m[0] for m in got])
            rate_hz = (len(arrivals) - 1) / (arrivals[-1] - arrivals[0])
            axis_rate_hz = (len(axis_arrivals) - 1) / (axis_arrivals[-1] - axis_arrivals[0])
            print(f"DrillToCArm: {len(got)} transforms at {rate_hz:.1f} Hz; the node's axes at {axis_rate_hz:.1f} Hz (camera 30 Hz)")
            # The server keeps the node's pace (the camera's, unless the machine is starved: the node drops stale frames).
            assert rate_hz > 0.85 * axis_rate_hz and rate_hz > 15, f"DrillToCArm arrived at {rate_hz:.1f} Hz, the axes at {axis_rate_hz:.1f} Hz"
            # Each shot arrives as an IMAGE on its detector, float32, one slice of rows x columns.
            assert {m[2] for m in images} == {"Fluoro-inlet", "Fluoro-outlet"}
            head, pixels = image_header(images[0][4])
            assert head[2] == 10 and head[4] == 1  # float32, RAS
            view = node.shots["inlet"].view if images[0][2] == "Fluoro-inlet" else node.shots["outlet"].view
            assert head[5:8] == (view.columns, view.rows, 1) and len(pixels) == view.rows * view.columns * 4
            expected = np.diag([-1, -1, 1, 1]) @ igtl.fluoro_image_lps_from_ijk(view)
            tsn = np.array(head[8:17]).reshape(3, 3).T  # columns: i, j, k directions with spacing
            assert np.allclose(tsn, expected[:3, :3], atol=1e-4)
            centre = expected @ [(view.columns - 1) / 2, (view.rows - 1) / 2, 0, 1]
            assert np.allclose(head[17:20], centre[:3], atol=0.05)

            # The server restarts on the same port: the client reconnects and gets the scene again.
            before = client.connections
            # A small CT (video-CT mode): oblique, anisotropic voxels, so the geometry check means something.
            patient_from_voxel = np.eye(4)
            patient_from_voxel[:3, :3] = Rotation.from_euler("zyx", [20, -10, 5], degrees=True).as_matrix() @ np.diag([0.8, 0.9, 2.5])
            patient_from_voxel[:3, 3] = [-100.0, 50.0, 300.0]
            ct = Volume(data=np.arange(6 * 7 * 8, dtype=np.float32).reshape(6, 7, 8) - 1000.4, patient_from_voxel=patient_from_voxel)
            with IgtlServer(session=node_session, prefix="drillnav", axis_drill=scene.calibrated_axis_drill, port=port, ct_volume=ct) as again:
                deadline = time.monotonic() + 10
                while client.connections == before and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert client.connections == before + 1, "the client reconnected to the restarted server"
                models = client.wait_for(igtl.DEVICE_DRILL_MODEL, count=2)
                assert len(models) == 2
                head, voxels = image_header(client.wait_for(igtl.DEVICE_CT)[0][4])
                assert head[2] == 4 and head[4] == 1 and head[5:8] == (8, 7, 6)  # int16, RAS, (i, j, k) sizes
                ras_from_voxel = np.diag([-1, -1, 1, 1]) @ patient_from_voxel
                assert np.allclose(np.array(head[8:17]).reshape(3, 3).T, ras_from_voxel[:3, :3], atol=1e-5)
                assert np.allclose(head[17:20], (ras_from_voxel @ [3.5, 3, 2.5, 1])[:3], atol=1e-3)  # OpenIGTLink sends the centre
                assert np.array_equal(np.frombuffer(voxels, "<i2").reshape(6, 7, 8), np.round(ct.data).astype(np.int16))
                # A new axis reaches the reconnected client. Identified by its own stamp, not by a count: the server may
                # also replay the newest pose on connect, and a late axis of the node may still be on its way.
                fresh = dict(axes[-1], source_frame_stamp_ns=int(axes[-1]["source_frame_stamp_ns"]) + 7_000_000_000)
                node_session.put(key("drillnav", "axis_carm"), msg.encode_json(fresh))
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline and not any(abs(m[3] - fresh["source_frame_stamp_ns"]) < 1000 for m in client.of(igtl.DEVICE_DRILL_TO_CARM)):
                    time.sleep(0.02)
                assert any(abs(m[3] - fresh["source_frame_stamp_ns"]) < 1000 for m in client.of(igtl.DEVICE_DRILL_TO_CARM)), "the new axis reached the client"
                assert again.clients == 1
                # A drill calibration installed while Slicer is connected reaches it as a new model.
                moved = Line3D(point_mm=scene.calibrated_axis_drill.point_mm + [5.0, 0, 0], direction=scene.calibrated_axis_drill.direction)
                again.set_drill_axis(moved)
                models = client.wait_for(igtl.DEVICE_DRILL_MODEL, count=3)
                first_point = lambda body: np.array(struct.unpack_from(">3f", body, 40))  # after the 10 counts of the POLYDATA header
                assert np.allclose(first_point(models[2][4]) - first_point(models[1][4]), [5.0, 0, 0], atol=1e-3)
        finally:
            if client is not None:
                client.close()
            node.close()
