"""Tags whose code reads only in part, named among the markers fluoroscopy posed and the camera has not found.

A tag blurred by the drill's motion, washed by a highlight on its gloss, or specked with blood still thresholds to
a dark four-sided outline (:func:`.tag_search.tag_candidates`), but its code reads in a handful of cells and its
edges show no clean border step: neither the dictionary-wide identity rule of :mod:`.tag_search` nor the edge fit
of :mod:`.tag_recovery` accepts it, and a frame whose every posed marker's tag is like that is refused (on the
operating-room twin, most refusals of a frame whose tags are in view). A registration on one marker, whose
neighbours' tags are like that, cannot predict them well enough to recover them, and rests on that one marker.

Here each outline's code is read at its four rotations (on the edges' fitted corners where
:func:`.tag_recovery.fit_tag_edges` fits them, on the outline's otherwise) and judged only among ``wanted``: the
ArUco ids of the markers fluoroscopy posed that the frame has not found. An outline is named when at least
``MIN_CELLS`` cells are read, at least ``MIN_AGREEMENT`` of them agree with one wanted id (at its best rotation),
and every other wanted id agrees with at least ``MIN_MARGIN_CELLS`` fewer. One outline per id, the one with the
most cells agreeing.

A name so given is a hypothesis, not an identity: a handful of cells can agree with a wanted id by chance. The
caller lets a hypothesis into a registration only where the registration bears it out
(:func:`.pipeline.register_with_recovery`: the joint solve keeps it beside another marker it fits, the two
markers' places agreeing in the camera and in fluoroscopy). A name whose code also meets the dictionary-wide rule
of a tag found with no prediction (:func:`.tag_search.identify_quad`, 20 cells or more: the caller checks,
:attr:`.video_markers.VideoMarker.identified_by_code`) is an identity, and may stand alone. Its corners are as good
as the outline, a few pixels (:data:`OUTLINE_CORNER_SIGMA_PX`): the joint solve weighs them so.

Given ``rivals`` (the ids of the marker set in the dictionary), each hypothesis also records how its cells agree with
the best of them other than the name, at any rotation, and with the name at its other rotations
(``set_runner_up_agreeing``). A name that leads that by ``MIN_MARGIN_CELLS`` is the only tag of the set the cells
read can be (:attr:`TagHypothesis.named_among_set`): a highlight only lifts a black cell to white, and a lifted or
clipped cell is left unread, so the cells read are the tag's own. Where nothing else registers the frame, the caller
lets such a name stand alone when its edges were also fitted to a view of its square
(:attr:`.video_markers.VideoMarker.named_among_set`), flagged unreliable (nothing checks it):
:func:`.pipeline._registration_with_named_tags`.

Pure math: numpy and OpenCV's image functions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .tag_recovery import dictionary_codes, fit_tag_edges, read_code
from .tag_search import tag_candidates

__all__ = ["TagHypothesis", "outline_hypotheses", "OUTLINE_CORNER_SIGMA_PX", "MIN_CELLS", "MIN_AGREEMENT", "MIN_MARGIN_CELLS"]

# The corner noise (1 sigma, px) of a tag placed by its outline alone. On the operating-room twin (seeds 6104-7004,
# tags of refused frames and of frames registered on one marker, about 150 px across) the outlines named this way
# lay 2.5-6.5 px from the truth at their worst corner for 19 of 27, 11-17 px for 6 (a bite taken by a highlight);
# the 111 registrations they joined over seeds 6100-7005 (M = 5) lay within their 90 % bounds for 96 % of positions
# and 95 % of angles. 4 px (the RMS measured over 20 named outlines, 4.1 px) covered no better: see
# docs/identity_and_error.md, "Tags named among the posed markers".
OUTLINE_CORNER_SIGMA_PX = 3.0
MIN_CELLS = 6             # code cells read, at least
MIN_AGREEMENT = 0.9       # of them agreeing with the named id
MIN_MARGIN_CELLS = 2      # over every other wanted id


@dataclass(frozen=True, kw_only=True)
class TagHypothesis:
    """An outline named among the wanted ids.

    corners_px : (4, 2) its corners, OpenCV order (TL, TR, BR, BL) for the named id's rotation.
    edges_fitted : the corners are its edges' fitted crossings (:func:`.tag_recovery.fit_tag_edges`), not the outline's.
    cells_read, cells_agreeing : code cells read, and those agreeing with ``aruco_id``.
    runner_up_agreeing : the cells agreeing with the best other wanted id (any rotation); -1 when none is wanted.
    set_runner_up_agreeing : the cells agreeing with the best of ``rivals`` other than ``aruco_id`` (any rotation) and with
        ``aruco_id`` at its other rotations; -1 when no rivals were given.
    """

    aruco_id: int
    corners_px: NDArray[np.float64]
    edges_fitted: bool
    cells_read: int
    cells_agreeing: int
    runner_up_agreeing: int
    set_runner_up_agreeing: int = -1

    @property
    def named_among_set(self) -> bool:
        """Whether the cells read name ``aruco_id`` among the set's ids (``rivals``) by ``MIN_MARGIN_CELLS``."""
        return self.set_runner_up_agreeing >= 0 and self.cells_agreeing - self.set_runner_up_agreeing >= MIN_MARGIN_CELLS


def outline_hypotheses(gray: NDArray[np.uint8], *, dictionary: str, wanted: Sequence[int], exclude_px: Sequence[NDArray[np.float64]] = (),
                       half_above_px: int = 800, tolerance_px: float = 6.0, rivals: Sequence[int] = ()) -> list[TagHypothesis]:
    """The outlines of a grayscale frame (H, W) uint8 named among ``wanted`` (ArUco ids of ``dictionary``) by the rule of
    the module docstring, at most one per id, sorted by id.

    ``exclude_px``: (4, 2) corners of tags already found (their outlines are skipped). ``half_above_px``: see
    :func:`.tag_search.tag_candidates`. ``tolerance_px``: how far each fitted edge may lie from the outline.
    ``rivals``: the ArUco ids of ``dictionary`` that may lie in the field (the marker set's), for
    ``set_runner_up_agreeing``.
    """
    ids = sorted({int(i) for i in wanted})
    if not ids:
        return []
    codes = dictionary_codes(dictionary)
    if ids[0] < 0 or ids[-1] >= len(codes):
        raise ValueError(f"wanted ids {ids} are not all ids of {dictionary} (0-{len(codes) - 1})")
    flat = codes.reshape(len(codes), -1)[ids]                                         # (w, s * s)
    set_ids = sorted({int(i) for i in rivals} | set(ids)) if len(rivals) else []
    set_flat = codes.reshape(len(codes), -1)[set_ids]                                 # (r, s * s)
    gray_f = gray.astype(np.float32)
    best: dict[int, TagHypothesis] = {}
    # Outlines as they are: a corner put beyond the frame's edge by two sides' lines is for the search, whose edge fit
    # places it; an outline named here keeps its own corners.
    for quad in tag_candidates(gray, half_above_px=half_above_px, exclude_px=exclude_px, beyond_edge=False):
        edges = fit_tag_edges(gray_f, quad, tolerance_px=tolerance_px)
        corners = edges.corners_px if edges.accepted else quad
        agree = np.zeros((4, len(ids)), dtype=np.int64)
        set_agree = np.zeros((4, len(set_ids)), dtype=np.int64)
        n_read = -1
        for k in range(4):
            read = read_code(gray_f, np.roll(corners, -k, axis=0), code_size=codes.shape[1], partial=True)
            if read.reason:
                break
            agree[k] = ((flat == read.bits[None, :]) & read.known[None, :]).sum(axis=1)
            set_agree[k] = ((set_flat == read.bits[None, :]) & read.known[None, :]).sum(axis=1)
            n_read = int(read.known.sum())
        else:
            per_id = agree.max(axis=0)                                                # (w,) each id at its best rotation
            order = np.argsort(-per_id, kind="stable")
            top = int(order[0])
            mine = int(per_id[top])
            runner_up = int(per_id[order[1]]) if len(ids) > 1 else -1
            if n_read < MIN_CELLS or mine < MIN_AGREEMENT * n_read or (runner_up >= 0 and mine - runner_up < MIN_MARGIN_CELLS):
                continue
            aruco_id = ids[top]
            if aruco_id in best and best[aruco_id].cells_agreeing >= mine:
                continue
            k = int(np.argmax(agree[:, top]))
            set_runner_up = -1
            if set_ids:
                others = set_agree.copy()
                others[k, set_ids.index(aruco_id)] = -1                               # the name at its own rotation
                set_runner_up = int(others.max())
            best[aruco_id] = TagHypothesis(aruco_id=aruco_id, corners_px=np.roll(corners, -k, axis=0), edges_fitted=bool(edges.accepted),
                                           cells_read=n_read, cells_agreeing=mine, runner_up_agreeing=runner_up,
                                           set_runner_up_agreeing=set_runner_up)
    return [best[i] for i in sorted(best)]
