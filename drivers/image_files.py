"""Reading camera frames from image files with clear errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from drillnav.registration.errors import DrillnavError

__all__ = ["ImageUnreadable", "read_image"]


class ImageUnreadable(DrillnavError):
    """A missing, empty, corrupt or non-image file."""


def read_image(path: str | Path, *, grayscale: bool = True) -> NDArray[np.uint8]:
    p = Path(path)
    if not p.is_file():
        raise ImageUnreadable(f"{p}: no such file")
    data = np.fromfile(str(p), dtype=np.uint8)
    if data.size == 0:
        raise ImageUnreadable(f"{p}: file is empty")
    img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR)
    if img is None:
        raise ImageUnreadable(f"{p}: not a readable image (corrupt or unsupported format)")
    return img
