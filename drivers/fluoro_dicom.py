"""Fluoroscopy intake: XA, XRF, DX/CR and secondary-capture DICOM images with their C-arm geometry.

Pixels become a float32 log-attenuation image (larger = more attenuation).
MONOCHROME1 values follow detector intensity and are converted with
-log(I / I0), I0 estimated from the brightest 0.5 %; log-processed
MONOCHROME2 images (the twin's, or Pixel Intensity Relationship LOG) are used
as they are; other MONOCHROME2 images are mapped by their 0.5-99.5 % range
onto typical line integrals (an approximation: calibrate such a C-arm).
Geometry comes from a calibrated projection-matrix JSON when given (it
overrides), else from the positioner attributes; anything missing or
inconsistent is refused with the attribute named.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
from numpy.typing import NDArray
from pydicom.errors import InvalidDicomError

from drillnav.registration.carm import IMAGE_INTENSIFIER_DISTORTION_PX, CArmView
from drillnav.registration.errors import DrillnavError
from drillnav.schemas.projection import read_projection

__all__ = ["FluoroImage", "DicomUnreadable", "DicomGeometryMissing", "read_fluoro", "SUPPORTED_SOP_CLASSES"]

SUPPORTED_SOP_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.12.1": "XA",
    "1.2.840.10008.5.1.4.1.1.12.1.1": "Enhanced XA",
    "1.2.840.10008.5.1.4.1.1.12.2": "XRF",
    "1.2.840.10008.5.1.4.1.1.1.1": "DX for presentation",
    "1.2.840.10008.5.1.4.1.1.1.1.1": "DX for processing",
    "1.2.840.10008.5.1.4.1.1.1": "CR",
    "1.2.840.10008.5.1.4.1.1.7": "Secondary Capture",
    "1.2.840.10008.5.1.4.1.1.7.2": "Multi-frame Grayscale Byte SC",
    "1.2.840.10008.5.1.4.1.1.7.3": "Multi-frame Grayscale Word SC",
}
SUPINE = {"HFS", "FFS"}


class DicomUnreadable(DrillnavError):
    """The file is not DICOM, is truncated, or has no usable pixel data."""


class DicomGeometryMissing(DrillnavError):
    """The C-arm geometry of an image cannot be established; names the attribute."""


@dataclass(frozen=True, kw_only=True)
class FluoroImage:
    pixels_log: NDArray[np.float32]
    view: CArmView
    source_file: str
    sop_class: str
    frame_index: int
    geometry_source: str  # "projection-matrix" or "positioner"
    view_name: str  # from the positioner angles (e.g. "p+0s-25"), else the file name


def _intensifier_sigma_px(ds) -> float:
    """The distortion prior of an image from an image intensifier, 0 from a flat panel.

    An intensifier says so in X-Ray Receptor Type (0018,9420) = IMG_INTENSIFIER (enhanced XA/XRF) or, in the
    older XA/RF modules, by its Intensifier Size (0018,1162). Its images carry pincushion and S distortion
    unless dewarped, which the joint solve then estimates per view (:data:`IMAGE_INTENSIFIER_DISTORTION_PX`).
    A calibrated projection JSON says it itself (``distortion_sigma_px``; 0 for a dewarped image).
    """
    receptor = str(getattr(ds, "XRayReceptorType", "") or "").upper()
    if receptor == "IMG_INTENSIFIER" or (not receptor and getattr(ds, "IntensifierSize", None) not in (None, "")):
        return IMAGE_INTENSIFIER_DISTORTION_PX
    return 0.0


def _geometry(ds, path: Path, rows: int, cols: int, projection: Path | None) -> tuple[CArmView, str]:
    if projection is not None:
        view = read_projection(projection)
        if (view.rows, view.columns) != (rows, cols):
            raise DicomGeometryMissing(f"{projection}: projection matrix is for {view.rows}x{view.columns} but {path.name} is {rows}x{cols}")
        return view, "projection-matrix"
    needed = {
        "PositionerPrimaryAngle": "(0018,1510)",
        "PositionerSecondaryAngle": "(0018,1511)",
        "DistanceSourceToDetector": "(0018,1110)",
        "DistanceSourceToPatient": "(0018,1111)",
        "ImagerPixelSpacing": "(0018,1164)",
    }
    for key, tag in needed.items():
        if getattr(ds, key, None) in (None, ""):
            raise DicomGeometryMissing(f"{path.name}: missing {key} {tag} and no projection-matrix JSON given")
    position = str(getattr(ds, "PatientPosition", "HFS") or "HFS")
    if position not in SUPINE:
        raise DicomGeometryMissing(f"{path.name}: PatientPosition {position} is not supported without a calibrated projection matrix (supine HFS/FFS only)")
    try:
        view = CArmView.from_positioner(
            distortion_sigma_px=_intensifier_sigma_px(ds),
            primary_deg=float(ds.PositionerPrimaryAngle),
            secondary_deg=float(ds.PositionerSecondaryAngle),
            source_to_detector_mm=float(ds.DistanceSourceToDetector),
            source_to_isocenter_mm=float(ds.DistanceSourceToPatient),
            pixel_spacing_mm=tuple(float(v) for v in ds.ImagerPixelSpacing),
            rows=rows,
            columns=cols,
        )
    except ValueError as exc:
        raise DicomGeometryMissing(f"{path.name}: inconsistent positioner geometry: {exc}") from None
    return view, "positioner"


def read_fluoro(path: str | Path, *, projection: str | Path | None = None) -> list[FluoroImage]:
    """Every frame of a fluoroscopy DICOM file as :class:`FluoroImage` (one per frame).

    ``projection`` defaults to ``<file>.json`` beside the image when that exists.
    """
    p = Path(path)
    if not p.is_file():
        raise DicomUnreadable(f"{p}: no such file")
    try:
        ds = pydicom.dcmread(str(p))
    except (InvalidDicomError, EOFError, OSError, ValueError) as exc:
        raise DicomUnreadable(f"{p.name}: not a readable DICOM file ({exc})") from None
    sop = str(getattr(ds, "SOPClassUID", ""))
    if sop not in SUPPORTED_SOP_CLASSES:
        raise DicomUnreadable(f"{p.name}: SOP class {sop or '(none)'} is not a fluoroscopy or radiography image")
    try:
        arr = ds.pixel_array.astype(np.float64)
    except Exception as exc:  # pydicom raises many types for broken pixel data
        raise DicomUnreadable(f"{p.name}: pixel data cannot be decoded ({type(exc).__name__}: {exc})") from None
    frames = arr if arr.ndim == 3 and int(getattr(ds, "NumberOfFrames", 1) or 1) > 1 else arr[None]
    if frames.ndim != 3 or int(getattr(ds, "SamplesPerPixel", 1)) != 1:
        raise DicomUnreadable(f"{p.name}: expected grayscale pixel data, got shape {arr.shape}")
    rows, cols = frames.shape[1:]
    if projection is None and p.with_suffix(".json").is_file():
        projection = p.with_suffix(".json")
    view, geometry_source = _geometry(ds, p, rows, cols, Path(projection) if projection else None)
    slope = float(getattr(ds, "RescaleSlope", 1.0) or 1.0)
    intercept = float(getattr(ds, "RescaleIntercept", 0.0) or 0.0)
    photometric = str(getattr(ds, "PhotometricInterpretation", "MONOCHROME2"))
    log_processed = str(getattr(ds, "Manufacturer", "")) == "drillnav digital twin" or "LOG" in str(getattr(ds, "PixelIntensityRelationship", "")).upper()
    try:
        view_name = f"p{float(ds.PositionerPrimaryAngle):+.0f}s{float(ds.PositionerSecondaryAngle):+.0f}"
    except (AttributeError, TypeError, ValueError):
        view_name = p.stem.replace(".", "_")
    out = []
    for i, frame in enumerate(frames):
        values = frame * slope + intercept
        if photometric == "MONOCHROME1":
            # Displayed white at the minimum: values follow detector intensity (low behind bone).
            i0 = np.percentile(values, 99.5)
            values = -np.log(np.clip(values, 1e-3, None) / max(i0, 1e-3))
        elif not log_processed:
            # A processed MONOCHROME2 image of unknown scale: map its range onto typical line integrals.
            lo, hi = np.percentile(values, [0.5, 99.5])
            values = (values - lo) / max(hi - lo, 1e-6) * 6.0
        out.append(FluoroImage(pixels_log=values.astype(np.float32), view=view, source_file=str(p), sop_class=SUPPORTED_SOP_CLASSES[sop], frame_index=i, geometry_source=geometry_source, view_name=view_name))
    return out
