"""The DICOM intake as the daemon owns it: SCP over TLS from settings, the watched folder, the journal across a restart, retention."""

import os
import time

import numpy as np

from drillnav.drivers.dicom_scp import client_tls_context, send_files
from drillnav.drivers.sim.dicom_io import write_xa
from drillnav.service.dicom_intake import DicomIntake
from drillnav.service.settings import load_settings
from conftest import free_port
from tls_certs import make_test_pki


def _wait_for(intake, n, deadline_s=10.0):
    got, end = [], time.monotonic() + deadline_s
    while len(got) < n and time.monotonic() < end:
        got += intake.wait(0.2)
    return got


def test_intake_over_tls_survives_a_restart_and_applies_retention(tmp_path):
    pki = make_test_pki(tmp_path / "pki")
    port = free_port()
    folder = tmp_path / "in"
    s = load_settings(dicom={"watch_folder": str(folder), "scp_port": port, "allowed_calling_aes": ["CARM1"], "tls_cert": str(pki.server_cert),
                             "tls_key": str(pki.server_key), "tls_ca": str(pki.ca), "retention_max_age_h": 1.0, "retention_every_s": 0.5}).dicom
    shots = [write_xa(tmp_path / f"s{i}.dcm", np.full((32, 32), 1.0 + i, np.float32), primary_deg=0, secondary_deg=-25, source_to_detector_mm=1164,
                      source_to_isocenter_mm=624, pixel_spacing_mm=(0.3, 0.3), study_uid="1.2.3", series_uid="1.2.3.4", instance_number=i) for i in range(2)]
    tls = client_tls_context(ca=pki.ca, cert=pki.client_cert, key=pki.client_key)
    errors = []
    with DicomIntake(settings=s, on_error=lambda p, m: errors.append(m)) as intake:
        assert send_files(host="127.0.0.1", port=port, called_ae="DRILLNAV", paths=shots, calling_ae="CARM1", ssl_context=tls) == [0, 0]
        got = _wait_for(intake, 2)
        assert len(got) == 2
        intake.mark_processed(got[0])  # the second was acknowledged but the process "dies" before handling it
    with DicomIntake(settings=s) as intake:
        assert _wait_for(intake, 1) == [got[1]]  # offered again after the restart; the processed one is not
        intake.mark_processed(got[1])
        old = time.time() - 2 * 3600
        os.utime(got[0], (old, old))
        time.sleep(0.6)  # past retention_every_s: the next wait applies it
        intake.wait(0.05)
        assert intake.removed == [got[0]] and not got[0].exists() and got[1].exists()
    assert errors == []
