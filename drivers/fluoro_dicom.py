"""Fluoroscopy intake: XA, XRF, DX/CR and secondary-capture DICOM images with their C-arm geometry.

Pixels become a float32 log-attenuation image (larger = more attenuation).
What the stored values mean is read from Pixel Intensity Relationship (0028,1040)
and its Sign (0028,1041) when the image states them (XA and XRF do): LIN values
follow the X-ray intensity and are converted with -log(I / I0), I0 from the
brightest 0.5 %; LOG values are used as they are when higher values mean less
intensity (Sign -1) and negated when they mean more (Sign +1). Without them:
the image says nothing of which way its values run (DISP: processed for display),
and displays differ: a radiograph's shows metal bright, most fluoroscopy
displays show it dark. Such an image is read both ways: first as its
photometric interpretation displays it metal bright (MONOCHROME1: values follow
the intensity, as LIN; MONOCHROME2: values rise with attenuation, mapped by
their 0.5-99.5 % range onto typical line integrals), and, in
``alternative_log``, the other way; the reading in which the markers are
identified is chosen downstream (``service/fluoro_polarity.py``). Either is an
approximation of the log attenuation: state LIN or LOG on such a C-arm.
Geometry comes from a calibrated projection-matrix JSON when given (it
overrides), else from the positioner attributes; anything missing or
inconsistent is refused with the attribute named. An enhanced XA / XRF image
states its geometry, intensity relationship and rescale per frame (or shared)
in its functional groups, which are read where the top level lacks them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pydicom
from numpy.typing import NDArray
from pydicom.errors import InvalidDicomError

from drillnav.registration.carm import CArmView, intensifier_distortion_sigma_px
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
    # How ``pixels_log`` was read from the stored values (Pixel Intensity Relationship, or the display's convention).
    reading: str = "stated by the file"
    # A file that does not say which way its values run (no LIN / LOG): the same pixels read the other way, and how;
    # None where the file says (``pixels_log`` is then its only reading).
    alternative_log: NDArray[np.float32] | None = None
    alternative_reading: str = ""

    @property
    def polarity_stated(self) -> bool:
        """Whether the file says which way its values follow the X-ray intensity (one reading only)."""
        return self.alternative_log is None

    def read_the_other_way(self) -> FluoroImage:
        """This image with its other reading (``alternative_log``) taken as its log attenuation, the first dropped."""
        if self.alternative_log is None:
            raise ValueError(f"{self.source_file}: the file states its polarity; there is no other reading")
        return replace(self, pixels_log=self.alternative_log, reading=self.alternative_reading, alternative_log=None, alternative_reading="")

    def read_as_first(self) -> FluoroImage:
        """This image with its first reading (``pixels_log``) kept, the other dropped."""
        return replace(self, alternative_log=None, alternative_reading="")


def _intensifier_sigma_px(ds, pixel_spacing_mm: tuple[float, ...]) -> float:
    """The distortion prior of an image from an image intensifier, 0 from a flat panel.

    An intensifier says so in X-Ray Receptor Type (0018,9420) = IMG_INTENSIFIER (enhanced XA/XRF) or, in the
    older XA/RF modules, by its Intensifier Size (0018,1162). Its images carry pincushion and S distortion
    unless dewarped, which the joint solve then estimates per view (:data:`IMAGE_INTENSIFIER_DISTORTION_PX`).
    A calibrated projection JSON says it itself (``distortion_sigma_px``; 0 for a dewarped image).
    """
    receptor = str(getattr(ds, "XRayReceptorType", "") or "").upper()
    if receptor == "IMG_INTENSIFIER" or (not receptor and getattr(ds, "IntensifierSize", None) not in (None, "")):
        # A size in mm at the detector: in this image's pixels (fewer on a binned read-out).
        return intensifier_distortion_sigma_px(pixel_spacing_mm[-1])  # the column spacing, as the detector's
    return 0.0


# Where an enhanced XA / XRF image keeps, per frame (or shared by all), what the older XA and XRF modules keep at the
# top level (PS3.3 C.8.19.6): the functional group's sequence for each attribute, and the enhanced attribute's own
# keyword where it differs (the source's distance to the isocentre: (0018,1111) in the older modules, (0018,9402) in the
# X-Ray Geometry Sequence).
_FUNCTIONAL_GROUP = {
    "PositionerPrimaryAngle": ("PositionerPositionSequence", "PositionerPrimaryAngle"),
    "PositionerSecondaryAngle": ("PositionerPositionSequence", "PositionerSecondaryAngle"),
    "DistanceSourceToDetector": ("XRayGeometrySequence", "DistanceSourceToDetector"),
    "DistanceSourceToPatient": ("XRayGeometrySequence", "DistanceSourceToIsocenter"),
    "ImagerPixelSpacing": ("FramePixelDataPropertiesSequence", "ImagerPixelSpacing"),
    "PixelIntensityRelationship": ("FramePixelDataPropertiesSequence", "PixelIntensityRelationship"),
    "PixelIntensityRelationshipSign": ("FramePixelDataPropertiesSequence", "PixelIntensityRelationshipSign"),
    "RescaleSlope": ("PixelValueTransformationSequence", "RescaleSlope"),
    "RescaleIntercept": ("PixelValueTransformationSequence", "RescaleIntercept"),
}
_TAGS = {
    "PositionerPrimaryAngle": "(0018,1510)",
    "PositionerSecondaryAngle": "(0018,1511)",
    "DistanceSourceToDetector": "(0018,1110)",
    "DistanceSourceToPatient": "(0018,1111)",
    "ImagerPixelSpacing": "(0018,1164)",
}


def _frame_attribute(ds, frame: int, keyword: str):
    """``keyword`` of frame ``frame`` (0-based): at the top level (the older XA and XRF modules), else in the frame's
    own functional group, else in the shared one (enhanced XA and XRF); None where absent."""
    value = getattr(ds, keyword, None)
    if value not in (None, "") or keyword not in _FUNCTIONAL_GROUP:
        return value
    sequence, enhanced = _FUNCTIONAL_GROUP[keyword]
    per_frame = getattr(ds, "PerFrameFunctionalGroupsSequence", None) or ()
    shared = getattr(ds, "SharedFunctionalGroupsSequence", None) or ()
    for groups in ([per_frame[frame]] if frame < len(per_frame) else []) + list(shared[:1]):
        items = getattr(groups, sequence, None) or ()
        value = getattr(items[0], enhanced, None) if items else None
        if value not in (None, ""):
            return value
    return None


def _geometry(ds, path: Path, rows: int, cols: int, projection: Path | None, frame: int = 0) -> tuple[CArmView, str]:
    if projection is not None:
        view = read_projection(projection)
        if (view.rows, view.columns) != (rows, cols):
            raise DicomGeometryMissing(f"{projection}: projection matrix is for {view.rows}x{view.columns} but {path.name} is {rows}x{cols}")
        return view, "projection-matrix"
    got = {key: _frame_attribute(ds, frame, key) for key in _TAGS}
    for key, tag in _TAGS.items():
        if got[key] in (None, ""):
            sequence, enhanced = _FUNCTIONAL_GROUP[key]
            where = f" (or {enhanced} in frame {frame + 1}'s {sequence})" if hasattr(ds, "PerFrameFunctionalGroupsSequence") or hasattr(ds, "SharedFunctionalGroupsSequence") else ""
            raise DicomGeometryMissing(f"{path.name}: missing {key} {tag}{where} and no projection-matrix JSON given")
    position = str(getattr(ds, "PatientPosition", "HFS") or "HFS")
    if position not in SUPINE:
        raise DicomGeometryMissing(f"{path.name}: PatientPosition {position} is not supported without a calibrated projection matrix (supine HFS/FFS only)")
    try:
        spacing = tuple(float(v) for v in got["ImagerPixelSpacing"])
        view = CArmView.from_positioner(
            distortion_sigma_px=_intensifier_sigma_px(ds, spacing),
            primary_deg=float(got["PositionerPrimaryAngle"]),
            secondary_deg=float(got["PositionerSecondaryAngle"]),
            source_to_detector_mm=float(got["DistanceSourceToDetector"]),
            source_to_isocenter_mm=float(got["DistanceSourceToPatient"]),
            pixel_spacing_mm=spacing,
            rows=rows,
            columns=cols,
        )
    except (TypeError, ValueError) as exc:
        raise DicomGeometryMissing(f"{path.name}: inconsistent positioner geometry: {exc}") from None
    return view, "positioner"


def _intensity_mapping(ds, name: str, frame: int = 0) -> str:
    """How stored values relate to the X-ray intensity: 'attenuation' (log, higher = less intensity), 'log intensity',
    'intensity', 'inverted intensity', or, where the file does not say, 'display' (MONOCHROME2) or 'display, low values
    bright' (MONOCHROME1).

    Pixel Intensity Relationship (0028,1040) LIN / LOG with its Sign (0028,1041): +1 lower values mean less
    intensity, -1 higher values mean less intensity (PS3.3 C.8.11.3). A stated relationship other than LIN or
    LOG (DISP: processed for display) falls back to the photometric interpretation.
    """
    relation = str(_frame_attribute(ds, frame, "PixelIntensityRelationship") or "").strip().upper()
    raw_sign = _frame_attribute(ds, frame, "PixelIntensityRelationshipSign")
    try:
        sign = None if raw_sign in (None, "") else int(raw_sign)
    except (TypeError, ValueError):
        raise DicomUnreadable(f"{name}: Pixel Intensity Relationship Sign (0028,1041) is {raw_sign!r}, expected +1 or -1") from None
    if sign not in (None, 1, -1):
        raise DicomUnreadable(f"{name}: Pixel Intensity Relationship Sign (0028,1041) is {sign}, expected +1 or -1")
    if relation == "LOG":
        # Without a sign, the older convention: log-processed as attenuation (higher = less intensity).
        return "log intensity" if sign == 1 else "attenuation"
    if relation == "LIN":
        return "inverted intensity" if sign == -1 else "intensity"
    if str(getattr(ds, "PhotometricInterpretation", "MONOCHROME2")) == "MONOCHROME1":
        return "display, low values bright"
    return "display"


def _intensity_to_log(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """Values (rows, columns) that follow the detector's intensity (low behind bone) as log attenuation: -log(I / I0),
    I0 from the brightest 0.5 %."""
    i0 = np.percentile(values, 99.5)
    return -np.log(np.clip(values, 1e-3, None) / max(i0, 1e-3))


def _range_to_log(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """Values (rows, columns) that rise with attenuation, of unknown scale: their 0.5-99.5 % range mapped onto 0-6,
    typical line integrals."""
    lo, hi = np.percentile(values, [0.5, 99.5])
    return (values - lo) / max(hi - lo, 1e-6) * 6.0


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
    out = []
    # An enhanced image states its geometry, intensity relationship and rescale per frame; the older modules once for all.
    per_frame = hasattr(ds, "PerFrameFunctionalGroupsSequence")
    for i, frame in enumerate(frames):
        if i == 0 or per_frame:
            view, geometry_source = _geometry(ds, p, rows, cols, Path(projection) if projection else None, frame=i)
            try:
                slope = float(_frame_attribute(ds, i, "RescaleSlope") or 1.0)
                intercept = float(_frame_attribute(ds, i, "RescaleIntercept") or 0.0)
            except (TypeError, ValueError) as exc:
                raise DicomUnreadable(f"{p.name}: Rescale Slope (0028,1053) / Intercept (0028,1052) of frame {i + 1} is not a number ({exc})") from None
            mapping = _intensity_mapping(ds, p.name, frame=i)
            try:
                view_name = f"p{float(_frame_attribute(ds, i, 'PositionerPrimaryAngle')):+.0f}s{float(_frame_attribute(ds, i, 'PositionerSecondaryAngle')):+.0f}"
            except (TypeError, ValueError):
                view_name = p.stem.replace(".", "_")  # every frame of one file without angles: one view, the newest frame standing
        values = frame * slope + intercept
        reading, alternative, alternative_reading = "stated by the file", None, ""
        if mapping == "intensity":
            values = _intensity_to_log(values)
        elif mapping == "inverted intensity":
            # Values fall as the intensity rises: I = (the largest value) - value.
            values = _intensity_to_log(values.max() - values)
        elif mapping == "log intensity":
            # log(I) up to a gain and an offset: negated, and the brightest 0.5 % taken as no attenuation.
            values = np.percentile(values, 99.5) - values
        elif mapping in ("display", "display, low values bright"):
            # Processed for display, of unknown scale and polarity: read as its photometric interpretation shows metal
            # bright, and the other way (-log of a display's gamma is a gain on the log attenuation).
            as_intensity, as_attenuation = _intensity_to_log(values), _range_to_log(values)
            if mapping == "display":
                values, reading = as_attenuation, "metal bright (MONOCHROME2: values rise with attenuation)"
                alternative, alternative_reading = as_intensity, "metal dark (values follow the intensity, as LIN)"
            else:
                values, reading = as_intensity, "metal bright (MONOCHROME1: values follow the intensity, as LIN)"
                alternative, alternative_reading = as_attenuation, "metal dark (values rise with attenuation)"
            alternative = alternative.astype(np.float32)
        out.append(FluoroImage(pixels_log=values.astype(np.float32), view=view, source_file=str(p), sop_class=SUPPORTED_SOP_CLASSES[sop], frame_index=i,
                               geometry_source=geometry_source, view_name=view_name, reading=reading, alternative_log=alternative,
                               alternative_reading=alternative_reading))
    return out
