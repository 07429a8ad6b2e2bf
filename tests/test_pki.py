"""drillnav pki: a site CA and per-client certificates (cryptography), via the functions and the CLI."""

import ipaddress
import os

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from drillnav.service.cli import main
from drillnav.service.pki import PkiError, common_name, init_ca, issue


def _load(path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_cli_makes_a_ca_and_client_certificates_signed_by_it(tmp_path, capsys):
    site = tmp_path / "site"
    assert main(["pki", "init", "--out", str(site)]) == 0
    assert main(["pki", "issue", "--ca", str(site), "--name", "drillnav-daemon", "--name", "display-1", "--host", "navcart.or3.local", "--host", "10.20.30.40"]) == 0
    out = capsys.readouterr().out
    assert "issued 'drillnav-daemon'" in out and "issued 'display-1'" in out
    ca = _load(site / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert os.stat(site).st_mode & 0o777 == 0o700
    for name in ("drillnav-daemon", "display-1"):
        cert = _load(site / f"{name}.pem")
        cert.verify_directly_issued_by(ca)  # raises if the signature is not the CA's
        assert common_name(site / f"{name}.pem") == name
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        usage = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert ExtendedKeyUsageOID.SERVER_AUTH in usage and ExtendedKeyUsageOID.CLIENT_AUTH in usage
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert "navcart.or3.local" in san.get_values_for_type(x509.DNSName)
        assert ipaddress.ip_address("10.20.30.40") in san.get_values_for_type(x509.IPAddress)
        assert ipaddress.ip_address("127.0.0.1") in san.get_values_for_type(x509.IPAddress)
        assert cert.not_valid_after_utc <= ca.not_valid_after_utc
    for key in site.glob("*.key"):
        assert os.stat(key).st_mode & 0o777 == 0o600, key
    assert {p.name for p in site.iterdir()} == {"ca.pem", "ca.key", "drillnav-daemon.pem", "drillnav-daemon.key", "display-1.pem", "display-1.key"}


def test_keys_are_0600_whatever_the_umask(tmp_path):
    old = os.umask(0)  # the most permissive umask: the files must still be private
    try:
        init_ca(tmp_path)
        issue(tmp_path, "camera-1", tmp_path / "out")
    finally:
        os.umask(old)
    assert os.stat(tmp_path / "ca.key").st_mode & 0o777 == 0o600
    assert os.stat(tmp_path / "out" / "camera-1.key").st_mode & 0o777 == 0o600


def test_refusals_name_the_problem(tmp_path, capsys):
    init_ca(tmp_path)
    with pytest.raises(PkiError, match="a site has one CA"):
        init_ca(tmp_path)
    issue(tmp_path, "camera-1", tmp_path)
    before = (tmp_path / "camera-1.pem").read_bytes()
    with pytest.raises(PkiError, match="camera-1.pem exists already"):
        issue(tmp_path, "camera-1", tmp_path)
    assert (tmp_path / "camera-1.pem").read_bytes() == before  # never overwritten
    with pytest.raises(PkiError, match="must be 1-63 letters"):
        issue(tmp_path, "../evil", tmp_path)
    with pytest.raises(PkiError, match="no CA in .*nowhere.*does not exist"):
        issue(tmp_path / "nowhere", "camera-2", tmp_path)
    other = tmp_path / "other"
    init_ca(other)
    (tmp_path / "mixed").mkdir()
    (tmp_path / "mixed" / "ca.pem").write_bytes((tmp_path / "ca.pem").read_bytes())
    (tmp_path / "mixed" / "ca.key").write_bytes((other / "ca.key").read_bytes())
    with pytest.raises(PkiError, match="is not the private key of"):
        issue(tmp_path / "mixed", "camera-2", tmp_path)
    assert main(["pki", "issue", "--ca", str(tmp_path), "--name", "bad name"]) == 1
    assert "must be 1-63 letters" in capsys.readouterr().err
