"""The drill axis for ROS 2: ``geometry_msgs/msg/PoseStamped`` on zenoh exactly as ``rmw_zenoh`` publishes it.

A ROS 2 node using ``rmw_zenoh_cpp`` (``RMW_IMPLEMENTATION=rmw_zenoh_cpp``) on the
same zenoh network subscribes to the topic (default ``/drillnav/drill_axis``) like
any other: the bridge declares a node and a publisher in the ROS graph (liveliness
tokens) and puts one CDR message, with rmw_zenoh's attachment, per drill axis.
Formats: :mod:`drillnav.schemas.ros2`; set-up and limits: docs/ros2.md.
"""

from __future__ import annotations

import threading

import zenoh

from drillnav.registration.line import Line3D
from drillnav.schemas import messages as msg
from drillnav.schemas import ros2
from drillnav.schemas.topics import key

__all__ = ["Ros2Bridge"]


class Ros2Bridge:
    """A context manager: the tokens, the publisher and the subscription exist between ``__enter__`` and ``close``.

    Parameters
    ----------
    session, prefix : the zenoh session and drillnav's key prefix.
    domain_id : ROS_DOMAIN_ID of the ROS 2 side.
    topic : absolute ROS topic name of the PoseStamped stream.
    node : ROS node name the bridge appears as (namespace "/").
    frame_id : header.frame_id ("carm": the C-arm frame, patient LPS at the isocentre, metres).
    """

    def __init__(self, *, session: zenoh.Session, prefix: str, domain_id: int = 0, topic: str = "/drillnav/drill_axis",
                 node: str = "drillnav", frame_id: str = "carm") -> None:
        if not 0 <= domain_id <= 232:
            raise ValueError(f"ROS domain id must be 0..232, got {domain_id}")
        self.session, self.prefix, self.domain_id, self.topic, self.node, self.frame_id = session, prefix, domain_id, topic, node, frame_id
        self.key = ros2.topic_key(domain_id, topic)
        zid = str(session.info.zid())
        self.node_token_key = ros2.node_token(domain_id=domain_id, zid=zid, node_id=0, namespace="/", node=node)
        self.publisher_token_key = ros2.publisher_token(domain_id=domain_id, zid=zid, node_id=0, entity_id=1, namespace="/", node=node, topic=topic)
        self.gid = ros2.publisher_gid(self.publisher_token_key)
        self.published = 0
        self.decode_errors = 0
        self._lock = threading.Lock()
        self._sequence = 0
        self._tokens: list = []
        self._publisher = None
        self._sub = None

    def __enter__(self) -> "Ros2Bridge":
        try:
            liveliness = self.session.liveliness()
            self._tokens = [liveliness.declare_token(self.node_token_key), liveliness.declare_token(self.publisher_token_key)]
            self._publisher = self.session.declare_publisher(self.key)
            self._sub = self.session.declare_subscriber(key(self.prefix, "axis_carm"), self._on_axis)
        except Exception:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        if self._publisher is not None:
            self._publisher.undeclare()
            self._publisher = None
        for t in self._tokens:
            t.undeclare()  # the ROS graph sees the node and its publisher leave
        self._tokens = []

    def _on_axis(self, sample: zenoh.Sample) -> None:
        try:
            doc = msg.decode_json(sample.payload.to_bytes())
            stamp = int(doc["source_frame_stamp_ns"])
            payload = ros2.axis_pose_stamped(Line3D(point_mm=doc["point_mm"], direction=doc["direction"]), stamp_ns=stamp, frame_id=self.frame_id)
        except (KeyError, TypeError, ValueError):
            self.decode_errors += 1
            return
        with self._lock:
            self._sequence += 1  # rmw_zenoh counts from 1
            attachment = ros2.attachment(sequence_number=self._sequence, source_timestamp_ns=stamp, gid=self.gid)
            publisher = self._publisher
        if publisher is not None:
            publisher.put(payload, attachment=attachment)
            self.published += 1
