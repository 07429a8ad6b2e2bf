"""Lossless compression of test DICOM files in the syntaxes C-arms send, with the encoders that install from PyPI.

pydicom's ``Dataset.compress`` encodes RLE (its own encoder), JPEG-LS (pyjpegls) and JPEG 2000 (pylibjpeg-openjpeg);
it has no JPEG Lossless encoder, so that one is made with GDCM (python-gdcm).
"""

from __future__ import annotations

from pathlib import Path

import pydicom
from pydicom.uid import JPEG2000Lossless, JPEGLosslessSV1, JPEGLSLossless, RLELossless

SYNTAXES = {"jpeg-lossless": JPEGLosslessSV1, "jpeg-ls": JPEGLSLossless, "jpeg2000": JPEG2000Lossless, "rle": RLELossless}


def compress_file(src: Path, dst: Path, syntax: str) -> Path:
    """Write ``src`` to ``dst`` in ``syntax`` (a key of SYNTAXES); returns ``dst``."""
    uid = SYNTAXES[syntax]
    if uid == JPEGLosslessSV1:
        import gdcm

        reader = gdcm.ImageReader()
        reader.SetFileName(str(src))
        if not reader.Read():
            raise ValueError(f"GDCM cannot read {src}")
        change = gdcm.ImageChangeTransferSyntax()
        change.SetTransferSyntax(gdcm.TransferSyntax(gdcm.TransferSyntax.JPEGLosslessProcess14_1))
        change.SetInput(reader.GetImage())
        if not change.Change():
            raise ValueError(f"GDCM cannot compress {src} to JPEG Lossless")
        writer = gdcm.ImageWriter()
        writer.SetFileName(str(dst))
        writer.SetFile(reader.GetFile())
        writer.SetImage(change.GetOutput())
        if not writer.Write():
            raise ValueError(f"GDCM cannot write {dst}")
    else:
        ds = pydicom.dcmread(str(src))
        ds.compress(uid)
        ds.save_as(str(dst), enforce_file_format=True)
    if pydicom.dcmread(str(dst), stop_before_pixels=True).file_meta.TransferSyntaxUID != uid:
        raise AssertionError(f"{dst} is not in {uid.name}")
    return dst
