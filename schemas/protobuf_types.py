"""Every protobuf schema name drillnav publishes, mapped to its message class (the recorder and the Foxglove bridge register them)."""

from __future__ import annotations

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

__all__ = ["PROTOBUF_TYPES"]

PROTOBUF_TYPES = {
    "foxglove.CompressedImage": CompressedImage,
    "foxglove.FrameTransform": FrameTransform,
    "foxglove.SceneUpdate": SceneUpdate,
    "foxglove.CameraCalibration": CameraCalibration,
    "foxglove.ImageAnnotations": ImageAnnotations,
    "foxglove.Log": Log,
}
