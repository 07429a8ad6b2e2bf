"""What ROS 2's ``rmw_zenoh`` puts on zenoh, so a ROS 2 node on the same zenoh subscribes to drillnav directly.

Read from the rmw_zenoh sources (``ros2/rmw_zenoh``: ``liveliness_utils.cpp``,
``attachment_helpers.cpp``, ``rmw_subscription_data.cpp``, ``qos.cpp``; docs/ros2.md):

- data key: ``<domain_id>/<topic without leading '/'>/<DDS type name>/<RIHS01 type hash>``;
- payload: the message in CDR (little-endian, with the 4-byte encapsulation header);
- attachment (a subscriber drops a sample without one): zenoh-ext serialisation of
  ``int64 sequence_number, int64 source_timestamp_ns, array<uint8, 16> source_gid``
  (the array carries its length, as zenoh-cpp writes ``std::array``);
- liveliness tokens for the graph (``ros2 node list``, ``ros2 topic info``):
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node>``
  and, for a publisher, ``/<topic>/<type>/<hash>/<qos>``, with '/' in names mangled to '%'.

The CDR and the type hash come from ``rosbags`` (a pure-Python ROS 2 type system
that computes RIHS01 hashes from the message definitions), not from hand-written code.
"""

from __future__ import annotations

import hashlib

import numpy as np
import zenoh.ext as zext
from numpy.typing import ArrayLike
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from drillnav.registration.line import Line3D

__all__ = [
    "POSE_STAMPED",
    "ADMIN_SPACE",
    "dds_type_name",
    "type_hash",
    "topic_key",
    "node_token",
    "publisher_token",
    "qos_keyexpr",
    "publisher_gid",
    "attachment",
    "axis_pose_stamped",
]

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ADMIN_SPACE = "@ros2_lv"
_MM_TO_M = 1e-3
# ROS 2 Jazzy's message definitions; PoseStamped (and its parts) are the same in Kilted and Rolling,
# so the hash is too. Humble has no type hashes (rmw_zenoh sends "TypeHashNotSupported" there).
_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

# rmw's QoS enums (rmw/types.h): RELIABILITY_RELIABLE, DURABILITY_VOLATILE, HISTORY_KEEP_LAST.
_RELIABLE, _VOLATILE, _KEEP_LAST = 1, 2, 1


def _mangle(name: str) -> str:
    return name.replace("/", "%")


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs::msg::dds_::PoseStamped_`` (the name rmw_zenoh puts in keys)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def type_hash(ros_type: str) -> str:
    return _TYPESTORE.hash_rihs01(ros_type)


def _check_topic(topic: str) -> str:
    if not topic.startswith("/") or "//" in topic or topic.endswith("/") or any(c in topic for c in "*$?# "):
        raise ValueError(f"ROS topic '{topic}' must be absolute ('/a/b'), without empty parts, spaces or zenoh wildcards")
    return topic


def topic_key(domain_id: int, topic: str, ros_type: str = POSE_STAMPED) -> str:
    return f"{int(domain_id)}/{_check_topic(topic).strip('/')}/{dds_type_name(ros_type)}/{type_hash(ros_type)}"


def _node_parts(domain_id: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str, enclave: str = "/") -> list[str]:
    return [ADMIN_SPACE, str(int(domain_id)), zid, str(int(node_id)), str(int(entity_id)), kind, _mangle(enclave), _mangle(namespace), _mangle(node)]


def node_token(*, domain_id: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    """The ``NN`` liveliness token of a node (its entity id is its node id, as rmw_zenoh does)."""
    return "/".join(_node_parts(domain_id, zid, node_id, node_id, "NN", namespace, node))


def qos_keyexpr(*, depth: int = 10) -> str:
    """A reliable, volatile, keep-last ``depth`` publisher in rmw_zenoh's QoS key format.

    rmw_zenoh leaves a field empty when it equals its default, and its default durability differs
    between releases (transient-local in some, volatile in others); the parser takes an explicit value as well,
    so reliability, durability, history and depth are always written. Deadline, lifespan and
    liveliness stay empty: infinite / automatic in every release.
    """
    if depth < 1:
        raise ValueError(f"history depth must be >= 1, got {depth}")
    return f"{_RELIABLE}:{_VOLATILE}:{_KEEP_LAST},{int(depth)}:,:,:,,"


def publisher_token(*, domain_id: int, zid: str, node_id: int, entity_id: int, namespace: str, node: str, topic: str,
                    ros_type: str = POSE_STAMPED, depth: int = 10) -> str:
    parts = _node_parts(domain_id, zid, node_id, entity_id, "MP", namespace, node)
    parts += [_mangle(_check_topic(topic)), dds_type_name(ros_type), type_hash(ros_type), qos_keyexpr(depth=depth)]
    return "/".join(parts)


def publisher_gid(token: str) -> bytes:
    """16 bytes naming the publisher. rmw_zenoh hashes the token with XXH3-128; any stable 16 bytes serve a
    subscriber (it only reports them in ``message_info``), so a standard hash of the same token is used."""
    return hashlib.blake2b(token.encode(), digest_size=16).digest()


def attachment(*, sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The sample attachment rmw_zenoh's subscribers require (zenoh-ext serialisation)."""
    if len(gid) != 16:
        raise ValueError(f"a ROS gid is 16 bytes, got {len(gid)}")
    return zext.z_serialize((zext.Int64(int(sequence_number)), zext.Int64(int(source_timestamp_ns)), bytes(gid))).to_bytes()


def axis_pose_stamped(axis_mm: Line3D, *, stamp_ns: int, frame_id: str) -> bytes:
    """The drill axis as ``geometry_msgs/msg/PoseStamped`` in CDR: position = the axis point (m), orientation
    taking +x onto the axis direction (RViz draws a pose as an arrow along +x). An axis has no roll: the
    rotation is the smallest one from +x, so only its x column carries information."""
    msgs = _TYPESTORE.types
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    q = _quaternion_x_to(axis_mm.direction)
    p = np.asarray(axis_mm.point_mm, dtype=np.float64).reshape(3) * _MM_TO_M
    msg = msgs[POSE_STAMPED](
        header=msgs["std_msgs/msg/Header"](stamp=msgs["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id),
        pose=msgs["geometry_msgs/msg/Pose"](position=msgs["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                             orientation=msgs["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))
    return bytes(_TYPESTORE.serialize_cdr(msg, POSE_STAMPED))


def _quaternion_x_to(direction: ArrayLike) -> np.ndarray:
    rot, _ = Rotation.align_vectors([np.asarray(direction, dtype=np.float64)], [[1.0, 0.0, 0.0]])
    return rot.as_quat()  # (x, y, z, w): ROS's order
