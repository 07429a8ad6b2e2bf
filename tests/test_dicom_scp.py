"""C-STORE SCP over real associations on loopback: stored before acknowledged, refusals, hostile UIDs, TLS, compression."""

import os
import ssl
import stat
import subprocess
import sys

import numpy as np
import pydicom
import pytest

from drillnav.drivers.dicom_scp import DicomNetworkError, StoreScp, client_tls_context, send_files, server_tls_context, stored_name
from drillnav.drivers.fluoro_dicom import read_fluoro
from drillnav.drivers.sim.dicom_io import write_xa
from conftest import free_port
from dicom_compress import SYNTAXES, compress_file
from tls_certs import make_test_pki


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
    (tmp_path / "in" / stored_name(uid)).mkdir()  # the file cannot be put in place: the store must fail
    port = free_port()
    with StoreScp(port=port, storage_dir=tmp_path / "in") as scp:
        statuses = send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa])
        assert statuses == [0xA700] and scp.stored == []


def _tree(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


HOSTILE_UIDS = ["/../../evil", "../../../../x", "..", ".", "a/b", "x" * 60, "1.2.3/../../../../etc/passwd", "1.2.3%2F..%2Fx", "~root", "1.2.3 4"]


@pytest.mark.filterwarnings("ignore:Invalid value for VR UI", "ignore:The value length")
def test_hostile_sop_instance_uids_write_nothing_outside(tmp_path, xa):
    """Each hostile UID goes over a real association; nothing appears outside in/, nothing named by the UID inside."""
    incoming = tmp_path / "site" / "in"
    port = free_port()
    before = _tree(tmp_path)
    with StoreScp(port=port, storage_dir=incoming) as scp:
        for uid in HOSTILE_UIDS:
            ds = pydicom.dcmread(str(xa))
            ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = uid
            statuses = send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", datasets=[ds])
            assert statuses == [0xA900], (uid, statuses)
        # A conformant UID is stored under its hash, inside the folder.
        assert send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa]) == [0]
    after = _tree(tmp_path)
    new = sorted(set(after) - set(before))
    uid = pydicom.dcmread(str(xa)).SOPInstanceUID
    assert new == ["site", "site/in", f"site/in/{stored_name(uid)}"]
    assert scp.stored == [incoming.resolve() / stored_name(uid)]
    assert not (tmp_path.parent / "evil").exists() and not (tmp_path / "evil").exists()


def test_incoming_folder_0700_and_files_0600(tmp_path, xa):
    port = free_port()
    old = os.umask(0o022)  # the usual umask: mkdir and open would give 0755 / 0644 without care
    try:
        with StoreScp(port=port, storage_dir=tmp_path / "in") as scp:
            assert send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa]) == [0]
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "in").stat().st_mode) == 0o700
    assert stat.S_IMODE(scp.stored[0].stat().st_mode) == 0o600


def test_allow_list_required_beyond_loopback(tmp_path):
    with pytest.raises(ValueError, match="allowed_calling_aes"):
        StoreScp(port=free_port(), host="0.0.0.0", storage_dir=tmp_path / "in")
    StoreScp(port=free_port(), host="0.0.0.0", storage_dir=tmp_path / "in", allowed_calling_aes=["CARM1"])  # constructed, not started


def test_tls_and_mutual_tls(tmp_path, xa):
    pki = make_test_pki(tmp_path / "pki")
    port = free_port()
    ctx = server_tls_context(cert=pki.server_cert, key=pki.server_key, ca=pki.ca)
    with StoreScp(port=port, storage_dir=tmp_path / "in", ssl_context=ctx) as scp:
        good = client_tls_context(ca=pki.ca, cert=pki.client_cert, key=pki.client_key)
        assert send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa], ssl_context=good) == [0]
        with pytest.raises(DicomNetworkError):  # no client certificate: mutual TLS refuses it
            send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa], ssl_context=client_tls_context(ca=pki.ca))
        with pytest.raises(DicomNetworkError):  # the server's certificate is not from the CA this client trusts
            send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa],
                       ssl_context=client_tls_context(ca=pki.other_ca, cert=pki.client_cert, key=pki.client_key))
        with pytest.raises(DicomNetworkError):  # plain DICOM to a TLS port
            send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=[xa])
        assert len(scp.stored) == 1


def test_compressed_syntaxes_negotiated_stored_and_decoded(tmp_path):
    rng = np.random.default_rng(3)
    image = rng.uniform(0.0, 4.0, (96, 80)).astype(np.float32)
    src = write_xa(tmp_path / "plain.dcm", image, primary_deg=0, secondary_deg=-25, source_to_detector_mm=1164,
                   source_to_isocenter_mm=624, pixel_spacing_mm=(0.304, 0.304), study_uid="1.2.3", series_uid="1.2.3.4", instance_number=1)
    want = pydicom.dcmread(str(src)).pixel_array
    port = free_port()
    with StoreScp(port=port, storage_dir=tmp_path / "in") as scp:
        for name, uid in SYNTAXES.items():
            sent = compress_file(src, tmp_path / f"{name}.dcm", name)
            ds = pydicom.dcmread(str(sent))
            ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = pydicom.uid.generate_uid()
            assert send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", datasets=[ds]) == [0], name
            stored = pydicom.dcmread(str(scp.stored[-1]))
            assert stored.file_meta.TransferSyntaxUID == uid, name  # stored as received, compressed
            assert np.array_equal(stored.pixel_array, want), name
            (fluoro,) = read_fluoro(scp.stored[-1])
            np.testing.assert_allclose(fluoro.pixels_log, want * float(stored.RescaleSlope), rtol=0, atol=1e-6)


def test_settings_refuse_an_open_listener_and_half_tls():
    from drillnav.service.settings import SettingsError, load_settings

    with pytest.raises(SettingsError, match=r"dicom\.allowed_calling_aes is required when dicom\.scp_host \(0\.0\.0\.0\)"):
        load_settings(dicom={"scp_host": "0.0.0.0"})
    assert load_settings(dicom={"scp_host": "0.0.0.0", "allowed_calling_aes": ["CARM1"]}).dicom.allowed_calling_aes == ["CARM1"]
    assert load_settings(dicom={"scp_host": "::1"}).dicom.allowed_calling_aes is None  # loopback: the allow list may stay open
    with pytest.raises(SettingsError, match=r"dicom\.tls_cert and dicom\.tls_key go together"):
        load_settings(dicom={"tls_cert": "/etc/drillnav/scp.pem"})
