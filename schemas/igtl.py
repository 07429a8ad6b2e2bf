"""OpenIGTLink messages for 3D Slicer (OpenIGTLinkIF), in Slicer's RAS world.

drillnav's frames C (C-arm) and V (CT) have DICOM LPS axes (docs/geometry.md);
Slicer's world is RAS, so every transform whose target is C or V is sent as
``ras_from_lps @ target_from_source`` and, when its source is C or V too, with
``@ lps_from_ras`` on the right. The drill frame D is the drill camera's own
(OpenCV) frame, not a patient frame: the drill model is sent in D's coordinates
as they are and placed by ``DrillToCArm``. Lengths stay millimetres.

Device names follow PLUS's ``<From>To<To>`` convention: ``DrillToCArm`` maps
drill points into the C-arm frame, i.e. it is RAS-``carm_from_drill``.

The byte layout is pyigtl's (``pyigtl.TransformMessage``, ``ImageMessage``,
``StringMessage``, ``PolyDataMessage``): one tested implementation of the
protocol's header, CRC-64 and bodies.
"""

from __future__ import annotations

import numpy as np
import pyigtl
from numpy.typing import ArrayLike, NDArray

from drillnav.registration.carm import CArmView
from drillnav.registration.line import Line3D
from drillnav.registration.transforms import invert
from drillnav.registration.volume import Volume

__all__ = [
    "RAS_FROM_LPS",
    "DEVICE_DRILL_TO_CARM",
    "DEVICE_DRILL_TO_CT",
    "DEVICE_CT_TO_CARM",
    "DEVICE_DRILL_MODEL",
    "DEVICE_STATE",
    "DEVICE_ALERT",
    "DEVICE_CT",
    "ras_transform",
    "transform_message",
    "fluoro_image_lps_from_ijk",
    "fluoro_image_message",
    "ct_image_message",
    "drill_cylinder",
    "drill_model_message",
    "string_message",
]

# LPS and RAS differ by the sign of x and y; the matrix is its own inverse.
RAS_FROM_LPS: NDArray[np.float64] = np.diag([-1.0, -1.0, 1.0, 1.0])

DEVICE_DRILL_TO_CARM = "DrillToCArm"
DEVICE_DRILL_TO_CT = "DrillToCT"
DEVICE_CT_TO_CARM = "CTToCArm"
DEVICE_DRILL_MODEL = "DrillModel"
DEVICE_STATE = "RegistrationState"
DEVICE_ALERT = "Alert"
DEVICE_CT = "CT"


def ras_transform(target_from_source: ArrayLike, *, source_is_patient: bool) -> NDArray[np.float64]:
    """A 4x4 whose target is an LPS frame (C or V), expressed for Slicer's RAS world.

    ``source_is_patient``: the source frame is LPS too (C or V) and is converted as well;
    False for the drill frame D, whose coordinates Slicer takes as they are.
    """
    m = np.asarray(target_from_source, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"a transform must be a finite 4x4 matrix, got shape {m.shape}")
    out = RAS_FROM_LPS @ m
    return out @ RAS_FROM_LPS if source_is_patient else out


def _seconds(stamp_ns: int) -> float:
    # pyigtl writes the header's 32.32 fixed-point stamp from float seconds: ~0.2 us resolution today.
    return int(stamp_ns) / 1e9


def transform_message(device: str, target_from_source_ras: ArrayLike, *, stamp_ns: int) -> pyigtl.TransformMessage:
    return pyigtl.TransformMessage(np.asarray(target_from_source_ras, dtype=np.float64), timestamp=_seconds(stamp_ns), device_name=device)


def fluoro_image_lps_from_ijk(view: CArmView) -> NDArray[np.float64]:
    """Where each pixel of a view lies on its detector, in C (LPS, mm): a 4x4 from (column, row, 0).

    The detector is the plane at the source-to-detector distance along the central ray:
    ``x_S = f * K^-1 (u, v, 1)`` in the source frame S, then ``carm_from_source``. The third
    column is the unit beam direction so the 2D image has a proper 3D orientation.
    """
    k, source_from_carm = view.decompose()
    carm_from_source = invert(source_from_carm)
    f_mm = abs(float(k[0, 0])) * view.pixel_spacing_mm[1]  # |K[0, 0]| = f / column spacing (negative: a mirrored detector)
    kinv = np.linalg.inv(k)
    detector_from_pixel = np.eye(4)
    detector_from_pixel[:3, 0] = f_mm * kinv[:, 0]
    detector_from_pixel[:3, 1] = f_mm * kinv[:, 1]
    detector_from_pixel[:3, 2] = [0.0, 0.0, 1.0]
    detector_from_pixel[:3, 3] = f_mm * kinv[:, 2]
    return carm_from_source @ detector_from_pixel


def fluoro_image_message(image_log: NDArray[np.float32], view: CArmView, *, device: str, stamp_ns: int) -> pyigtl.ImageMessage:
    """A shot as an IMAGE: float32 log attenuation, placed on its detector in RAS."""
    img = np.asarray(image_log, dtype=np.float32)
    if img.shape != (view.rows, view.columns):
        raise ValueError(f"image is {img.shape}, the view says {view.rows}x{view.columns}")
    ras_from_ijk = RAS_FROM_LPS @ fluoro_image_lps_from_ijk(view)
    # pyigtl takes voxels as (k, j, i): one slice of rows x columns.
    return pyigtl.ImageMessage(img[np.newaxis], ijk_to_world_matrix=ras_from_ijk, world_coordinate_system="ras",
                               timestamp=_seconds(stamp_ns), device_name=device)


def ct_image_message(volume: Volume, *, stamp_ns: int) -> pyigtl.ImageMessage:
    """The CT as an IMAGE in RAS: HU rounded to int16 (half of float32's bytes; HU are integers as stored in DICOM)."""
    hu = np.clip(np.round(np.asarray(volume.data, dtype=np.float32)), -32768, 32767).astype(np.int16)
    if max(hu.shape) > 65535:
        raise ValueError(f"OpenIGTLink sizes are 16-bit; the CT is {hu.shape}")
    # Volume.data is (slice, row, column) = (k, j, i), as pyigtl wants it; patient_from_voxel maps (i, j, k) to LPS.
    return pyigtl.ImageMessage(hu, ijk_to_world_matrix=RAS_FROM_LPS @ volume.patient_from_voxel, world_coordinate_system="ras",
                               timestamp=_seconds(stamp_ns), device_name=DEVICE_CT)


def drill_cylinder(axis_drill: Line3D, *, start_mm: float, length_mm: float, radius_mm: float, sides: int = 16) -> tuple[NDArray[np.float32], NDArray[np.uint32]]:
    """A closed cylinder along the drill axis in D: (points (2*sides+2, 3) mm, VTK polygon cell array).

    It runs from ``start_mm`` to ``start_mm + length_mm`` along the axis from its point,
    so with the twin's numbers it is the K-wire from the chuck forwards.
    """
    if length_mm <= 0 or radius_mm <= 0 or sides < 3:
        raise ValueError(f"the drill model needs length > 0, radius > 0 and >= 3 sides, got {length_mm}, {radius_mm}, {sides}")
    d = axis_drill.direction
    u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    angles = 2 * np.pi * np.arange(sides) / sides
    ring = radius_mm * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
    a, b = axis_drill.at(start_mm), axis_drill.at(start_mm + length_mm)
    points = np.vstack([a + ring, b + ring, a, b]).astype(np.float32)
    cells: list[int] = []
    for i in range(sides):
        j = (i + 1) % sides
        cells += [4, i, j, sides + j, sides + i]           # side quad
        cells += [3, 2 * sides, j, i]                       # start cap
        cells += [3, 2 * sides + 1, sides + i, sides + j]   # end cap
    return points, np.asarray(cells, dtype=np.uint32)


def drill_model_message(axis_drill: Line3D, *, start_mm: float, length_mm: float, radius_mm: float, stamp_ns: int) -> pyigtl.PolyDataMessage:
    points, polygons = drill_cylinder(axis_drill, start_mm=start_mm, length_mm=length_mm, radius_mm=radius_mm)
    return pyigtl.PolyDataMessage(points=points, polygons=polygons, timestamp=_seconds(stamp_ns), device_name=DEVICE_DRILL_MODEL)


def string_message(device: str, text: str, *, stamp_ns: int) -> pyigtl.StringMessage:
    return pyigtl.StringMessage(text, timestamp=_seconds(stamp_ns), device_name=device)
