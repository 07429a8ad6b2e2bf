"""C-arm via DICOM networking: a C-STORE SCP that stores each image to disk before acknowledging it.

Accepted storage SOP classes: XA, Enhanced XA, XRF, DX (presentation and
processing), CR and secondary capture (single and multi-frame grayscale).
A calling AE title outside the allow list is rejected at association; an
unknown SOP class is not accepted in negotiation; a dataset that cannot be
written returns 0xA700 (out of resources), so nothing unwritten is ever
acknowledged.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from pathlib import Path

from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian
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

__all__ = ["StoreScp", "ACCEPTED_SOP_CLASSES", "DicomNetworkError", "send_files"]

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
TRANSFER_SYNTAXES = [ExplicitVRLittleEndian, ImplicitVRLittleEndian]


class DicomNetworkError(DrillnavError):
    """An association could not be made, or a C-STORE was not accepted."""


class StoreScp:
    """``with StoreScp(ae_title=..., port=..., storage_dir=...) as scp:`` serves in a background thread."""

    def __init__(self, *, ae_title: str = "DRILLNAV", port: int = 11112, storage_dir: str | Path, allowed_calling_aes: Iterable[str] | None = None, on_stored: Callable[[Path], None] | None = None, host: str = "127.0.0.1") -> None:
        if not 1 <= len(ae_title) <= 16:
            raise ValueError(f"AE title must be 1-16 characters, got '{ae_title}'")
        self.ae_title, self.port, self.host = ae_title, port, host
        self.storage_dir = Path(storage_dir)
        self.storage_dir.mkdir(parents=True, exist_ok=True)
        self.allowed = None if allowed_calling_aes is None else {a.strip() for a in allowed_calling_aes}
        self.on_stored = on_stored
        self.stored: list[Path] = []
        self._lock = threading.Lock()
        self._server = None

    def _handle_store(self, event) -> int:
        try:
            ds = event.dataset
            ds.file_meta = event.file_meta
            name = f"{ds.SOPInstanceUID}.dcm"
            tmp = self.storage_dir / f".{name}.part"
            with open(tmp, "wb") as f:
                ds.save_as(f, enforce_file_format=True)
                f.flush()
                os.fsync(f.fileno())
            final = self.storage_dir / name
            os.replace(tmp, final)  # the file appears whole before the success status goes back
        except Exception:  # any failure to persist must not be acknowledged
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
            self._server = ae.start_server((self.host, self.port), block=False, evt_handlers=handlers)
        except OSError as exc:
            raise DicomNetworkError(f"cannot listen for DICOM on {self.host}:{self.port}: {exc.strerror}") from None
        return self

    def __exit__(self, *exc) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server = None


def send_files(*, host: str, port: int, called_ae: str, paths: Iterable[str | Path], calling_ae: str = "CARM") -> list[int]:
    """C-STORE each file (a test SCU, and the twin C-arm's sender); returns the status per file."""
    import pydicom

    datasets = [pydicom.dcmread(str(p)) for p in paths]
    ae = AE(ae_title=calling_ae)
    for ds in datasets:
        ae.add_requested_context(ds.SOPClassUID, TRANSFER_SYNTAXES)
    assoc = ae.associate(host, port, ae_title=called_ae)
    if not assoc.is_established:
        raise DicomNetworkError(f"association with {called_ae}@{host}:{port} was rejected or failed")
    statuses = []
    try:
        for ds in datasets:
            try:
                st = assoc.send_c_store(ds)
            except ValueError as exc:  # no accepted presentation context for this SOP class
                raise DicomNetworkError(f"{called_ae} does not accept SOP class {ds.SOPClassUID}: {exc}") from None
            statuses.append(int(st.Status) if st else -1)
    finally:
        assoc.release()
    return statuses
