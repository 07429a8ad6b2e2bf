"""C-arm via DICOM networking: a C-STORE SCP that stores each image to disk before acknowledging it.

Accepted storage SOP classes: XA, Enhanced XA, XRF, DX (presentation and
processing), CR and secondary capture (single and multi-frame grayscale), in
uncompressed and lossless compressed transfer syntaxes (JPEG Lossless, JPEG-LS
Lossless, JPEG 2000 Lossless, RLE; decoded later by pydicom with the pylibjpeg
plugins). A calling AE title outside the allow list is rejected at association;
an unknown SOP class is not accepted in negotiation; a dataset that cannot be
written returns 0xA700 (out of resources), so nothing unwritten is ever
acknowledged.

Received data never names a file (and a SOP Instance UID that is not a valid UID is refused, 0xA900): each image is stored as
``<sha256 of its SOP Instance UID>.dcm`` (0600, in a 0700 folder), so a hostile
UID such as ``/../../x`` cannot steer a write out of the folder. Listening on
anything but loopback needs an allow list of calling AE titles. TLS (and mutual
TLS with a CA) comes from :func:`server_tls_context` / :func:`client_tls_context`.
"""

from __future__ import annotations

import hashlib
import ipaddress
import logging
import os
import re
import ssl
import threading
from collections.abc import Callable, Iterable
from pathlib import Path

from pydicom.uid import (
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
    JPEG2000Lossless,
    JPEGLossless,
    JPEGLosslessSV1,
    JPEGLSLossless,
    RLELossless,
)
from pynetdicom import AE, evt
from pynetdicom.sop_class import (  # type: ignore[attr-defined]
    ComputedRadiographyImageStorage,
    DigitalXRayImageStorageForPresentation,
    DigitalXRayImageStorageForProcessing,
    EnhancedXAImageStorage,
    MultiFrameGrayscaleByteSecondaryCaptureImageStorage,
    MultiFrameGrayscaleWordSecondaryCaptureImageStorage,
    SecondaryCaptureImageStorage,
    XRayAngiographicImageStorage,
    XRayRadiofluoroscopicImageStorage,
)

from drillnav.registration.errors import DrillnavError

from .private_files import make_private_dir, open_private

__all__ = [
    "StoreScp",
    "ACCEPTED_SOP_CLASSES",
    "TRANSFER_SYNTAXES",
    "COMPRESSED_TRANSFER_SYNTAXES",
    "DicomNetworkError",
    "send_files",
    "stored_name",
    "is_loopback",
    "server_tls_context",
    "client_tls_context",
]

log = logging.getLogger(__name__)

ACCEPTED_SOP_CLASSES = (
    XRayAngiographicImageStorage,
    EnhancedXAImageStorage,
    XRayRadiofluoroscopicImageStorage,
    DigitalXRayImageStorageForPresentation,
    DigitalXRayImageStorageForProcessing,
    ComputedRadiographyImageStorage,
    SecondaryCaptureImageStorage,
    MultiFrameGrayscaleByteSecondaryCaptureImageStorage,
    MultiFrameGrayscaleWordSecondaryCaptureImageStorage,
)
# Lossless only: a lossy image would shift the marker centroids the registration is built on.
COMPRESSED_TRANSFER_SYNTAXES = [JPEGLosslessSV1, JPEGLossless, JPEGLSLossless, JPEG2000Lossless, RLELossless]
TRANSFER_SYNTAXES = [ExplicitVRLittleEndian, ImplicitVRLittleEndian, *COMPRESSED_TRANSFER_SYNTAXES]


class DicomNetworkError(DrillnavError):
    """An association could not be made, or a C-STORE was not accepted."""


def stored_name(sop_instance_uid: str) -> str:
    """The file name an image is stored under: a hash, so received text never becomes a path."""
    return hashlib.sha256(str(sop_instance_uid).encode("utf-8", "surrogateescape")).hexdigest()[:40] + ".dcm"


# Digits and dots only; leading zeros in a component are tolerated (some C-arms send them) since the name is a hash anyway.
_UID = re.compile(r"^[0-9]+(\.[0-9]+)*$")


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name other than localhost may resolve to anything
        return False


def server_tls_context(*, cert: str | Path, key: str | Path, ca: str | Path | None = None) -> ssl.SSLContext:
    """TLS for the SCP; with ``ca`` the client must present a certificate signed by it (mutual TLS)."""
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.load_cert_chain(certfile=str(cert), keyfile=str(key))
    if ca is not None:
        ctx.load_verify_locations(cafile=str(ca))
        ctx.verify_mode = ssl.CERT_REQUIRED
    return ctx


def client_tls_context(*, ca: str | Path, cert: str | Path | None = None, key: str | Path | None = None) -> ssl.SSLContext:
    """TLS for a sender: trusts ``ca``; ``cert``/``key`` for an SCP that requires client certificates."""
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(ca))
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    if cert is not None:
        ctx.load_cert_chain(certfile=str(cert), keyfile=str(key) if key else None)
    return ctx


def _calling(event) -> str:
    req = event.assoc.requestor
    return f"{str(req.ae_title).strip()}@{req.address}"


class StoreScp:
    """``with StoreScp(ae_title=..., port=..., storage_dir=...) as scp:`` serves in a background thread."""

    def __init__(
        self,
        *,
        ae_title: str = "DRILLNAV",
        port: int = 11112,
        storage_dir: str | Path,
        allowed_calling_aes: Iterable[str] | None = None,
        on_stored: Callable[[Path], None] | None = None,
        host: str = "127.0.0.1",
        ssl_context: ssl.SSLContext | None = None,
    ) -> None:
        if not 1 <= len(ae_title) <= 16:
            raise ValueError(f"AE title must be 1-16 characters, got '{ae_title}'")
        if allowed_calling_aes is None and not is_loopback(host):
            raise ValueError(f"the DICOM SCP listens on {host}, beyond loopback: an allow list of calling AE titles (dicom.allowed_calling_aes) is required")
        self.ae_title, self.port, self.host = ae_title, port, host
        self.storage_dir = make_private_dir(storage_dir)
        self._root = self.storage_dir.resolve()
        self.allowed = None if allowed_calling_aes is None else {a.strip() for a in allowed_calling_aes}
        self.on_stored = on_stored
        self.ssl_context = ssl_context
        self.stored: list[Path] = []
        self._lock = threading.Lock()
        self._server = None

    def _handle_store(self, event) -> int:
        try:
            ds = event.dataset
            ds.file_meta = event.file_meta
            uid = str(ds.SOPInstanceUID)
            if len(uid) > 64 or not _UID.match(uid):
                # No C-arm sends such a UID; the hash below would keep it harmless, but it is refused and logged.
                log.warning("C-STORE from %s refused: SOP Instance UID %r is not a valid UID", _calling(event), uid[:80])
                return 0xA900  # dataset does not match SOP class
            name = stored_name(uid)
            final = self._root / name
            tmp = self._root / f".{name}.part"
            if final.parent != self._root or tmp.parent != self._root:  # cannot happen with a hex name; checked all the same
                raise ValueError("stored path left the incoming folder")
            with open_private(tmp, "wb") as f:
                ds.save_as(f, enforce_file_format=True)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, final)  # the file appears whole before the success status goes back
        except Exception as exc:  # any failure to persist must not be acknowledged
            log.error("C-STORE from %s not stored: %s: %s", _calling(event), type(exc).__name__, exc)
            return 0xA700
        with self._lock:
            self.stored.append(final)
        if self.on_stored is not None:
            self.on_stored(final)
        return 0x0000

    def __enter__(self) -> "StoreScp":
        ae = AE(ae_title=self.ae_title)
        for sop in ACCEPTED_SOP_CLASSES:
            ae.add_supported_context(sop, TRANSFER_SYNTAXES)
        if self.allowed is not None:
            # Associations from any other calling AE title are rejected (calling AE title not recognised).
            ae.require_calling_aet = sorted(self.allowed)
        handlers = [(evt.EVT_C_STORE, self._handle_store)]
        try:
            self._server = ae.start_server((self.host, self.port), block=False, evt_handlers=handlers, ssl_context=self.ssl_context)
        except OSError as exc:
            raise DicomNetworkError(f"cannot listen for DICOM on {self.host}:{self.port}: {exc.strerror}") from None
        return self

    def __exit__(self, *exc) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server = None


def send_files(
    *,
    host: str,
    port: int,
    called_ae: str,
    paths: Iterable[str | Path] = (),
    calling_ae: str = "CARM",
    datasets: Iterable = (),
    ssl_context: ssl.SSLContext | None = None,
    server_hostname: str | None = None,
) -> list[int]:
    """C-STORE each file, then each dataset (a test SCU, and the twin C-arm's sender); returns the status per image.

    Each image goes in its own transfer syntax (a compressed file is sent compressed).
    """
    import pydicom

    items = [pydicom.dcmread(str(p)) for p in paths] + list(datasets)
    ae = AE(ae_title=calling_ae)
    contexts = set()
    for ds in items:
        ts = ds.file_meta.TransferSyntaxUID if "TransferSyntaxUID" in getattr(ds, "file_meta", {}) else ExplicitVRLittleEndian
        contexts.add((str(ds.SOPClassUID), str(ts)))
    for sop, ts in sorted(contexts):
        ae.add_requested_context(sop, [ts])
    tls_args = (ssl_context, server_hostname or host) if ssl_context is not None else None
    assoc = ae.associate(host, port, ae_title=called_ae, tls_args=tls_args)
    if not assoc.is_established:
        raise DicomNetworkError(f"association with {called_ae}@{host}:{port} was rejected or failed")
    statuses = []
    try:
        for ds in items:
            try:
                st = assoc.send_c_store(ds)
            except ValueError as exc:  # no accepted presentation context for this SOP class
                raise DicomNetworkError(f"{called_ae} does not accept SOP class {ds.SOPClassUID}: {exc}") from None
            statuses.append(int(st.Status) if st else -1)
    finally:
        assoc.release()
    return statuses
