"""A camera device for tests: an MJPG file that OpenCV opens as it opens /dev/videoN (rename it away to unplug it)."""

from pathlib import Path

import cv2
import numpy as np


def camera_file(folder: Path, *, frames: int = 30) -> Path:
    """``folder/video0.avi``: ``frames`` grey 320x240 frames, each brighter than the last."""
    path = Path(folder) / "video0.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    assert writer.isOpened()
    for i in range(frames):
        writer.write(np.full((240, 320, 3), int(200 * i / max(frames - 1, 1)), np.uint8))
    writer.release()
    return path
