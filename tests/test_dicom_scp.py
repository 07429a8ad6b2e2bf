"""C-STORE SCP over real associations on loopback: stored before acknowledged, refusals."""

import subprocess
import sys

import numpy as np
import pydicom
import pytest

from drillnav.drivers.dicom_scp import DicomNetworkError, StoreScp, send_files
from drillnav.drivers.sim.dicom_io import write_xa
from conftest import free_port


@pytest.fixture()
def xa(tmp_path):
    return write_xa(tmp_path / "shot.dcm", np.full((64, 64), 2.0, np.float32), primary_deg=0, secondary_deg=-25, source_to_detector_mm=1164,
                    source_to_isocenter_mm=624, pixel_spacing_mm=(0.304, 0.304), study_uid="1.2.3", series_uid="1.2.3.4", instance_number=1)


def test_store_from_a_separate_process(tmp_path, xa):
    stored = []
    port = free_port()
    with StoreScp(port=port, storage_dir=tmp_path / "in", on_stored=stored.append) as scp:
        code = (
            "from drillnav.drivers.dicom_scp import send_files; import sys;"
            f"print(send_files(host='127.0.0.1', port={port}, called_ae='DRILLNAV', paths=[r'{xa}']))"
        )
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == "[0]"
    (path,) = stored
    ds = pydicom.dcmread(str(path))
    assert ds.PositionerSecondaryAngle == -25 and ds.SOPInstanceUID == pydicom.dcmread(str(xa)).SOPInstanceUID
    assert not list((tmp_path / "in").glob(".*.part"))


def test_calling_ae_not_allowed(tmp_path, xa):
    port = free_port()
    with StoreScp(port=port, storage_dir=tmp_path / "in", allowed_calling_aes={"CARM1"}):
        with pytest.raises(DicomNetworkError, match="rejected"):
            send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa], calling_ae="INTRUDER")
        assert send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa], calling_ae="CARM1") == [0]


def test_unknown_sop_class_is_not_accepted(tmp_path, xa):
    ds = pydicom.dcmread(str(xa))
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2"  # CT Image Storage
    ds.save_as(str(tmp_path / "ct.dcm"))
    port = free_port()
    with StoreScp(port=port, storage_dir=tmp_path / "in") as scp:
        with pytest.raises(DicomNetworkError):
            send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[tmp_path / "ct.dcm"])
        assert scp.stored == []


def test_unwritable_storage_is_not_acknowledged(tmp_path, xa):
    uid = pydicom.dcmread(str(xa)).SOPInstanceUID
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / f"{uid}.dcm").mkdir()  # the file cannot be put in place: the store must fail
    port = free_port()
    with StoreScp(port=port, storage_dir=tmp_path / "in") as scp:
        statuses = send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa])
        assert statuses == [0xA700] and scp.stored == []
