"""A square tag's four outer border edges in a grey image: profiles across them, step positions, lines, corners.

The pieces shared by the locator's edge refinement of detected tags (``video_markers._edge_refined``) and the
recovery of a tag the detector missed from where the registration predicts it (``tag_recovery``): both sample
each edge across its normal, place the black border's step in every profile, fit a line to each edge and take
the corners as the lines' intersections (a straight edge blurred by a symmetric kernel keeps its place where a
rounded corner does not; a hidden corner is still the crossing of its two edges' lines). All batched over
tags, edges and samples: a per-tag loop on the frame path costs numpy's per-call overhead for every tag.

Edge k of a tag runs from its corner k to corner k + 1 (OpenCV order TL, TR, BR, BL, clockwise in the image);
its normal points out of the tag.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["EdgeProfiles", "edge_profiles", "step_positions", "fit_edge_lines", "edge_corners"]


@dataclass(frozen=True, kw_only=True)
class EdgeProfiles:
    """Grey levels sampled across each edge of n tags.

    base_px : (n, 4, s, 2) points on the edges (at ``along`` fractions from corner k to k + 1).
    normal : (n, 4, 2) unit normals pointing out of each tag (image px).
    offsets_px : (o,) offsets along the normal at which each profile is sampled (negative: inside the tag).
    values : (n, 4, s, o) grey levels (bilinear), float32.
    length_px : (n, 4) edge lengths.
    inside : (n,) whether every sample point of the tag lies in the frame.
    sample_inside : (n, 4, s) whether every point of that sample's profile lies in the frame (a tag partly out of
        the frame is sampled with the border replicated; its samples outside say nothing).
    point_inside : (n, 4, s, o) whether each point of each profile lies in the frame (an edge running just inside
        the frame's edge has no profile wholly in it, but its step and the levels either side may be).
    """

    base_px: NDArray[np.float64]
    normal: NDArray[np.float64]
    offsets_px: NDArray[np.float64]
    values: NDArray[np.float32]
    length_px: NDArray[np.float64]
    inside: NDArray[np.bool_]
    sample_inside: NDArray[np.bool_]
    point_inside: NDArray[np.bool_]


def edge_profiles(gray: NDArray[np.float32], quads: NDArray[np.float64], *, along: NDArray[np.float64], offsets_px: NDArray[np.float64]) -> EdgeProfiles:
    """Profiles across the four edges of each quad (n, 4, 2) (corners in OpenCV order), all in one ``cv2.remap``."""
    quads = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
    n = len(quads)
    h, w = gray.shape
    d = np.roll(quads, -1, axis=1) - quads                                           # (n, 4, 2)
    length = np.linalg.norm(d, axis=2)                                               # (n, 4)
    # (d_y, -d_x) points out of a quad whose corners run clockwise in the image (y down), as OpenCV orders them.
    normal = np.stack([d[..., 1], -d[..., 0]], axis=2) / np.maximum(length, 1e-9)[..., None]
    base = quads[:, :, None, :] + along[None, None, :, None] * d[:, :, None, :]      # (n, 4, s, 2)
    pts = base[:, :, :, None, :] + offsets_px[None, None, None, :, None] * normal[:, :, None, None, :]
    in_frame = (pts[..., 0] >= 0) & (pts[..., 1] >= 0) & (pts[..., 0] <= w - 1) & (pts[..., 1] <= h - 1)  # (n, 4, s, o)
    sample_inside = in_frame.all(axis=3)
    inside = sample_inside.reshape(n, -1).all(axis=1)
    flat = pts.reshape(-1, len(offsets_px), 2).astype(np.float32)
    values = cv2.remap(gray, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return EdgeProfiles(base_px=base, normal=normal, offsets_px=np.asarray(offsets_px, dtype=np.float64),
                        values=values.reshape(n, 4, len(along), len(offsets_px)), length_px=length, inside=inside, sample_inside=sample_inside,
                        point_inside=in_frame)


def step_positions(values: NDArray[np.float32], offsets_px: NDArray[np.float64], *, falling_inwards: bool = False) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Each profile's step position along the normal (px) and whether it had one.

    values : (..., o) profiles sampled at ``offsets_px`` (o,), evenly spaced. The step is the centroid of the
    upper half of the gradient's magnitude (of the gradient itself with ``falling_inwards``: only a step from
    bright outside to dark inside counts, as a black border on a white base gives).
    """
    step = float(offsets_px[1] - offsets_px[0])
    diff = np.diff(values, axis=-1)
    grad = np.clip(diff, 0.0, None) if falling_inwards else np.abs(diff)  # offsets grow outwards: bright outside is a rise
    weight = np.clip(grad - 0.5 * grad.max(axis=-1, keepdims=True), 0.0, None)
    total = weight.sum(axis=-1)
    safe = np.where(total > 0, total, 1.0)
    pos = offsets_px[0] + (weight @ (np.arange(grad.shape[-1]) + 0.5)) / safe * step
    return pos, total > 0


def fit_edge_lines(edge_px: NDArray[np.float64], keep: NDArray[np.bool_] | None = None
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Total-least-squares lines through edge points (n, 4, s, 2), each over its ``keep`` (n, 4, s) samples (all if None).

    Returns point (n, 4, 2) (the kept samples' centroid), direction (n, 4, 2) (unit), the signed distance of every
    sample from its line (n, 4, s) px, and the RMS of the kept ones (n, 4) (nan where fewer than 2 are kept).
    """
    if keep is None:
        keep = np.ones(edge_px.shape[:3], dtype=bool)
    wgt = keep.astype(np.float64)
    count = wgt.sum(axis=2)                                                          # (n, 4)
    safe = np.maximum(count, 1.0)
    point = np.einsum("nks,nksi->nki", wgt, edge_px) / safe[..., None]
    rel = edge_px - point[:, :, None, :]
    scatter = np.einsum("nks,nksi,nksj->nkij", wgt, rel, rel)                        # (n, 4, 2, 2)
    _, vecs = np.linalg.eigh(scatter)
    direction = vecs[..., :, 1]                                                      # the principal axis: largest eigenvalue
    across = np.stack([-direction[..., 1], direction[..., 0]], axis=2)
    off_line = np.einsum("nksi,nki->nks", rel, across)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(count >= 2, np.sqrt(np.einsum("nks,nks->nk", wgt, off_line**2) / safe), np.nan)
    return point, direction, off_line, rms


def edge_corners(point: NDArray[np.float64], direction: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Corners (n, 4, 2) as the intersections of edge k - 1 and edge k (lines (n, 4) through ``point`` along ``direction``),
    and whether all four lines of a tag cross (n,)."""
    # Corner k lies on edge k-1 (corner k-1 -> k) and on edge k (corner k -> k+1): p1 + s d1 = p2 + t d2.
    p1, d1 = np.roll(point, 1, axis=1), np.roll(direction, 1, axis=1)
    p2, d2 = point, direction
    det = -d1[..., 0] * d2[..., 1] + d2[..., 0] * d1[..., 1]
    ok = (np.abs(det) > 1e-12).all(axis=1)
    rhs = p2 - p1
    s_par = (-rhs[..., 0] * d2[..., 1] + rhs[..., 1] * d2[..., 0]) / np.where(np.abs(det) > 1e-12, det, 1.0)
    return p1 + s_par[..., None] * d1, ok
