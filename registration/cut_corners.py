"""Tag corners that the frame's edge made: where the edge cuts a tag, its outline's corner there is not the tag's.

A tag partly outside the camera frame, named on its outline (:mod:`.tag_hypotheses`), has an outline whose corners
on the frame's edge are where the tag's sides leave the frame, not its corners: the tag's corner lies beyond, on
the same side, by as much as the part of the side the frame cut off (seed 3001's marker 41: 12 and 28 px; seed
13000's marker 38, flat markers, AP+lateral: 28 and 20 px, which put the axis 3.3 mm off at the entry under a 2.6 mm
bound). Such a corner still shows where its side runs, across it, to a few pixels. Left out altogether, the tag
loses that too (tried: a registration on such a tag, seed 14601, went 0.83 -> 1.40 mm). So the tag's own pose
(:class:`.video_markers.VideoMarkerLocator`) and the joint solve take it with a slide: its noise along its side as
large as the tag's side (:func:`cut_corner_slides_px`), across it as any outline corner's.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["cut_corner_slides_px", "across_slides", "EDGE_PX"]

# A corner within this of the frame's outermost pixel centres (px), either side, lies on its edge: an outline that
# the frame cuts runs along the edge's pixels (0 or width - 1); a tag the detector found whole keeps some pixels
# from it, and a tag recovered on its edges has its corners beyond the frame where its edges' lines cross.
EDGE_PX = 0.5


def _on_edge(point_px: NDArray[np.float64], width: int, height: int, edge_px: float) -> bool:
    """Within ``edge_px`` of one of the frame's edge lines (its outermost pixel centres), on either side: a corner
    farther beyond the frame is the crossing of two fitted edges (:mod:`.tag_recovery`), a corner of the tag."""
    x, y = float(point_px[0]), float(point_px[1])
    return min(abs(x), abs(y), abs(x - (width - 1)), abs(y - (height - 1))) <= edge_px


def cut_corner_slides_px(corners_px: NDArray[np.float64], *, width: int, height: int, edge_px: float = EDGE_PX) -> NDArray[np.float64]:
    """Per corner of a tag's outline (4, 2) px, the slide (4, 2) px the joint solve gives it (``corner_slide_px``).

    A corner on the frame's edge with one neighbour on it and one off it is where the side from the neighbour off
    the edge leaves the frame: its slide points along that side, as long as the tag's longest side with both
    corners off the edge (its whole length: the part cut off is at most that), or its longest side where none is.
    Every other corner: (0, 0). ``width``, ``height``: the frame's size in pixels.
    """
    corners = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    if not np.all(np.isfinite(corners)):
        raise ValueError(f"a tag's corners must be finite, got {corners.tolist()}")
    on = [_on_edge(c, width, height, edge_px) for c in corners]
    slides = np.zeros((4, 2))
    if not any(on):
        return slides
    sides = [(k, (k + 1) % 4) for k in range(4)]
    whole = [float(np.linalg.norm(corners[a] - corners[b])) for a, b in sides if not on[a] and not on[b]]
    length = max(whole) if whole else max(float(np.linalg.norm(corners[a] - corners[b])) for a, b in sides)
    for k in range(4):
        off = [n for n in ((k - 1) % 4, (k + 1) % 4) if not on[n]]
        if not on[k] or len(off) != 1:
            continue
        d = corners[k] - corners[off[0]]
        norm = float(np.linalg.norm(d))
        if norm > 0:
            slides[k] = d / norm * length
    return slides


def across_slides(errors_px: NDArray[np.float64], slides_px: NDArray[np.float64]) -> NDArray[np.float64]:
    """Corner errors (N, 2) px with their components along their slides (N, 2) removed: a corner with a slide is
    measured across it only; one without keeps its error."""
    slides = np.asarray(slides_px, dtype=np.float64).reshape(-1, 2)
    length = np.linalg.norm(slides, axis=1, keepdims=True)
    u = np.divide(slides, length, out=np.zeros_like(slides), where=length > 0)
    return errors_px - np.sum(errors_px * u, axis=1, keepdims=True) * u
