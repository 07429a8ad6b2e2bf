"""CT intake: DICOM series (any order, any orientation, broken series refused with files named) and NIfTI."""

import shutil
import warnings
from pathlib import Path

import numpy as np
import pydicom
import pytest

from drillnav.drivers.ct_volume import CtSeriesBroken, CtSpacingWarning, CtUnreadable, read_ct
from drillnav.drivers.sim.dicom_io import write_ct_series
from drillnav.registration.transforms import apply, from_rotvec
from drillnav.registration.volume import Volume

SHARED_CT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ct"


def small_volume(rotation=np.eye(3)) -> Volume:
    rng = np.random.default_rng(3)
    data = rng.integers(-1000, 2000, size=(12, 20, 16)).astype(np.int16)
    a = np.eye(4)
    a[:3, :3] = rotation @ np.diag([0.8, 0.9, 2.5])
    a[:3, 3] = [-30.0, 12.0, -100.0]
    return Volume(data=data, patient_from_voxel=a)


@pytest.fixture
def series(tmp_path):
    vol = small_volume()
    write_ct_series(tmp_path / "ct", vol)
    return vol, tmp_path / "ct"


def test_round_trip_in_any_file_order(series, tmp_path):
    vol, folder = series
    shuffled = tmp_path / "shuffled"
    shuffled.mkdir()
    for n, f in enumerate(sorted(folder.iterdir(), reverse=True)):  # names no longer follow position
        shutil.copy(f, shuffled / f"x{(n * 7) % 12:02d}_{n}.dcm")
    got = read_ct(shuffled)
    np.testing.assert_array_equal(got.data, vol.data)
    np.testing.assert_allclose(got.patient_from_voxel, vol.patient_from_voxel, atol=1e-3)


def test_oblique_orientation_maps_voxels_to_the_same_patient_points(tmp_path):
    vol = small_volume(from_rotvec([0.3, -0.2, 0.5])[:3, :3])
    write_ct_series(tmp_path / "ob", vol)
    got = read_ct(tmp_path / "ob")
    ijk = np.array([[0, 0, 0], [15, 19, 11], [3, 7, 5]], float)
    np.testing.assert_allclose(apply(got.patient_from_voxel, ijk), apply(vol.patient_from_voxel, ijk), atol=1e-3)
    np.testing.assert_array_equal(got.data, vol.data)


def test_missing_slice_names_its_neighbours(series):
    _, folder = series
    (folder / "CT0006.dcm").unlink()
    with pytest.raises(CtSeriesBroken, match=r"slices missing between CT0005.dcm-CT0007.dcm"):
        read_ct(folder)


def test_mixed_series_and_unreadable_files(series, tmp_path):
    _, folder = series
    other = tmp_path / "other"
    write_ct_series(other, small_volume(), series_description="second")
    shutil.copy(other / "CT0001.dcm", folder / "Z0001.dcm")
    with pytest.raises(CtSeriesBroken, match="mixed series"):
        read_ct(folder)
    (folder / "Z0001.dcm").unlink()
    (folder / "notes.dcm").write_bytes(b"not dicom at all")
    with pytest.raises(CtUnreadable, match="notes.dcm"):
        read_ct(folder)


def test_missing_orientation_and_non_ct_are_named(series):
    _, folder = series
    ds = pydicom.dcmread(folder / "CT0003.dcm")
    del ds.ImageOrientationPatient
    ds.save_as(folder / "CT0003.dcm")
    with pytest.raises(CtSeriesBroken, match=r"ImageOrientationPatient \(0020,0037\) missing in CT0003.dcm"):
        read_ct(folder)


def test_uneven_spacing_is_resampled_with_a_warning(series):
    vol, folder = series
    ds = pydicom.dcmread(folder / "CT0004.dcm")
    pos = [float(v) for v in ds.ImagePositionPatient]
    ds.ImagePositionPatient = [pos[0], pos[1], pos[2] + 0.4]  # 0.4 mm off in a 2.5 mm grid
    ds.save_as(folder / "CT0004.dcm")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = read_ct(folder)
    assert any(issubclass(w.category, CtSpacingWarning) and "resampled" in str(w.message) for w in caught)
    assert got.shape == vol.shape
    np.testing.assert_allclose(got.spacing_mm, vol.spacing_mm, atol=1e-6)


def test_bad_paths(tmp_path):
    with pytest.raises(CtUnreadable, match="no such file or folder"):
        read_ct(tmp_path / "absent")
    (tmp_path / "ct.txt").write_text("x")
    with pytest.raises(CtUnreadable, match="DICOM CT series, or a .nii"):
        read_ct(tmp_path / "ct.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CtUnreadable, match="no files"):
        read_ct(tmp_path / "empty")
    (tmp_path / "bad.nii.gz").write_bytes(b"\x1f\x8b garbage")
    with pytest.raises(CtUnreadable, match="not a readable NIfTI"):
        read_ct(tmp_path / "bad.nii.gz")


def test_nifti_ras_affine_becomes_lps(tmp_path):
    import nibabel as nib

    arr = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)  # (i, j, k)
    affine = np.diag([0.7, 0.7, 2.5, 1.0])
    affine[:3, 3] = [-100.0, 50.0, -20.0]
    nib.save(nib.Nifti1Image(arr, affine), tmp_path / "v.nii.gz")
    vol = read_ct(tmp_path / "v.nii.gz")
    assert vol.shape == (6, 5, 4)
    assert vol.data[5, 4, 3] == arr[3, 4, 5]
    ras = affine @ [3, 4, 5, 1]
    np.testing.assert_allclose(apply(vol.patient_from_voxel, [[3, 4, 5]])[0], [-ras[0], -ras[1], ras[2]])


def test_real_chest_ct_reads_with_its_labels():
    if not (SHARED_CT / "cxr.nii.gz").is_file():
        pytest.skip("../shared/data/ct is not present on this machine")
    ct = read_ct(SHARED_CT / "cxr.nii.gz")
    labels = read_ct(SHARED_CT / "mask.nii.gz")
    assert ct.shape == (133, 512, 512) and labels.shape == ct.shape
    np.testing.assert_allclose(ct.spacing_mm, [0.703, 0.703, 2.5], atol=2e-3)
    # Vertebrae (TotalSegmentator labels 25-50) are bone: their median HU is well above soft tissue.
    bone = np.isin(labels.data, np.arange(25, 51))
    assert bone.sum() > 10_000 and np.median(ct.data[bone]) > 150
