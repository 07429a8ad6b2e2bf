"""Touching BBs: one blob over the detector's threshold split into the BB shadows it is made of.

A marker steep to the beam crowds its pattern across the ring's ellipse, so the
shadows of two of its BBs can touch; over the detector's threshold they make one
blob, whose centroid lies between them and places neither. Each shadow is a dome
(a sphere's chord profile), so two touching ones keep a saddle between their
peaks: thresholded at rising levels, the blob falls apart into one piece per
dome before the saddle's level is reached and each piece's own peak is. The
pixels of the whole blob are then shared out to the piece nearest each.

Pure math: numpy and OpenCV's connected components.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["split_touching"]

# A piece counts as a dome of its own where the saddle joining it to the rest lies at most this fraction of its own
# peak. Seed 11300's lateral view: a 3.5 mm BB and the 2.0 mm central one of a marker 70 deg to the beam, their saddle
# at about 0.6 of the smaller peak. A single dome 7 sigma high, blurred as the detector blurs, is split in none of
# 200 noise draws at 0.75, and in some at 0.95 (tests/test_blob_split.py).
SPLIT_PROMINENCE = 0.75
# Levels tried between the blob's threshold and its peak.
SPLIT_LEVELS = 12


def split_touching(values: NDArray[np.float32], mask: NDArray[np.bool_], *, threshold: float, min_area_px: int = 4) -> list[NDArray[np.bool_]]:
    """The pixels (masks of ``values``'s shape) of each BB shadow in one blob: ``values`` (H, W) the blob's window,
    ``mask`` (H, W) its pixels over ``threshold``; [``mask``] when it is one dome.

    A piece is a dome when its pixels over some level (``min_area_px`` or more of them) form a component apart from
    the others' while its own peak reaches the level over :data:`SPLIT_PROMINENCE`; the level that parts the most
    such pieces is taken (the lowest of equals, so each piece holds as much of its dome as it can).
    """
    vals = np.where(mask, values, 0.0).astype(np.float32)
    peak = float(vals.max())
    if peak <= threshold:
        return [mask]
    best: list[NDArray[np.bool_]] = []
    for level in threshold + (peak - threshold) * np.arange(1, SPLIT_LEVELS + 1) / (SPLIT_LEVELS + 1):
        n, labels, stats, _ = cv2.connectedComponentsWithStats((vals > level).astype(np.uint8), connectivity=8)
        seeds = [labels == i for i in range(1, n)
                 if stats[i, cv2.CC_STAT_AREA] >= min_area_px and float(vals[labels == i].max()) * SPLIT_PROMINENCE >= level]
        if len(seeds) > max(1, len(best)):
            best = seeds
    if not best:
        return [mask]
    # Each pixel of the blob goes to the nearest seed.
    rows, cols = np.nonzero(mask)
    dist = np.full((len(best), rows.size), np.inf)
    for k, seed in enumerate(best):
        sr, sc = np.nonzero(seed)
        d2 = (rows[:, None] - sr[None, :]) ** 2 + (cols[:, None] - sc[None, :]) ** 2
        dist[k] = d2.min(axis=1)
    owner = np.argmin(dist, axis=0)
    pieces = []
    for k in range(len(best)):
        piece = np.zeros_like(mask)
        piece[rows[owner == k], cols[owner == k]] = True
        pieces.append(piece)
    return pieces
