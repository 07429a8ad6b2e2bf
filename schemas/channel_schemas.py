"""The schema of every drillnav channel, as MCAP and Foxglove want it: one home for the recorder and the live bridge."""

from __future__ import annotations

import json
from dataclasses import dataclass

from .calibration_message import CALIBRATION_SCHEMA
from .messages import JSON_SCHEMAS, protobuf_schema
from .protobuf_types import PROTOBUF_TYPES
from .topics import Encoding, Topic

__all__ = ["ChannelSchema", "channel_schema"]


@dataclass(frozen=True, kw_only=True)
class ChannelSchema:
    name: str              # e.g. "foxglove.FrameTransform", "drillnav.DrillAxis"
    encoding: str          # the schema's encoding: "protobuf" (a FileDescriptorSet) or "jsonschema"
    message_encoding: str  # the messages' encoding: "protobuf" or "json"
    data: bytes


def channel_schema(topic: Topic) -> ChannelSchema:
    """The schema record of ``topic``; raises KeyError for a schema name no module defines."""
    if topic.encoding is Encoding.PROTOBUF:
        return ChannelSchema(name=topic.schema_name, encoding="protobuf", message_encoding="protobuf",
                             data=protobuf_schema(PROTOBUF_TYPES[topic.schema_name]))
    doc = CALIBRATION_SCHEMA if topic.schema_name == "drillnav.Calibration" else JSON_SCHEMAS[topic.schema_name]
    return ChannelSchema(name=topic.schema_name, encoding="jsonschema", message_encoding="json", data=json.dumps(doc).encode())
