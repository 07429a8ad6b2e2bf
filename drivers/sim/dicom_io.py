"""The twin C-arm's DICOM output: XA images with the positioner attributes a C-arm sends."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, XRayAngiographicImageStorage, generate_uid

__all__ = ["write_xa", "LOG_SCALE"]

# Stored value = log attenuation x LOG_SCALE (RescaleSlope = 1 / LOG_SCALE): a log-processed, MONOCHROME2 image.
LOG_SCALE = 4000.0


def write_xa(
    path: str | Path,
    image_log: NDArray[np.float32],
    *,
    primary_deg: float,
    secondary_deg: float,
    source_to_detector_mm: float,
    source_to_isocenter_mm: float,
    pixel_spacing_mm: tuple[float, float],
    study_uid: str,
    series_uid: str,
    instance_number: int,
    patient_id: str = "TWIN",
) -> Path:
    """Write one single-frame XA image; returns the path."""
    path = Path(path)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = XRayAngiographicImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
    now = dt.datetime.now(dt.timezone.utc)
    ds.SOPClassUID = XRayAngiographicImageStorage
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID, ds.SeriesInstanceUID = study_uid, series_uid
    ds.Modality = "XA"
    ds.Manufacturer = "drillnav digital twin"
    ds.PatientName, ds.PatientID = "Twin^Pelvis", patient_id
    ds.StudyDate = ds.ContentDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.ContentTime = now.strftime("%H%M%S")
    ds.InstanceNumber = instance_number
    ds.PatientPosition = "HFS"
    ds.PositionerPrimaryAngle = f"{primary_deg:.2f}"
    ds.PositionerSecondaryAngle = f"{secondary_deg:.2f}"
    ds.DistanceSourceToDetector = f"{source_to_detector_mm:.1f}"
    ds.DistanceSourceToPatient = f"{source_to_isocenter_mm:.1f}"
    ds.ImagerPixelSpacing = [f"{pixel_spacing_mm[0]:.4f}", f"{pixel_spacing_mm[1]:.4f}"]
    ds.KVP = "75"
    ds.ExposureTime = "10"
    ds.XRayTubeCurrent = "5"
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = image_log.shape
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.RescaleIntercept, ds.RescaleSlope = "0", f"{1.0 / LOG_SCALE:.8f}"
    ds.RescaleType = "US"
    ds.PixelData = np.clip(np.round(image_log * LOG_SCALE), 0, 65535).astype(np.uint16).tobytes()
    ds.save_as(str(path), enforce_file_format=True)
    return path
