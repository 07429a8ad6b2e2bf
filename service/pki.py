"""A site's own certificate authority for the zenoh bus: one CA, one certificate per client.

The bus's TLS links (and mutual TLS) need a CA every party trusts and a
certificate per party whose common name is the name the access-control rules
know it by (``drillnav-daemon``, ``camera-1``, ``display-1``). A hospital
network has no public name for an operating-room cart, so the site makes its
own CA with :func:`init_ca` and issues certificates with :func:`issue`.

Files, in one folder:

- ``ca.pem`` (the CA certificate: give it to every client) and ``ca.key``
  (the CA's private key: keep it off the bus machines once the certificates
  are issued);
- ``<name>.pem`` and ``<name>.key`` per client.

Private keys are written 0600 and never overwritten: reissuing means removing
the old files first, on purpose. Keys are ECDSA P-256 (rustls, which zenoh
uses, accepts them; they are small and quick to make).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from drillnav.registration.errors import DrillnavError

__all__ = ["PkiError", "IssuedCertificate", "init_ca", "issue", "common_name", "CA_CERT", "CA_KEY", "DEFAULT_SANS"]

CA_CERT = "ca.pem"
CA_KEY = "ca.key"
# Every certificate also names the loopback host, so a client on the daemon's own machine verifies it.
DEFAULT_SANS: tuple[str, ...] = ("localhost", "127.0.0.1", "::1")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,62}$")


class PkiError(DrillnavError):
    """A certificate authority or certificate that cannot be made or read."""


@dataclass(frozen=True)
class IssuedCertificate:
    name: str
    certificate: Path
    private_key: Path
    not_after: dt.datetime


def _check_name(name: str) -> str:
    if not _NAME.match(name):
        raise PkiError(f"certificate name '{name}' must be 1-63 letters, digits, '.', '_' or '-' (it becomes the common name and the file name)")
    return name


def _write_new(path: Path, data: bytes, mode: int) -> None:
    """Create ``path`` with ``mode`` from the start (no window where a key is world-readable); never overwrite."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    except FileExistsError:
        raise PkiError(f"{path} exists already: remove it first to make a new one") from None
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.chmod(path, mode)  # the umask may have narrowed it; say exactly what we mean


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())


def _san(names: tuple[str, ...]) -> x509.SubjectAlternativeName:
    entries: list[x509.GeneralName] = []
    for n in dict.fromkeys(names):  # keep order, drop repeats
        try:
            entries.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            entries.append(x509.DNSName(n))
    return x509.SubjectAlternativeName(entries)


def init_ca(out: Path, *, organisation: str = "drillnav site", days: int = 3650) -> Path:
    """Make a new CA in folder ``out`` (created 0700 if missing); return the CA certificate's path."""
    if days < 1:
        raise PkiError(f"CA validity must be at least 1 day, got {days}")
    out = Path(out)
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    for existing in (out / CA_CERT, out / CA_KEY):
        if existing.exists():
            raise PkiError(f"{existing} exists already: a site has one CA; remove it first to start over")
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, organisation), x509.NameAttribute(NameOID.COMMON_NAME, f"{organisation} CA")])
    now = dt.datetime.now(dt.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))  # clocks on a site network disagree by minutes
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False, data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write_new(out / CA_KEY, _key_pem(key), 0o600)
    _write_new(out / CA_CERT, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return out / CA_CERT


def _load_ca(ca: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    ca = Path(ca)
    try:
        cert = x509.load_pem_x509_certificate((ca / CA_CERT).read_bytes())
        key = serialization.load_pem_private_key((ca / CA_KEY).read_bytes(), password=None)
    except FileNotFoundError as exc:
        raise PkiError(f"no CA in {ca}: {exc.filename} does not exist (make one with 'drillnav pki init --out {ca}')") from None
    except ValueError as exc:
        raise PkiError(f"the CA in {ca} cannot be read: {exc}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey) or key.public_key().public_numbers() != cert.public_key().public_numbers():
        raise PkiError(f"{ca / CA_KEY} is not the private key of {ca / CA_CERT}")
    return cert, key


def issue(ca: Path, name: str, out: Path, *, hosts: tuple[str, ...] = (), days: int = 825) -> IssuedCertificate:
    """Issue ``<out>/<name>.pem`` and ``<name>.key``, signed by the CA in folder ``ca``.

    ``name`` is the certificate's common name, the identity the bus's access
    control matches; ``hosts`` are extra DNS names or IP addresses the holder
    is reached at (a listening daemon's host name), besides loopback. The
    certificate serves as both TLS server and client (a zenoh peer is both).
    """
    _check_name(name)
    if days < 1:
        raise PkiError(f"certificate validity must be at least 1 day, got {days}")
    ca_cert, ca_key = _load_ca(ca)
    out = Path(out)
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    cert_path, key_path = out / f"{name}.pem", out / f"{name}.key"
    for existing in (cert_path, key_path):
        if existing.exists():
            raise PkiError(f"{existing} exists already: remove it first to reissue '{name}'")
    now = dt.datetime.now(dt.timezone.utc)
    not_after = min(now + dt.timedelta(days=days), ca_cert.not_valid_after_utc)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False, data_encipherment=False, key_agreement=True, key_cert_sign=False, crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        .add_extension(_san(tuple(hosts) + DEFAULT_SANS), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write_new(key_path, _key_pem(key), 0o600)
    _write_new(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return IssuedCertificate(name=name, certificate=cert_path, private_key=key_path, not_after=not_after)


def common_name(certificate: Path) -> str:
    """The common name of a PEM certificate (what the bus's access control matches)."""
    try:
        cert = x509.load_pem_x509_certificate(Path(certificate).read_bytes())
    except ValueError as exc:
        raise PkiError(f"{certificate} is not a PEM certificate: {exc}") from None
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not names:
        raise PkiError(f"{certificate} has no common name")
    return str(names[0].value)
