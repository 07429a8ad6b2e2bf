"""CT intake: a DICOM series from a folder, or a NIfTI file, as a HU volume with ``patient_from_voxel``.

DICOM: the slices of one series are sorted by their position along the slice
normal (any orientation); duplicate or missing slices, mixed series, differing
orientations or sizes and unreadable files are refused with the files named;
slightly uneven spacing is resampled onto the median spacing with a
:class:`CtSpacingWarning`. Stored values are rescaled to HU.

NIfTI (``.nii``, ``.nii.gz``, read by nibabel): the sform/qform affine (RAS)
is turned into LPS so that V is the DICOM patient frame either way.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pydicom
from numpy.typing import NDArray
from pydicom.errors import InvalidDicomError

from drillnav.registration.errors import DrillnavError
from drillnav.registration.volume import Volume

__all__ = ["CtUnreadable", "CtSeriesBroken", "CtSpacingWarning", "read_ct", "read_ct_series", "read_nifti"]

CT_LIKE_SOP_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.2": "CT",
    "1.2.840.10008.5.1.4.1.1.2.1": "Enhanced CT",
    "1.2.840.10008.5.1.4.1.1.2.2": "Legacy Converted Enhanced CT",
}
SPACING_TOLERANCE = 0.02  # relative: gaps within 2 % of the median are "even"


class CtUnreadable(DrillnavError):
    """The CT path does not exist, is not DICOM/NIfTI, or a file in it cannot be read."""


class CtSeriesBroken(DrillnavError):
    """The slices do not form one complete, consistent volume; names the files."""


class CtSpacingWarning(UserWarning):
    """The slice spacing was uneven and the volume was resampled."""


def read_ct(path: str | Path, *, series_uid: str | None = None) -> Volume:
    """A folder of DICOM files, or a ``.nii``/``.nii.gz`` file."""
    p = Path(path)
    if not p.exists():
        raise CtUnreadable(f"{p}: no such file or folder")
    if p.is_dir():
        return read_ct_series(p, series_uid=series_uid)
    if p.name.endswith((".nii", ".nii.gz")):
        return read_nifti(p)
    raise CtUnreadable(f"{p}: give a folder holding one DICOM CT series, or a .nii/.nii.gz file")


def _names(paths: list[Path], limit: int = 6) -> str:
    shown = ", ".join(p.name for p in paths[:limit])
    return shown + (f" and {len(paths) - limit} more" if len(paths) > limit else "")


def read_ct_series(folder: str | Path, *, series_uid: str | None = None) -> Volume:
    folder = Path(folder)
    files = sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith(".") and f.name.upper() != "DICOMDIR")
    if not files:
        raise CtUnreadable(f"{folder}: the folder holds no files")
    datasets, unreadable = [], []
    for f in files:
        try:
            datasets.append((f, pydicom.dcmread(f)))
        except (InvalidDicomError, OSError, ValueError, EOFError) as exc:
            unreadable.append((f, exc))
    if unreadable:
        raise CtUnreadable(f"{folder}: {len(unreadable)} file(s) are not readable DICOM: {_names([f for f, _ in unreadable])} ({unreadable[0][1]})")
    by_series: dict[str, list[tuple[Path, pydicom.Dataset]]] = {}
    for f, ds in datasets:
        by_series.setdefault(str(getattr(ds, "SeriesInstanceUID", "?")), []).append((f, ds))
    if series_uid is not None:
        if series_uid not in by_series:
            raise CtSeriesBroken(f"{folder}: no series {series_uid}; found {', '.join(by_series)}")
        chosen = by_series[series_uid]
    elif len(by_series) > 1:
        parts = "; ".join(f"{uid} ({len(v)} files, e.g. {v[0][0].name}, {getattr(v[0][1], 'Modality', '?')} '{getattr(v[0][1], 'SeriesDescription', '')}')" for uid, v in by_series.items())
        raise CtSeriesBroken(f"{folder}: mixed series, choose one: {parts}")
    else:
        chosen = next(iter(by_series.values()))
    not_ct = [f for f, ds in chosen if str(getattr(ds, "SOPClassUID", "")) not in CT_LIKE_SOP_CLASSES]
    if not_ct:
        raise CtSeriesBroken(f"{folder}: not CT images: {_names(not_ct)} (SOP class {getattr(dict(chosen)[not_ct[0]], 'SOPClassUID', 'missing')})")
    if len(chosen) < 2:
        raise CtSeriesBroken(f"{folder}: a volume needs at least 2 slices, found {len(chosen)} ({_names([f for f, _ in chosen])})")
    for key, tag in (("ImageOrientationPatient", "(0020,0037)"), ("ImagePositionPatient", "(0020,0032)"), ("PixelSpacing", "(0028,0030)")):
        missing = [f for f, ds in chosen if getattr(ds, key, None) in (None, "")]
        if missing:
            raise CtSeriesBroken(f"{folder}: {key} {tag} missing in {_names(missing)}")
    iop = np.array([float(v) for v in chosen[0][1].ImageOrientationPatient])
    odd = [f for f, ds in chosen if not np.allclose([float(v) for v in ds.ImageOrientationPatient], iop, atol=1e-4)]
    if odd:
        raise CtSeriesBroken(f"{folder}: slice orientation differs from {chosen[0][0].name} in {_names(odd)} (a gantry-tilted or mixed acquisition)")
    size = (int(chosen[0][1].Rows), int(chosen[0][1].Columns))
    odd = [f for f, ds in chosen if (int(ds.Rows), int(ds.Columns)) != size]
    if odd:
        raise CtSeriesBroken(f"{folder}: slice size differs from {size[0]}x{size[1]} in {_names(odd)}")
    row_dir, col_dir = iop[:3], iop[3:]
    normal = np.cross(row_dir, col_dir)
    positions = np.array([[float(v) for v in ds.ImagePositionPatient] for _, ds in chosen])
    along = positions @ normal
    order = np.argsort(along)
    chosen = [chosen[i] for i in order]
    positions, along = positions[order], along[order]
    gaps = np.diff(along)
    dup = np.flatnonzero(gaps < 1e-3)
    if dup.size:
        raise CtSeriesBroken(f"{folder}: slices at the same position: {chosen[dup[0]][0].name} and {chosen[dup[0] + 1][0].name}")
    median = float(np.median(gaps))
    missing = np.flatnonzero(gaps > 1.5 * median)
    if missing.size:
        pairs = ", ".join(f"{chosen[i][0].name}-{chosen[i + 1][0].name} ({gaps[i]:.2f} mm)" for i in missing[:4])
        raise CtSeriesBroken(f"{folder}: {missing.size} gap(s) in the series (median spacing {median:.2f} mm), slices missing between {pairs}")
    pixels = []
    for f, ds in chosen:
        try:
            arr = ds.pixel_array.astype(np.float32)
        except Exception as exc:  # pydicom raises many types for bad pixel data  # noqa: BLE001
            raise CtUnreadable(f"{f}: pixel data unreadable ({exc})") from None
        slope, intercept = float(getattr(ds, "RescaleSlope", 1) or 1), float(getattr(ds, "RescaleIntercept", 0) or 0)
        pixels.append(arr * slope + intercept)
    data = np.stack(pixels)
    spacing_rc = [float(v) for v in chosen[0][1].PixelSpacing]  # (between rows, between columns)
    if np.ptp(gaps) > SPACING_TOLERANCE * median:
        warnings.warn(CtSpacingWarning(f"{folder}: slice spacing varies from {gaps.min():.3f} to {gaps.max():.3f} mm; resampled to {median:.3f} mm"), stacklevel=2)
        data, along = _resample(data, along, median)
    a = np.eye(4)
    a[:3, 0] = row_dir * spacing_rc[1]
    a[:3, 1] = col_dir * spacing_rc[0]
    a[:3, 2] = normal * median
    a[:3, 3] = positions[0]
    if np.allclose(data, np.rint(data)) and data.min() >= -32768 and data.max() <= 32767:
        data = data.astype(np.int16)
    desc = f"DICOM CT {folder.name}: {len(chosen)} slices, {spacing_rc[1]:.3g}x{spacing_rc[0]:.3g}x{median:.3g} mm"
    return Volume(data=data, patient_from_voxel=a, description=desc)


def _resample(data: NDArray[np.float32], along: NDArray[np.float64], spacing: float) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Linear interpolation of slices onto an even grid from the first slice."""
    n = int(np.floor((along[-1] - along[0]) / spacing + 1e-6)) + 1
    grid = along[0] + spacing * np.arange(n)
    idx = np.clip(np.searchsorted(along, grid, side="right") - 1, 0, len(along) - 2)
    w = ((grid - along[idx]) / (along[idx + 1] - along[idx])).astype(np.float32)[:, None, None]
    return (1 - w) * data[idx] + w * data[idx + 1], grid


def read_nifti(path: str | Path) -> Volume:
    import nibabel as nib  # imported here: only NIfTI users pay for it

    p = Path(path)
    try:
        img = nib.load(str(p))
        arr = np.asarray(img.dataobj)
    except Exception as exc:  # nibabel raises ImageFileError, OSError, EOFError, zlib errors  # noqa: BLE001
        raise CtUnreadable(f"{p}: not a readable NIfTI file ({exc})") from None
    if arr.ndim == 4 and arr.shape[3] == 1:
        arr = arr[..., 0]
    if arr.ndim != 3:
        raise CtUnreadable(f"{p}: expected a 3-D volume, got shape {arr.shape}")
    affine_ras = np.asarray(img.affine, dtype=np.float64)
    lps_from_ras = np.diag([-1.0, -1.0, 1.0, 1.0])
    data = np.ascontiguousarray(np.transpose(arr, (2, 1, 0)))  # (i, j, k) -> (k, j, i)
    if not np.issubdtype(data.dtype, np.integer):
        data = data.astype(np.float32)
        if np.allclose(data, np.rint(data)) and data.min() >= -32768 and data.max() <= 32767:
            data = data.astype(np.int16)
    sp = np.linalg.norm(affine_ras[:3, :3], axis=0)
    return Volume(data=data, patient_from_voxel=lps_from_ras @ affine_ras, description=f"NIfTI {p.name}: {arr.shape[0]}x{arr.shape[1]}x{arr.shape[2]}, {sp[0]:.3g}x{sp[1]:.3g}x{sp[2]:.3g} mm")
