"""The drill axis as rmw_zenoh's PoseStamped: key, CDR, attachment and graph tokens, checked against rmw_zenoh's formats on real zenoh.

The expected strings and byte layouts here are written from rmw_zenoh's sources and the CDR rules, not
computed by the code under test: the RIHS01 hash is the one ROS 2 Jazzy publishes for
geometry_msgs/msg/PoseStamped, the CDR is unpacked with struct, the attachment as zenoh-cpp writes it.
"""

import struct
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import free_endpoint
from drillnav.registration.line import Line3D
from drillnav.schemas import messages as msg
from drillnav.schemas import ros2
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.ros2_bridge import Ros2Bridge

HASH = "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
KEY = f"0/drillnav/drill_axis/geometry_msgs::msg::dds_::PoseStamped_/{HASH}"


def parse_pose_stamped(cdr: bytes):
    """XCDR1 little-endian PoseStamped: encapsulation, Header{Time{int32, uint32}, string}, then 7 float64 aligned to 8."""
    assert cdr[:4] == b"\x00\x01\x00\x00", "CDR_LE encapsulation header"
    body = cdr[4:]
    sec, nanosec, n = struct.unpack_from("<iII", body, 0)
    frame_id = body[12 : 12 + n - 1].decode()
    assert body[12 + n - 1] == 0, "strings carry their NUL"
    off = 12 + n
    off += (-off) % 8  # doubles align to 8 from the start of the body
    values = struct.unpack_from("<7d", body, off)
    assert off + 56 == len(body)
    return sec, nanosec, frame_id, np.array(values[:3]), np.array(values[3:])


def parse_attachment(att: bytes):
    """zenoh-ext: int64 LE, int64 LE, then std::array<uint8_t, 16> as a sequence (LEB128 length 16, bytes)."""
    assert len(att) == 33 and att[16] == 16
    seq, ts = struct.unpack_from("<qq", att, 0)
    return seq, ts, att[17:]


def test_key_and_tokens_follow_rmw_zenoh():
    assert ros2.topic_key(0, "/drillnav/drill_axis") == KEY
    assert ros2.type_hash(ros2.POSE_STAMPED) == HASH
    token = ros2.publisher_token(domain_id=7, zid="1f2e", node_id=0, entity_id=1, namespace="/", node="drillnav", topic="/drillnav/drill_axis")
    parts = token.split("/")
    # rmw_zenoh's Entity::make(keyexpr): 13 non-empty parts for a publisher, '/' in names mangled to '%'.
    assert parts == ["@ros2_lv", "7", "1f2e", "0", "1", "MP", "%", "%", "drillnav", "%drillnav%drill_axis",
                     "geometry_msgs::msg::dds_::PoseStamped_", HASH, "1:2:1,10:,:,:,,"]
    qos = parts[-1].split(":")  # keyexpr_to_qos: 6 parts; history, deadline, lifespan split by ',' into 2, 2, 2 and liveliness into 3
    assert len(qos) == 6 and [len(p.split(",")) for p in qos[2:]] == [2, 2, 2, 3]
    node = ros2.node_token(domain_id=7, zid="1f2e", node_id=0, namespace="/", node="drillnav").split("/")
    assert node == ["@ros2_lv", "7", "1f2e", "0", "0", "NN", "%", "%", "drillnav"]
    with pytest.raises(ValueError, match="absolute"):
        ros2.topic_key(0, "drill_axis")


def test_pose_stamped_cdr():
    axis = Line3D(point_mm=[12.5, -40.0, 230.0], direction=[0.2, -0.3, 0.9])
    sec, nanosec, frame_id, p, q = parse_pose_stamped(ros2.axis_pose_stamped(axis, stamp_ns=1_795_000_000_987_654_321, frame_id="carm"))
    assert (sec, nanosec, frame_id) == (1_795_000_000, 987_654_321, "carm")
    assert np.allclose(p, [0.0125, -0.040, 0.230])  # metres (REP 103)
    assert np.allclose(Rotation.from_quat(q).apply([1, 0, 0]), axis.direction)  # +x along the axis; (x, y, z, w)


def test_bridge_publishes_what_a_ros2_subscriber_takes():
    ep = free_endpoint()
    got, tokens = [], []
    with open_session(listen=[ep]) as node_session, open_session(connect=[ep]) as ros_side:
        with Ros2Bridge(session=node_session, prefix="drillnav") as bridge:
            # What rmw_zenoh's subscription declares: the exact data key.
            ros_side.declare_subscriber(KEY, lambda s: got.append((s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment else None)))
            time.sleep(0.3)
            # What rmw_zenoh's graph cache queries at start-up.
            tokens = [str(r.ok.key_expr) for r in ros_side.liveliness().get(f"{ros2.ADMIN_SPACE}/0/**", timeout=2.0) if r.ok is not None]
            stamps = [1_795_000_000_000_000_000 + i * 33_333_333 for i in range(5)]
            for i, stamp in enumerate(stamps):
                axis = {"stamp_ns": stamp + 5_000_000, "frame_id": "carm", "point_mm": [10.0 * i, 2.0, 3.0], "direction": [0.0, 0.6, 0.8],
                        "source_frame_stamp_ns": stamp, "predicted_error": {"position_mm": 1.0, "angle_deg": 0.5}, "registration_id": 1}
                node_session.put(key("drillnav", "axis_carm"), msg.encode_json(axis))
            node_session.put(key("drillnav", "axis_carm"), b"{not json")
            deadline = time.monotonic() + 5
            while len(got) < 5 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert bridge.decode_errors == 1
        # Closing the bridge takes the node and its publisher out of the ROS graph.
        time.sleep(0.3)
        left = [r for r in ros_side.liveliness().get(f"{ros2.ADMIN_SPACE}/0/**", timeout=1.0) if r.ok is not None]
    assert sorted(t.split("/")[5] for t in tokens) == ["MP", "NN"]
    assert bridge.publisher_token_key in tokens and bridge.node_token_key in tokens
    assert left == []
    assert len(got) == 5
    for i, ((payload, att), stamp) in enumerate(zip(got, stamps)):
        sec, nanosec, frame_id, p, q = parse_pose_stamped(payload)
        assert sec * 1_000_000_000 + nanosec == stamp and frame_id == "carm"
        assert np.allclose(p, [0.010 * i, 0.002, 0.003])
        assert np.allclose(Rotation.from_quat(q).apply([1, 0, 0]), [0, 0.6, 0.8])
        seq, ts, gid = parse_attachment(att)
        assert (seq, ts, gid) == (i + 1, stamp, bridge.gid)
