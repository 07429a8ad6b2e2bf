"""The twin's DICOM output: the C-arm's XA images with their positioner attributes, and the preoperative CT series."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, XRayAngiographicImageStorage, generate_uid

from drillnav.registration.volume import Volume

__all__ = ["write_xa", "write_ct_series", "LOG_SCALE"]

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
    image_intensifier: bool = False,
) -> Path:
    """Write one single-frame XA image; returns the path.

    ``image_intensifier``: the C-arm's receptor is an (uncorrected) image intensifier, which the image says in
    X-Ray Receptor Type (0018,9420) and Intensifier Size (0018,1162); else a flat panel (DIGITAL_DETECTOR).
    """
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
    ds.XRayReceptorType = "IMG_INTENSIFIER" if image_intensifier else "DIGITAL_DETECTOR"
    if image_intensifier:
        ds.IntensifierSize = f"{max(image_log.shape) * pixel_spacing_mm[0]:.1f}"
    ds.KVP = "75"
    ds.ExposureTime = "10"
    ds.XRayTubeCurrent = "5"
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    # Log attenuation: higher values mean less X-ray intensity (PS3.3 C.8.11.3).
    ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign = "LOG", -1
    ds.Rows, ds.Columns = image_log.shape
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.RescaleIntercept, ds.RescaleSlope = "0", f"{1.0 / LOG_SCALE:.8f}"
    ds.RescaleType = "US"
    ds.PixelData = np.clip(np.round(image_log * LOG_SCALE), 0, 65535).astype(np.uint16).tobytes()
    ds.save_as(str(path), enforce_file_format=True)
    return path


def write_ct_series(folder: str | Path, volume: Volume, *, patient_id: str = "TWIN", series_description: str = "twin pelvis CT") -> list[Path]:
    """Write ``volume`` (int16 HU, axial slices along +k) as a CT Image Storage series, one file per slice."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    a = volume.patient_from_voxel
    spacing = volume.spacing_mm
    row_dir, col_dir = a[:3, 0] / spacing[0], a[:3, 1] / spacing[1]
    study, series, frame = generate_uid(), generate_uid(), generate_uid()
    now = dt.datetime.now(dt.timezone.utc)
    data = np.asarray(volume.data)
    if data.dtype != np.int16:
        data = np.clip(np.rint(data), -32768, 32767).astype(np.int16)
    paths = []
    for k in range(data.shape[0]):
        path = folder / f"CT{k + 1:04d}.dcm"
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
        ds.Modality, ds.Manufacturer, ds.SeriesDescription = "CT", "drillnav digital twin", series_description
        ds.PatientName, ds.PatientID, ds.PatientPosition = "Twin^Pelvis", patient_id, "HFS"
        ds.StudyDate = ds.SeriesDate = now.strftime("%Y%m%d")
        ds.StudyTime = ds.SeriesTime = now.strftime("%H%M%S")
        ds.SeriesNumber, ds.InstanceNumber = 1, k + 1
        ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
        ds.ImagePositionPatient = [f"{v:.4f}" for v in a[:3, :3] @ [0.0, 0.0, k] + a[:3, 3]]
        ds.ImageOrientationPatient = [f"{v:.6f}" for v in (*row_dir, *col_dir)]
        ds.PixelSpacing = [f"{spacing[1]:.4f}", f"{spacing[0]:.4f}"]  # row spacing (between rows), column spacing
        ds.SliceThickness = f"{spacing[2]:.4f}"
        ds.KVP = "120"
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.Rows, ds.Columns = data.shape[1], data.shape[2]
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "0", "1", "HU"
        ds.WindowCenter, ds.WindowWidth = "300", "1500"
        ds.PixelData = np.ascontiguousarray(data[k]).tobytes()
        ds.save_as(str(path), enforce_file_format=True)
        paths.append(path)
    return paths
