"""Marker localisation in drill-camera video: ArUco detection, sub-pixel corners, IPPE pose, X_D.

Per frame: detect the 6x6 tags, refine corners to sub-pixel, solve each tag's
pose with IPPE for squares (both solutions, the better reprojection wins, then
Levenberg-Marquardt refinement), and move from the tag centre to the central BB
by the marker's tag offset: ``X_D = camera_from_tag @ (-tag_center_mm)``
(``(0, 0, -2)`` mm in the default design).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .aruco_detect import detect_aruco
from .camera import PinholeCamera
from .cut_corners import across_slides, cut_corner_slides_px
from .markers import MarkerSet
from .tag_border import border_shift_px, code_cells, moved_outline
from .tag_edges import edge_corners, edge_profiles, fit_edge_lines, step_positions
from .tag_recovery import RECOVERED_CORNER_SIGMA_PX, SQUARE_FIT_MAX_CORNER_SIGMA_PX, BorderSteps, dictionary_codes, fit_tag_edges, read_code, recover_tag
from .tag_square_fit import SquareFit, fit_square_to_edges
from .tag_hypotheses import OUTLINE_CORNER_SIGMA_PX, outline_hypotheses
from .tag_search import identify_quad, search_tags
from .transforms import make_transform

__all__ = ["VideoMarker", "VideoDetections", "VideoMarkerLocator", "detect_tags", "tag_object_points", "placed_elsewhere", "PLACED_MARGIN_PX",
           "RECOVERED_MAX_SQUARE_RMS_PX", "DISPLACED_CORNER_CHECK_PX", "SQUARE_MISFIT_MIN_PX", "MISREAD_MIN_CELLS", "with_markers"]

# Two tags of the marker set cannot be confused by a recovery when the registration places them at least this much
# farther apart than its two predictions can both be off (:func:`placed_elsewhere`): about a quarter of a small
# (60 px) tag's side.
PLACED_MARGIN_PX = 16.0

# A recovered tag's four corners must be a view of its square (the tag's size, this camera) within this RMS, px
# (``VideoMarker.reprojection_error_px``). Measured on a foreshortened, gloved and blurred tag (twin seed 6104,
# marker 45, recovered from 147 predictions up to 34 px off): every placement within 2.6 px of the truth fitted its
# square within 0.49 px, the four 5-9 px off (one edge fitted to the wrong step) at 1.49-2.63 px.
RECOVERED_MAX_SQUARE_RMS_PX = 1.0

# A tag ArUco decoded whose corners fit a view of its square worse than this RMS, px, is tried from three of its
# corners (:meth:`VideoMarkerLocator._one_corner_displaced`). Under every camera degradation with the surgeon's
# markers (twin seeds 5000-5029, 3 poses, 233 decoded tags) 221 fitted within 0.3 px (corners at most 2.65 px off),
# 11 within 0.3-0.6 px (at most 3.0 px), and the two over 1.5 px had a corner 6.5 and 8.6 px off; a rendered tag
# with a gloved corner 10 px off fitted within 0.85 px.
DISPLACED_CORNER_CHECK_PX = 0.5
# How far (px) the edge search looks about a tag predicted from three of its corners: as far as a recovery from a
# registration's prediction looks (``VideoMarkerLocator.recover``). The three are not exact either: where the glove's
# cut is longer, ArUco's outline moves every corner by 5-7 px and the displaced one by 20.
REPAIR_TOLERANCE_PX = 8.0
# A tag's corners that fit a view of its square within this RMS, px, are as clean as a tag's: the joint solve charges
# a misfit above it as extra corner noise (:func:`.joint_solve.square_misfit_noise_px`), and the repair of a displaced
# corner stops at a placement this good.
SQUARE_MISFIT_MIN_PX = 0.2
# A detected tag's corner noise from its own edges (:func:`_edge_refined`): each corner is the crossing of two lines
# fitted to samples of the edges' middle 60 %, which scatter about their lines by s px RMS; a blur w px wide leaves
# about 0.6 side / w of them independent (n, 2 to the samples taken). A line so fitted places its ends, half a side
# from its middle, to s sqrt((1 + 12 (0.5 / 0.6)^2) / n) = 3.05 s / sqrt(n); EDGE_SIGMA_GAIN times that is the tag's
# stated corner noise (``VideoMarker.edge_sigma_px``), which the joint solve charges where it exceeds its own
# (:func:`.video_fluoro._corner_extra_px`). Most of a tag's corner error moves its corners as another view of the
# square would (a tilt, a turn): its pose absorbs it and no residual shows it, but its edges do. Against the twin's
# truth under every camera degradation (seeds 9200-9207, 4 frames each, the corners' error less its shift and scale,
# RMS): at 1280x720 (85 tags) the bare prediction (gain 1) states 0.11 px RMS where the tags were 0.15 px off, at
# 640x480 (88 tags) 0.20 px where they were 0.47 px off; the gain of 2 states 0.22 and 0.39 px. At 1280x720 that stays
# under the joint solve's own 0.3 px for nearly every tag: only the smaller frame's tags are charged more.
EDGE_SIGMA_PER_SAMPLE = 3.05
EDGE_SIGMA_GAIN = 2.0


def edge_corner_sigma_px(edge_rms_px: NDArray[np.float64], side_px: float, step_width_px: float, *, samples: int = 24) -> float:
    """A tag's corner noise (1 sigma, px) from its four edges' line fits: ``edge_rms_px`` (4,) each edge's samples' RMS
    distance from its line, ``side_px`` the tag's mean side, ``step_width_px`` the edges' step width (the blur's
    extent); see :data:`EDGE_SIGMA_GAIN`. NaN where an edge's scatter is not finite."""
    s = float(np.sqrt(np.mean(np.square(np.asarray(edge_rms_px, dtype=np.float64)))))
    n = float(np.clip(0.6 * side_px / max(step_width_px, 1.0), 2.0, samples))
    return EDGE_SIGMA_GAIN * EDGE_SIGMA_PER_SAMPLE * s / np.sqrt(n)


# A tag ArUco decoded is misread when its code cells, read again through its refined corners
# (:func:`.tag_recovery.read_code`, which leaves a cell under a highlight, a glove's edge or blur between the levels
# unread), disagree with its id in at least MISREAD_MIN_CELLS cells and another id of the marker set's (at any
# rotation) agrees with more of them than its id does. Under every camera degradation (twin seeds 3000-3011, and
# 5000-5011 with the surgeon's markers; 3 poses) the 207 tags ArUco decoded rightly read 10-36 cells, none
# disagreeing; the one it misread (seed 3010, second pose: marker 25's tag, foreshortened and blurred, decoded as 43
# while 43's own was decoded too) read 10, 8 agreeing with 43 and 9 with 25. On a real photograph (a ChArUco board's
# 26 px tags, 3 px cells, blurred 1.5-2.5 px; the board's 17 ids the set) rightly decoded tags read 11-23 cells with
# up to 8 disagreeing, and once another of the board's ids agreed with as many (15 of 23) as the tag's own:
# disagreement alone, or a tie, would set such tags aside. ArUco's decoding stands unless the set holds a better fit.
MISREAD_MIN_CELLS = 2


@dataclass(frozen=True, kw_only=True)
class VideoMarker:
    """One localised marker.

    corners_px : (4, 2) sub-pixel tag corners, OpenCV order (TL, TR, BR, BL).
    camera_from_tag : (4, 4) tag pose in frame D.
    position_camera_mm : (3,) X_D, the central BB in frame D.
    covariance_mm2 : (3, 3) first-order covariance of X_D from the corner noise.
    reprojection_error_px : RMS corner reprojection error of the chosen pose.
    recovered : the detector missed the tag; it was found where the registration predicted it and its identity
        verified by the code cells that could be read (:mod:`.tag_recovery`).
    corner_sigma_px : the corner noise (1 sigma, px) ``covariance_mm2`` was computed with: larger for a recovered
        tag (up to one corner is the crossing of two partly hidden edges).
    edge_sigma_px : a detected tag's corner noise as its own edges' scatter states it (:func:`edge_corner_sigma_px`;
        0 where its edges were not fitted, and for a recovered tag): the joint solve charges it where it exceeds its
        own (:func:`.video_fluoro._corner_extra_px`).
    named_among_posed : its code read only in part, it was named among the markers posed in fluoroscopy that the
        frame had not found (:mod:`.tag_hypotheses`), and a registration bore the name out; also ``recovered``.
    identified_by_code : ``named_among_posed`` only: its code, though read in part, also meets the dictionary-wide
        rule of a tag found with no prediction (:func:`.tag_search.identify_quad`: 20 cells or more read, 90 % of
        them agreeing, every other id of the dictionary at least 4 behind): the name stands without another marker
        beside it. Its corners are still its outline's.
    named_among_set : ``named_among_posed`` only: the cells read name it among every tag of the marker set, at every
        rotation, by :data:`.tag_hypotheses.MIN_MARGIN_CELLS` (:attr:`.tag_hypotheses.TagHypothesis.named_among_set`),
        and its corners are its fitted edges' crossings, a view of its square (within ``SQUARE_MISFIT_MIN_PX``): the
        name may stand alone, flagged unreliable, where nothing else registers the frame.
    """

    marker_id: int
    corners_px: NDArray[np.float64]
    camera_from_tag: NDArray[np.float64]
    position_camera_mm: NDArray[np.float64]
    covariance_mm2: NDArray[np.float64]
    reprojection_error_px: float
    recovered: bool = False
    corner_sigma_px: float = 0.1
    edge_sigma_px: float = 0.0
    named_among_posed: bool = False
    identified_by_code: bool = False
    named_among_set: bool = False


@dataclass(frozen=True, kw_only=True)
class VideoDetections:
    markers: tuple[VideoMarker, ...]
    ignored_ids: tuple[int, ...]
    image_size: tuple[int, int]
    # Markers of the set whose tag ArUco decoded but whose corners are no view of its square (or a poor one, its edges
    # not fitted) and could not be placed from three of them (:meth:`VideoMarkerLocator.locate`): not in ``markers``,
    # left for the recovery to find.
    unplaced_ids: tuple[int, ...] = ()
    # Ids of the marker set that ArUco decoded on a tag whose code cells, read again, another id of the set fits
    # better (``MISREAD_MIN_CELLS``; the marker may still be in ``markers``, found at its own tag), or at two places in
    # one frame (then not in ``markers``: neither place is taken).
    misread_ids: tuple[int, ...] = ()

    def by_id(self) -> dict[int, VideoMarker]:
        return {m.marker_id: m for m in self.markers}


def with_markers(video: VideoDetections, found: Iterable[VideoMarker]) -> VideoDetections:
    """``video`` with the markers ``found`` added (a marker placed so is no longer unplaced)."""
    found = tuple(found)
    ids = {m.marker_id for m in found}
    return replace(video, markers=tuple(sorted(video.markers + found, key=lambda m: m.marker_id)),
                   unplaced_ids=tuple(i for i in video.unplaced_ids if i not in ids))


def _dictionary(name: str):
    if not hasattr(cv2.aruco, name):
        raise ValueError(f"unknown ArUco dictionary '{name}' (e.g. DICT_6X6_250)")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def _detector(dictionary: str, *, refine: bool = True) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX if refine else cv2.aruco.CORNER_REFINE_NONE
    params.cornerRefinementWinSize = 4
    params.cornerRefinementMinAccuracy = 0.01
    params.adaptiveThreshWinSizeMin = 7
    params.adaptiveThreshWinSizeMax = 31
    params.adaptiveThreshWinSizeStep = 12
    params.minMarkerPerimeterRate = 0.05
    # Correct up to the dictionary's full maxCorrectionBits (5 in DICT_6X6_250, whose ids are >= 11 bits apart, so
    # decoding stays unique) instead of 60 % of it: a glare spot on a glossy tag flips several black cells white.
    # Measured (benchmarks/tag_detection.py, seeds 3000-3002 x 4 poses): tag_glare 48 -> 51 of 60 tags, no false ids.
    params.errorCorrectionRate = 1.0
    return cv2.aruco.ArucoDetector(_dictionary(dictionary), params)


def _gray(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise ValueError(f"expected a grayscale (H, W) or BGR (H, W, 3) image, got shape {img.shape}")
    return img


def _edge_refined(gray: NDArray[np.float32], quads: NDArray[np.float64], *, samples: int = 24, half_px: float = 4.0, step_px: float = 0.5,
                  max_residual_px: float = 0.35) -> list[tuple[NDArray[np.float64], float] | None]:
    """Each tag's corners (4, 2) as the intersections of lines fitted to the four outer edges of its black border, with
    the corner noise (px) its edges' scatter states (:func:`edge_corner_sigma_px`), or None.

    quads : (n, 4, 2) detected corners of n tags; one result per tag.

    Motion blur and defocus round a tag's corners, so a corner detector (cv2.cornerSubPix) is pulled
    inwards (1.3 px RMS under motion blur), while a straight edge blurred by a symmetric kernel keeps its
    place. Each edge is sampled over its middle 60 % (away from the rounded corners and a glove over
    one), its position along the normal taken as the centroid of the gradient's upper half, and a line
    fitted (total least squares): +-``half_px`` about the detector's corners, then, for a tag whose step is wider
    than 3 px (motion blur) or whose first fit failed, twice as far about the lines found, with the samples off
    their line left out. None when an edge does not look
    straight in either pass (a sample off the frame, blood on it): the caller then fits the edges' clean stretches
    (``VideoMarkerLocator._edges_despite_occlusion``), else keeps the sub-pixel corners. Every
    tag's edges are sampled in one remap and fitted in one batch (a per-tag loop cost ~0.9 ms a tag on the frame
    path, most of it numpy's per-call overhead).
    """
    quads = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
    n = len(quads)
    if n == 0:
        return []
    along = np.linspace(0.2, 0.8, samples)

    def lines(around: NDArray[np.float64], reach_px: float, falling_inwards: bool, trim: bool = False
              ) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64] | None, NDArray[np.float64]]:
        """Corners (m, 4, 2), whether found (m,), (first pass only, else None) each tag's median step width
        (m,): px where the gradient is over half its peak (about 2 px for a sharp edge, the blur's extent for a
        wide one), and each edge's samples' RMS distance from its line (m, 4)."""
        offsets = np.arange(-reach_px, reach_px + step_px / 2, step_px)
        prof = edge_profiles(gray, around, along=along, offsets_px=offsets)
        width = None
        if not trim:
            grad = np.abs(np.diff(prof.values, axis=-1))
            width = np.median((grad > 0.5 * grad.max(axis=-1, keepdims=True)).sum(axis=-1).reshape(len(around), -1), axis=1) * step_px
        good = (prof.length_px >= 8.0).all(axis=1) & prof.inside
        shift, stepped = step_positions(prof.values, offsets, falling_inwards=falling_inwards)
        edge = prof.base_px + shift[..., None] * prof.normal[:, :, None, :]          # (n, 4, samples, 2)
        if not trim:
            good &= stepped.reshape(len(around), -1).all(axis=1)
            point, direction, _, rms = fit_edge_lines(edge)
            good &= rms.max(axis=1) <= max_residual_px
        else:
            # Samples off the line by over 3 robust sigmas (at least 0.4 px) left out, twice, as tag recovery
            # does: a blood speck or a glare spot on the border moves a few samples, not the edge. An edge keeps
            # 75 % of its samples; a widely blurred edge scatters more (0.4-0.5 px RMS) and still places its line
            # to about 0.1 px over 24 samples, far better than a blurred corner (1.3 px).
            keep = stepped.copy()
            for _ in range(2):
                _, _, off, _ = fit_edge_lines(edge, keep)
                spread = np.nanmedian(np.where(keep, np.abs(off), np.nan), axis=2)           # (n, 4)
                keep = stepped & (np.abs(off) <= np.maximum(3.0 * 1.4826 * np.nan_to_num(spread), 0.4)[..., None])
            point, direction, _, rms = fit_edge_lines(edge, keep)
            good &= (keep.mean(axis=2) >= 0.75).all(axis=1) & (np.nan_to_num(rms, nan=np.inf).max(axis=1) <= 1.5 * max_residual_px)
        found, crossed = edge_corners(point, direction)
        return found, good & crossed, width, rms

    corners, ok, width, rms = lines(quads, half_px, False)
    # Again, centred on the lines found, over twice the reach: a motion blur wider than the first window (up to
    # 12 px against +-4 px) leaves a flat gradient across it, whose centroid is the window's centre, i.e. the
    # detector's corners, which blur pulls inwards. Only a rise from the black border out to the white base
    # counts in the wider window: a small tag's first code cell (white inside black) lies within it.
    # Only where the step is wider than 3 px (a sharp edge's is about 2 px: the first window holds it whole) or
    # the first pass failed (its edges' steps flattened by the blur): sharp frames keep their corners as before.
    ok &= np.linalg.norm(corners - quads, axis=2).max(axis=1) <= half_px
    redo = np.nonzero(~ok | (width > 3.0))[0]
    if len(redo):
        again, ok2, _, rms2 = lines(np.where(ok[redo, None, None], corners[redo], quads[redo]), 2.0 * half_px, True, trim=True)
        # The detector's corners can lie 4-5 px inside a tag blurred by 12 px: the second pass's corners may lie as
        # far from them as its own reach.
        ok2 &= np.linalg.norm(again - quads[redo], axis=2).max(axis=1) <= 2.0 * half_px
        corners[redo] = np.where(ok2[:, None, None], again, corners[redo])
        rms[redo] = np.where(ok2[:, None], rms2, rms[redo])
        ok[redo] |= ok2
    side = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).mean(axis=1)
    return [(corners[i], edge_corner_sigma_px(rms[i], float(side[i]), float(width[i]), samples=samples)) if ok[i] else None for i in range(n)]


def detect_tags(image: NDArray[np.uint8], *, dictionary: str = "DICT_6X6_250") -> list[tuple[int, NDArray[np.float64]]]:
    """All tags of ``dictionary`` in the image: (id, corners (4, 2)), no camera needed."""
    ids, corners = detect_aruco(_detector(dictionary), _gray(image))
    return list(zip(ids, corners))


def _grid(step_px: float, reach_px: float) -> NDArray[np.float64]:
    """(K, 2) shifts (px) on a square grid of ``step_px`` out to ``reach_px`` (per axis), nearest first, (0, 0) first."""
    n = int(np.floor(max(reach_px, 0.0) / step_px)) if step_px > 0 else 0
    ax = np.arange(-n, n + 1) * step_px
    grid = np.stack(np.meshgrid(ax, ax), axis=-1).reshape(-1, 2)
    return grid[np.argsort(np.hypot(grid[:, 0], grid[:, 1]), kind="stable")]


def placed_elsewhere(other_px: NDArray[np.float64], here_px: NDArray[np.float64], *, tolerance_px: float, reach_px: float) -> bool:
    """Whether a tag predicted at ``other_px`` (k, 4, 2) cannot be the one found near ``here_px`` (m, 4, 2) (candidates:
    a marker's two mirror poses, the registration's two solutions): every candidate's centre lies farther from every
    one here than two predictions of one registration can both be off, 2 (``tolerance_px`` + ``reach_px`` sqrt 2)
    (each is found up to ``tolerance_px`` from its prediction, shifted up to ``reach_px`` per axis), plus
    ``PLACED_MARGIN_PX``. k = 0 (the tag predicted behind the camera) is elsewhere."""
    other = np.asarray(other_px, dtype=np.float64).reshape(-1, 4, 2).mean(axis=1)
    here = np.asarray(here_px, dtype=np.float64).reshape(-1, 4, 2).mean(axis=1)
    if not len(other):
        return True
    limit = 2.0 * (tolerance_px + reach_px * np.sqrt(2.0)) + PLACED_MARGIN_PX
    return bool(np.linalg.norm(other[:, None] - here[None], axis=-1).min() > limit)


def tag_object_points(tag_size_mm: float) -> NDArray[np.float64]:
    """(4, 3) tag corners in the tag frame (IPPE_SQUARE order)."""
    h = tag_size_mm / 2.0
    return np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)


@dataclass(frozen=True)
class _TagSpec:
    marker_id: int
    object_points: NDArray[np.float64]  # (4, 3) tag corners in the tag frame
    bb_tag_mm: NDArray[np.float64]      # (3,) the central BB in the tag frame
    dictionary: str                     # the ArUco dictionary and id the tag is printed with
    aruco_id: int


class VideoMarkerLocator:
    """Localises the configured markers in drill-camera frames.

    With ``marker_set`` (markers.json), every marker's own ArUco dictionary, ArUco id, tag size and tag
    offset are used (the tag frame has the marker's axes, its origin at the marker's ``tag_center_mm``);
    otherwise one ``dictionary``, ``tag_size_mm`` and ``tag_to_bb_offset_mm`` for ``marker_ids``, ArUco id =
    marker id. ``border_shift``: each tag's outline is moved to where the width of its black border puts it
    (:mod:`.tag_border`: where a tag's white base clips, its edges' steps lie inside the truth); False keeps the steps.
    """

    def __init__(
        self,
        *,
        camera: PinholeCamera,
        marker_ids: Iterable[int] = range(48),
        tag_size_mm: float = 30.0,
        tag_to_bb_offset_mm: float = 2.0,
        dictionary: str = "DICT_6X6_250",
        corner_sigma_px: float = 0.1,
        detect_below_px: int = 800,
        marker_set: MarkerSet | None = None,
        border_shift: bool = True,
    ) -> None:
        self.camera = camera
        self.border_shift = bool(border_shift)
        self.corner_sigma_px = float(corner_sigma_px)
        self.detect_below_px = detect_below_px
        specs: dict[str, dict[int, _TagSpec]] = {}
        if marker_set is not None:
            for m in marker_set.markers:
                per_dict = specs.setdefault(m.aruco_dictionary, {})
                if m.aruco_id in per_dict:
                    raise ValueError(f"markers {per_dict[m.aruco_id].marker_id} and {m.marker_id} share ArUco id {m.aruco_id} of {m.aruco_dictionary}")
                per_dict[m.aruco_id] = _TagSpec(m.marker_id, tag_object_points(m.tag_size_mm), -np.asarray(m.tag_center_mm, dtype=np.float64),
                                                m.aruco_dictionary, m.aruco_id)
        else:
            bb_tag = np.array([0.0, 0.0, -float(tag_to_bb_offset_mm)])
            specs[dictionary] = {int(i): _TagSpec(int(i), tag_object_points(float(tag_size_mm)), bb_tag, dictionary, int(i)) for i in marker_ids}
        self._specs = specs
        self.marker_ids = frozenset(spec.marker_id for per in specs.values() for spec in per.values())
        # Large frames are searched at half resolution (4x fewer pixels) and the corners refined at full resolution.
        self._detectors = {name: (_detector(name), _detector(name, refine=False)) for name in specs}

    def locate(self, image: NDArray[np.uint8]) -> VideoDetections:
        gray = _gray(image)
        h, w = gray.shape
        if (w, h) != (self.camera.width, self.camera.height):
            raise ValueError(f"frame is {w}x{h} but the camera calibration is for {self.camera.width}x{self.camera.height}")
        small = cv2.resize(gray, (w // 2, h // 2), interpolation=cv2.INTER_AREA) if w > self.detect_below_px else None
        found: list[VideoMarker] = []
        ignored: list[int] = []
        unplaced: list[int] = []
        misread: list[int] = []
        gray_f: NDArray[np.float32] | None = None
        for name, (fine, coarse) in self._detectors.items():
            if small is not None:
                ids, corners = detect_aruco(coarse, small)
                if ids:
                    pts = np.concatenate(corners) * 2.0 + 0.5
                    refined = cv2.cornerSubPix(gray, pts.astype(np.float32).reshape(-1, 1, 2), (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
                    corners = [refined[4 * i : 4 * i + 4].reshape(4, 2).astype(np.float64) for i in range(len(ids))]
            else:
                ids, corners = detect_aruco(fine, gray)
            if not ids:
                continue
            kept: list[tuple[int, _TagSpec, NDArray[np.float64]]] = []
            for aruco_id, c in zip(ids, corners):
                spec = self._specs[name].get(int(aruco_id))
                if spec is None:
                    ignored.append(int(aruco_id))
                    continue
                kept.append((int(aruco_id), spec, c.reshape(4, 2).astype(np.float64)))
            if not kept:
                continue
            if gray_f is None:
                gray_f = gray.astype(np.float32)
            edges = _edge_refined(gray_f, np.stack([quad for _, _, quad in kept]))
            for (aruco_id, spec, quad), fitted in zip(kept, edges):
                e, edge_sigma = fitted if fitted is not None else (None, None)
                if e is None:
                    e = self._edges_despite_occlusion(gray_f, quad, aruco_id=aruco_id, dictionary=name, spec=spec)
                marker = self._pose(spec, quad if e is None else e, edge_sigma_px=edge_sigma)
                if marker.reprojection_error_px > DISPLACED_CORNER_CHECK_PX:
                    # A poor view of its square: one corner may have moved (a glove's edge taken for the tag's). Placed
                    # from the other three where its edges and code bear that out and the square fits better; not so
                    # placed, it is left for the recovery to find when it is no view of its square at all, or when its
                    # edges could not be fitted either (nothing bears out any of its corners: a glove's cut at 20 deg
                    # left ArUco's a view of the square within 0.93 px, one of them 21.6 px off).
                    placed = self._one_corner_displaced(marker.corners_px, spec=spec, as_read=marker, place=lambda pred, aruco_id=aruco_id, spec=spec, name=name: recover_tag(
                        gray_f, pred, aruco_id=aruco_id, dictionary=name, tolerance_px=REPAIR_TOLERANCE_PX, rivals=(), partial=True,
                        square=lambda steps: self._square_fit(steps, spec=spec, predicted_px=pred)).corners_px)
                    if placed is not None:  # within DISPLACED_CORNER_CHECK_PX: better than the corners that sent it here
                        marker = placed
                    elif marker.reprojection_error_px > RECOVERED_MAX_SQUARE_RMS_PX or e is None:
                        unplaced.append(spec.marker_id)
                        continue
                if self._misread(gray_f, marker.corners_px, aruco_id=aruco_id, dictionary=name):
                    misread.append(spec.marker_id)
                    continue
                found.append(self._border_shifted(marker, spec=spec, gray=gray_f))
        # One tag per marker: an id decoded at two places in one frame names neither (a misread the code cells did not
        # catch, or a tag printed twice).
        twice = {m.marker_id for m in found if sum(o.marker_id == m.marker_id for o in found) > 1}
        return VideoDetections(markers=tuple(sorted((m for m in found if m.marker_id not in twice), key=lambda m: m.marker_id)),
                               ignored_ids=tuple(sorted(ignored)), image_size=(w, h), unplaced_ids=tuple(sorted(unplaced)),
                               misread_ids=tuple(sorted(set(misread) | twice)))

    def _misread(self, gray: NDArray[np.float32], corners_px: NDArray[np.float64], *, aruco_id: int, dictionary: str) -> bool:
        """The code cells of the tag with corners (4, 2) px (OpenCV order, as decoded), read again, contradict ``aruco_id``
        (``MISREAD_MIN_CELLS``) and another id of the marker set's in ``dictionary`` fits them better. A tag whose
        cells cannot be read at all is not contradicted."""
        codes = dictionary_codes(dictionary)
        got = read_code(gray, corners_px, code_size=codes.shape[1], partial=True)
        if got.reason:
            return False
        mine = int(((codes[aruco_id].reshape(-1) == got.bits) & got.known).sum())
        if int(got.known.sum()) - mine < MISREAD_MIN_CELLS:
            return False
        others = [a for a in self._specs[dictionary] if a != aruco_id]
        if not others:
            return False
        rotated = np.stack([np.rot90(codes[a], k).reshape(-1) for a in others for k in range(4)])
        return int(((rotated == got.bits[None, :]) & got.known[None, :]).sum(axis=1).max()) > mine

    def _one_corner_displaced(self, quad: NDArray[np.float64], *, spec: _TagSpec, as_read: VideoMarker,
                              place: Callable[[NDArray[np.float64]], NDArray[np.float64] | None], corner_sigma_px: float | None = None
                              ) -> VideoMarker | None:
        """A tag whose corners ``quad`` (4, 2) are a poor view of its square (``as_read``, its pose from them, fits worse
        than ``DISPLACED_CORNER_CHECK_PX``): placed from three of them, or None. ``place``: the tag's corners (4, 2) found
        about a prediction (4, 2), or None; ``corner_sigma_px``: the placed tag's corner noise (None: a detected tag's).

        A glove over one corner of a tag leaves ArUco's outline following the glove's edge there: that corner moves
        by up to tens of pixels while the other three stay (on the operating-room twin, 20 px on a 150 px tag, twin
        seed 4405; the 4-corner pose it gave was 100 deg off). Each corner is left out in turn; each pose of the
        tag that puts the other three where they are (P3P: up to four) predicts the whole tag, and ``place`` looks
        for it there: for a decoded tag the edge search that verifies a recovered tag (:func:`.tag_recovery.recover_tag`:
        the clean stretches of its edges, a hidden edge placed by the other three, its code cells); for an outline named
        among the posed markers its edges alone (:func:`.tag_recovery.fit_tag_edges`). Of the placements it accepts,
        those that are a good view of the square (within ``DISPLACED_CORNER_CHECK_PX``), the best fitting is taken:
        an outline cut by the frame's edge, placed 2-4 px off at every corner by its edges, fitted its square within
        0.79 px (twin seed 4701, random pair, second pose) and would have been used as a tag placed to 0.5 px. The
        corner farthest from where ``as_read``'s pose puts it is left out first, and a placement that fits as well as
        a clean tag (within ``SQUARE_MISFIT_MIN_PX``, which the joint solve charges nothing) ends the search: 3-5 edge
        searches a gloved tag in ``tests/test_tag_displaced_corner.py``'s frames. ``benchmarks/tag_detection.py``
        (glove; every camera degradation with the surgeon's markers) prints the time to locate a frame: 5.8 and 7.7 ms,
        against 5.9 and 7.1 ms before.
        """
        k, dist = self.camera.camera_matrix, self.camera.distortion
        best: VideoMarker | None = None
        rvec = cv2.Rodrigues(as_read.camera_from_tag[:3, :3])[0]
        fitted = cv2.projectPoints(spec.object_points, rvec, as_read.camera_from_tag[:3, 3], k, dist)[0].reshape(4, 2)
        for left_out in np.argsort(-np.linalg.norm(fitted - quad, axis=1)):
            keep = [j for j in range(4) if j != left_out]
            try:
                _, rvecs, tvecs = cv2.solveP3P(spec.object_points[keep], quad[keep], k, dist, flags=cv2.SOLVEPNP_P3P)
            except cv2.error:
                continue
            for rvec, tvec in zip(rvecs, tvecs):
                if float(np.ravel(tvec)[2]) <= 0.0:
                    continue
                pred = cv2.projectPoints(spec.object_points, rvec, tvec, k, dist)[0].reshape(4, 2)
                if not np.isfinite(pred).all():
                    continue
                corners = place(pred)
                if corners is None:
                    continue
                marker = self._pose(spec, corners, corner_sigma_px=corner_sigma_px)
                if marker.reprojection_error_px <= DISPLACED_CORNER_CHECK_PX and (best is None or marker.reprojection_error_px < best.reprojection_error_px):
                    best = marker
                    if best.reprojection_error_px <= SQUARE_MISFIT_MIN_PX:
                        return best
        return best

    def _edges_despite_occlusion(self, gray: NDArray[np.float32], quad: NDArray[np.float64], *, aruco_id: int, dictionary: str,
                                 spec: _TagSpec) -> NDArray[np.float64] | None:
        """A decoded tag whose edges :func:`_edge_refined` could not fit (a highlight or a glove over part of one, blood
        on it): its corners from the edge search that recovers missed tags (:func:`.tag_recovery.recover_tag`,
        which keeps only the clean stretches of each edge, and places a tag with one edge hidden by its other three),
        within 4 px of the detector's corners; None when that fails too (the caller keeps the detector's sub-pixel
        corners). Under every camera degradation (twin seeds 5000-5030, 3 poses) 10 of 314 tags had no edge fit, their
        detector corners 2.3-5.8 px off at worst; 3 of them were placed within 1.23 px this way, the others kept. On
        other frames of the same seeds, 6 had no edge fit; the square fit placed 2 of them within 0.74 px (from 3.47
        and 4.25 px) and a third at 3.20 px (from 4.09 px), where four edges placed none."""
        got = recover_tag(gray, quad, aruco_id=aruco_id, dictionary=dictionary, tolerance_px=4.0, rivals=(),
                          square=lambda steps: self._square_fit(steps, spec=spec, predicted_px=quad))
        return got.corners_px

    def recover(self, image: NDArray[np.uint8], video: VideoDetections, expected_corners_px: Mapping[int, NDArray[np.float64]], *,
                tolerance_px: float = 8.0, reach_px: float = 0.0, placed_px: Mapping[int, NDArray[np.float64]] | None = None,
                by_place: bool = False) -> VideoDetections:
        """``video`` with the missing markers found where they are expected (:func:`.tag_recovery.recover_tag`).

        expected_corners_px : {marker id: (4, 2) or (k, 4, 2)} predicted tag corners (OpenCV order), k candidates
            (e.g. a marker's two mirror poses in fluoroscopy): the first one verified is taken. A tag partly out of
            the frame is looked for on what of it is in the frame (``recover_tag(partial=True)``).
        ``reach_px``: a prediction that may be off by more than ``tolerance_px`` (a registration on one or two
            markers) is also tried shifted, on a grid of ``tolerance_px`` steps out to ``reach_px``, nearest first,
            when it is not verified where predicted (``benchmarks/tag_detection.py`` prints the time per frame).
        ``placed_px``: {marker id: (k, 4, 2)} where the same registration puts the tag of every marker posed in
            fluoroscopy, seen or not (k = 0: nowhere it can be seen). A tag of the marker set is a rival of a
            missing one (its identity judged against it, :func:`.tag_recovery.recover_tag`'s ``rivals``) unless it
            is seen elsewhere in the frame or placed away from the missing tag (:func:`placed_elsewhere`).
        ``by_place``: ``placed_px`` comes from a registration (with its mirror open, from both solutions, merged) and
            ``expected_corners_px`` from the same one: where a tag is found as predicted (or within ``reach_px`` of
            it), the marker posed in fluoroscopy there is where it is, so no marker the registration does not place
            can be there (markers are 40 mm across); only the posed markers it places here too (within the reach:
            :func:`placed_elsewhere`) are rivals, and with none the code cells read need only agree, however few a
            glare leaves (:func:`.tag_recovery.recover_tag`'s ``placed_here``).
        Markers already in ``video`` and ids not in the marker set are skipped. Returns ``video`` itself when
        nothing was recovered. A recovered marker is flagged ``recovered`` and its covariance computed with
        ``RECOVERED_CORNER_SIGMA_PX``.
        """
        have = {m.marker_id for m in video.markers}
        by_marker = {spec.marker_id: (name, aruco_id, spec) for name, per in self._specs.items() for aruco_id, spec in per.items()}
        todo = {i: c for i, c in expected_corners_px.items() if i not in have and i in by_marker}
        if not todo:
            return video
        gray = _gray(image).astype(np.float32)
        found: list[VideoMarker] = []
        steps = _grid(tolerance_px, reach_px)
        placed = placed_px or {}
        for marker_id, cands in sorted(todo.items()):
            name, aruco_id, spec = by_marker[marker_id]
            preds = np.asarray(cands, dtype=np.float64).reshape(-1, 4, 2)
            # The tags that could lie where this one is expected: the marker set's, less those seen elsewhere in this
            # frame and those the registration places away from here.
            rivals = tuple(a for a, other in self._specs[name].items() if other.marker_id not in have
                           and not (other.marker_id in placed and placed_elsewhere(placed[other.marker_id], preds, tolerance_px=tolerance_px, reach_px=reach_px)))

            # Identity by place: of the rivals, only the posed markers the registration may put here.
            here = by_place and placed_px is not None
            if here:
                rivals = tuple(a for a in rivals if self._specs[name][a].marker_id in placed)

            def attempt(pred) -> VideoMarker | None:
                got = recover_tag(gray, pred, aruco_id=aruco_id, dictionary=name, tolerance_px=tolerance_px, rivals=rivals, placed_here=here,
                                  partial=True, square=lambda steps: self._square_fit(steps, spec=spec, predicted_px=pred))
                if not got.accepted:
                    return None
                marker = self._pose(spec, got.corners_px, corner_sigma_px=RECOVERED_CORNER_SIGMA_PX)
                # Four corners that are no view of the tag's square (an edge's line fitted to a glove's or a code cell's
                # step) are no tag there.
                return self._border_shifted(marker, spec=spec, gray=gray) if marker.reprojection_error_px <= RECOVERED_MAX_SQUARE_RMS_PX else None

            for k, pred in enumerate(p + shift for shift in steps for p in preds):
                got = attempt(pred)
                if got is not None:
                    if k >= len(preds):
                        # Found from a shifted prediction: looked for once more where it was found, so that its edges
                        # (and a hidden edge's square fit) are placed from a prediction as near as a good registration's.
                        again = attempt(got.corners_px)
                        got = again if again is not None else got
                    found.append(got)
                    break
        if not found:
            return video
        return with_markers(video, found)

    def _square_fit(self, steps: BorderSteps, *, spec: _TagSpec, predicted_px: NDArray[np.float64]) -> SquareFit | None:
        """A tag with one edge hidden placed by its pose fitted to the other three edges' steps, with this camera and the
        tag's size (:func:`.tag_square_fit.fit_square_to_edges`); refused past ``SQUARE_FIT_MAX_CORNER_SIGMA_PX``."""
        return fit_square_to_edges(steps.points_px, steps.kept, camera=self.camera, object_points_mm=spec.object_points, predicted_px=predicted_px,
                                   max_corner_sigma_px=SQUARE_FIT_MAX_CORNER_SIGMA_PX)

    def search(self, image: NDArray[np.uint8], video: VideoDetections, marker_ids: Iterable[int]) -> VideoDetections:
        """``video`` with the tags of ``marker_ids`` that it misses found where nothing predicts them: dark outlines
        with a part hidden, of which ArUco made no candidate (:func:`.tag_search.search_tags`).

        For a frame with no registration to predict from (:meth:`recover` needs one). Ids not in the marker set
        and markers already in ``video`` are skipped. A found marker is flagged ``recovered``, its covariance
        computed with ``RECOVERED_CORNER_SIGMA_PX``. Returns ``video`` itself when nothing was found.
        """
        missing = self._missing(video, marker_ids)
        if not missing:
            return video
        gray = _gray(image)
        gray_f: NDArray[np.float32] | None = None
        found: list[VideoMarker] = []
        for name, per, wanted in missing:
            for tag in search_tags(gray, dictionary=name, wanted=wanted, exclude_px=[m.corners_px for m in video.markers + tuple(found)],
                                   half_above_px=self.detect_below_px, rivals=list(per)):
                gray_f = gray_f if gray_f is not None else gray.astype(np.float32)
                spec = per[tag.aruco_id]
                found.append(self._border_shifted(self._pose(spec, tag.corners_px, corner_sigma_px=RECOVERED_CORNER_SIGMA_PX), spec=spec, gray=gray_f))
        if not found:
            return video
        return with_markers(video, found)

    def name_among_posed(self, image: NDArray[np.uint8], video: VideoDetections, marker_ids: Iterable[int]) -> tuple[VideoMarker, ...]:
        """Hypotheses for the tags of ``marker_ids`` (markers posed in fluoroscopy) that ``video`` misses: outlines whose
        code, read only in part, names one of them (:func:`.tag_hypotheses.outline_hypotheses`).

        Each is returned as a marker flagged ``recovered`` and ``named_among_posed``, its covariance computed with
        ``OUTLINE_CORNER_SIGMA_PX`` (``RECOVERED_CORNER_SIGMA_PX`` where its edges were fitted), and
        ``identified_by_code`` where its code, read on the outline's corners, meets the dictionary-wide rule (the
        search's, with the set's ids as rivals). They are not added to ``video``: a caller adds them only where a
        registration bears them out.
        """
        missing = self._missing(video, marker_ids)
        if not missing:
            return ()
        gray = _gray(image)
        gray_f: NDArray[np.float32] | None = None
        named: list[VideoMarker] = []
        for name, per, wanted in missing:
            for hyp in outline_hypotheses(gray, dictionary=name, wanted=wanted, exclude_px=[m.corners_px for m in video.markers],
                                          half_above_px=self.detect_below_px, rivals=list(per)):
                spec = per[hyp.aruco_id]
                gray_f = gray_f if gray_f is not None else gray.astype(np.float32)
                by_code = identify_quad(gray_f, hyp.corners_px, dictionary=name, wanted=[hyp.aruco_id], partial=True, rivals=list(per)) is not None
                marker = self._pose(spec, hyp.corners_px, corner_sigma_px=RECOVERED_CORNER_SIGMA_PX if hyp.edges_fitted else OUTLINE_CORNER_SIGMA_PX)
                if marker.reprojection_error_px > DISPLACED_CORNER_CHECK_PX:
                    # An outline with one corner on a glove's edge: placed by its edges from three of its corners (the
                    # name stays a hypothesis).
                    placed = self._one_corner_displaced(hyp.corners_px, spec=spec, as_read=marker, corner_sigma_px=RECOVERED_CORNER_SIGMA_PX,
                                                        place=lambda pred, spec=spec: fit_tag_edges(
                                                            gray_f, pred, tolerance_px=REPAIR_TOLERANCE_PX, partial=True,
                                                            square=lambda steps: self._square_fit(steps, spec=spec, predicted_px=pred)).corners_px)
                    marker = placed if placed is not None else marker
                # Alone, nothing but the tag's own edges checks where it lies: a name among the set stands alone only on
                # edges fitted to a view of its square (an outline cut by the frame's edge lay 28 px off, twin seed 3001).
                alone = hyp.named_among_set and hyp.edges_fitted and marker.reprojection_error_px <= SQUARE_MISFIT_MIN_PX
                named.append(replace(self._border_shifted(marker, spec=spec, gray=gray_f), named_among_posed=True, identified_by_code=by_code,
                                     named_among_set=alone))
        return tuple(sorted(named, key=lambda m: m.marker_id))

    def _missing(self, video: VideoDetections, marker_ids: Iterable[int]) -> list[tuple[str, dict, list[int]]]:
        """Per dictionary with any: (its name, its tag specs by ArUco id, the ArUco ids of ``marker_ids`` that ``video`` misses)."""
        todo = {int(i) for i in marker_ids} - {m.marker_id for m in video.markers}
        missing = []
        for name, per in self._specs.items():
            wanted = [a for a, spec in per.items() if spec.marker_id in todo]
            if wanted:
                missing.append((name, per, wanted))
        return missing

    def _border_shifted(self, marker: VideoMarker, *, spec: _TagSpec, gray: NDArray[np.float32]) -> VideoMarker:
        """``marker`` posed again from its outline moved to where the width of its tag's black border puts it
        (:func:`.tag_border.border_shift_px`: a tag whose white base clips), or ``marker`` itself (not measured, or
        ``border_shift`` False). Applied to a marker once it is accepted: the checks that accept it (a view of its
        square, a corner displaced by a glove) judge the outline its steps gave."""
        if not self.border_shift:
            return marker
        shift, profiles = border_shift_px(gray, marker.corners_px, code_cells(spec.dictionary, spec.aruco_id))
        if not profiles:
            return marker
        moved = self._pose(spec, moved_outline(marker.corners_px, shift), corner_sigma_px=marker.corner_sigma_px if marker.recovered else None,
                           edge_sigma_px=None if marker.recovered else marker.edge_sigma_px)
        return replace(moved, named_among_posed=marker.named_among_posed)

    def _pose(self, spec: _TagSpec, corners: NDArray[np.float64], *, corner_sigma_px: float | None = None,
              edge_sigma_px: float | None = None) -> VideoMarker:
        """The tag's pose from its ``corners`` (4, 2). ``corner_sigma_px``: a recovered tag's corner noise (marks it
        recovered); ``edge_sigma_px``: a detected tag's, as its edges state it (:func:`edge_corner_sigma_px`), kept
        on the marker for the joint solve (``VideoMarker.edge_sigma_px``)."""
        k, dist = self.camera.camera_matrix, self.camera.distortion
        obj = spec.object_points
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, corners, k, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        best = int(np.argmin(np.asarray(errs).ravel()))
        rvec, tvec = cv2.solvePnPRefineLM(obj, corners, k, dist, rvecs[best].copy(), tvecs[best].copy())
        sigma = self.corner_sigma_px if corner_sigma_px is None else float(corner_sigma_px)
        edge_sigma = float(edge_sigma_px) if corner_sigma_px is None and edge_sigma_px is not None and np.isfinite(edge_sigma_px) else 0.0
        # A corner the frame's edge made (an outline the edge cuts) lies somewhere along its side: weighed so, across it.
        slides = cut_corner_slides_px(corners, width=self.camera.width, height=self.camera.height)
        slid = bool(np.any(slides != 0))
        if slid:
            whiten = _corner_whitening(sigma, slides)
            rvec, tvec = _refine_whitened(obj, corners, k, dist, rvec, tvec, whiten)
        rot, dr = cv2.Rodrigues(rvec)  # dr: dR/d(rvec), 3x9 (R row-major)
        camera_from_tag = make_transform(rot, tvec.ravel())
        bb_tag = spec.bb_tag_mm
        x_d = rot @ bb_tag + tvec.ravel()
        proj, jac = cv2.projectPoints(obj, rvec, tvec, k, dist)
        off = proj.reshape(4, 2) - corners
        err = float(np.sqrt(np.mean(np.sum((across_slides(off, slides) if slid else off) ** 2, axis=1))))
        # First-order covariance of the 6 pose parameters, pushed to X_D.
        j = jac[:, :6]
        if slid:
            jw = np.concatenate([w @ j[2 * c:2 * c + 2] for c, w in enumerate(whiten)])
            normal, scale = jw.T @ jw, 1.0
        else:
            normal, scale = j.T @ j, sigma**2
        try:  # a tag seen at any usable angle gives a well-conditioned 6x6 normal matrix: an inverse (0.2 ms less than pinv)
            cov_pose = np.linalg.inv(normal) * scale
        except np.linalg.LinAlgError:
            cov_pose = np.linalg.pinv(normal) * scale
        # dX_D/d(rvec) from Rodrigues' own Jacobian, dX_D/dt = I.
        jx = np.hstack([(dr.reshape(3, 3, 3) @ bb_tag).T, np.eye(3)])
        cov = jx @ cov_pose @ jx.T
        return VideoMarker(marker_id=spec.marker_id, corners_px=corners, camera_from_tag=camera_from_tag, position_camera_mm=x_d, covariance_mm2=cov, reprojection_error_px=err,
                           recovered=corner_sigma_px is not None, corner_sigma_px=sigma, edge_sigma_px=edge_sigma)


def _corner_whitening(sigma_px: float, slides_px: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Per corner, the (2, 2) whitening of its error: covariance ``sigma_px``^2 I plus its slide's ``v v^T``."""
    return [np.linalg.inv(np.linalg.cholesky(sigma_px**2 * np.eye(2) + np.outer(v, v))) for v in np.asarray(slides_px).reshape(4, 2)]


def _refine_whitened(obj: NDArray[np.float64], corners: NDArray[np.float64], k: NDArray[np.float64], dist: NDArray[np.float64],
                     rvec: NDArray[np.float64], tvec: NDArray[np.float64], whiten: list[NDArray[np.float64]]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The tag's pose (rvec, tvec (3, 1)) minimising its corners' whitened errors (scipy's Levenberg-Marquardt, from the given pose)."""
    w = np.zeros((8, 8))
    for c, wc in enumerate(whiten):
        w[2 * c:2 * c + 2, 2 * c:2 * c + 2] = wc

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        proj, _ = cv2.projectPoints(obj, x[:3], x[3:], k, dist)
        return w @ (proj.reshape(8) - corners.reshape(8))

    def jacobian(x: NDArray[np.float64]) -> NDArray[np.float64]:
        _, jac = cv2.projectPoints(obj, x[:3], x[3:], k, dist)
        return w @ jac[:, :6]

    x = least_squares(residuals, np.concatenate([np.ravel(rvec), np.ravel(tvec)]), jac=jacobian, method="lm").x
    return x[:3].reshape(3, 1), x[3:].reshape(3, 1)
