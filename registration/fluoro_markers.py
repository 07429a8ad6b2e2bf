"""Marker detection in fluoroscopy: wire rings (ellipses) and BBs (sub-pixel blobs), identified by BB pattern.

Input is a log-attenuation image (rows, columns): larger = more attenuation.
A white top-hat removes anatomy; an opening separates the BBs (discs of
10-25 px) from the thin wire (4-6 px wide); a blob that is no disc is split into the
touching BB shadows it may be made of (:mod:`.blob_split`). Each ring is a large thin
connected component fitted with an ellipse; the BBs inside it are rectified
into the marker plane through the ellipse (circle of 24 mm) and matched with
:func:`drillnav.registration.markers.identify`. A ring that touches the image
border keeps its arc (and its BBs in the field) when at least half of it is
in the field; rings that cross in projection, one piece of wire too large to be
a ring or whose BBs match no marker and whose pixels do not follow one ellipse,
are split into their ellipses (:mod:`.ring_split`) and each identified on its
own.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .carm import REFERENCE_PIXEL_MM, CArmView
from .blob_split import split_touching
from .markers import MarkerNotIdentified, MarkerSet, identify
from .ring_split import ellipse_distance, split_rings

__all__ = ["DetectedBB", "DetectedMarker", "RejectedRing", "FluoroDetections", "detect_in_view", "detect_markers", "magnification_range", "blob_key"]


# A sphere's shadow is a disc: the principal axes of a BB's half-maximum footprint agree (on the operating-room twin,
# seeds 3001-3004, every pair and view: median ratio 1.03, 533 of 535 BBs whose centre lies within 0.5 px of the
# truth at most 1.2). A blob longer than that is a BB merged with a neighbour's shadow, a K-wire's or a clamp's, or
# cut by the field's edge: all 23 blobs there whose centre lay 1.5-5.7 px off the BB's (ratio 1.21-3.12). Its
# centroid does not place the BB: it still counts for identifying its marker, and poses it only where too few others
# would (:data:`.marker_pose.MIN_PLACING_BBS`). Such a blob is first split where it is made of touching domes, two
# BBs' shadows (:func:`.blob_split.split_touching`); each piece is measured again.
MAX_BB_ELONGATION = 1.2


def blob_key(center_px: NDArray[np.float64]) -> tuple[float, float]:
    """A blob centre (2,) as a hashable key: the same detection gives the same key wherever it is passed along."""
    return tuple(np.round(np.asarray(center_px, dtype=np.float64), 3).tolist())


@dataclass(frozen=True, kw_only=True)
class DetectedBB:
    center_px: NDArray[np.float64]  # (2,) column, row
    diameter_px: float
    large: bool
    # Ratio of the principal axes of the blob's half-maximum footprint (1: a disc).
    elongation: float = 1.0

    @property
    def places(self) -> bool:
        """Whether the blob's centroid places its BB: its footprint is a disc (``MAX_BB_ELONGATION``)."""
        return self.elongation <= MAX_BB_ELONGATION


@dataclass(frozen=True, kw_only=True)
class DetectedMarker:
    """One identified marker in one view.

    bb_index : (N,) design BB index of each detected BB (-1: unmatched).
    ring_ellipse : ((cx, cy), (major, minor), angle_deg) as cv2.fitEllipse gives it.
    """

    marker_id: int
    bbs: tuple[DetectedBB, ...]
    bb_index: NDArray[np.int64]
    ring_ellipse: tuple
    mirrored: bool
    identification_cost_mm: float
    # (N,) the same marker's other assignment of these BBs that matched nearly as well
    # (:attr:`.markers.Identification.alternative_bb_index`; None: the assignment is unambiguous).
    alternative_bb_index: NDArray[np.int64] | None = None


@dataclass(frozen=True, kw_only=True)
class RejectedRing:
    reason: str
    center_px: NDArray[np.float64]
    # The marker whose pattern the ring's BBs match at a cost over identify's limit but within
    # CORROBORATED_MAX_COST_MM (none identified in the view by that id): an identity that stands only where the
    # camera sees that marker's tag (:attr:`.marker_pose.MarkerPose.needs_camera`).
    candidate: "DetectedMarker | None" = None
    # The ring's BBs matched against each marker of the set on its own, at up to LOOSE_MAX_COST_MM (rings that
    # identify no marker for their pattern's cost or margin, with 4 or more BBs): hypotheses that stand only where
    # the camera's constellation of markers bears one out in fluoroscopy (:func:`.video_claims.corroborate_loose`).
    loose: "tuple[DetectedMarker, ...]" = ()


@dataclass(frozen=True, kw_only=True)
class FluoroDetections:
    markers: tuple[DetectedMarker, ...]
    rejected: tuple[RejectedRing, ...]
    # Every BB-like blob of the view, identified or not: a marker posed from another view can claim its
    # BBs here by projection when its own ring could not identify it (edge-on, overlapping, cut).
    blobs: tuple[DetectedBB, ...] = ()
    # The log image (H, W) the detections were made on (:func:`detect_in_view` keeps it): an edge-on marker posed
    # through other views is measured across its ring's stroke there (:mod:`.edge_on_ring`). None: not kept.
    image_log: NDArray[np.float32] | None = field(default=None, repr=False, compare=False)

    def by_id(self) -> dict[int, DetectedMarker]:
        return {m.marker_id: m for m in self.markers}

    def candidates(self) -> tuple[DetectedMarker, ...]:
        """The rejected rings' candidate markers (:attr:`RejectedRing.candidate`) whose id the view did not identify,
        one per id (an id two rings match on different BBs is left out: which one it is, is not guessed)."""
        found = {m.marker_id for m in self.markers}
        by_id: dict[int, list[DetectedMarker]] = {}
        for r in self.rejected:
            if r.candidate is not None and r.candidate.marker_id not in found:
                by_id.setdefault(r.candidate.marker_id, []).append(r.candidate)
        out = []
        for group in by_id.values():
            best = _one_ring(group)
            if best is not None:
                out.append(best)
        return tuple(sorted(out, key=lambda m: m.marker_id))


def _blobs(bb_image: NDArray[np.float32], threshold: float) -> list[tuple[NDArray[np.float64], float, float]]:
    """[(centre (2,) px, diameter px, elongation)]: the BB-like blobs over ``threshold``, centred on their weight;
    elongation: the ratio of the principal axes of the half-maximum footprint. A blob that is no disc is split into
    the touching BB shadows it may be made of (:func:`.blob_split.split_touching`)."""
    mask = (bb_image > threshold).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    out = []
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        if area < 12 or w > 60 or h > 60:
            continue
        values = bb_image[y : y + h, x : x + w]
        own = labels[y : y + h, x : x + w] == i
        blob = _blob(values, own, x, y)
        if blob[2] > MAX_BB_ELONGATION:
            pieces = split_touching(values, own, threshold=threshold)
            if len(pieces) > 1:
                out += [_blob(values, piece, x, y) for piece in pieces]
                continue
        out.append(blob)
    return out


def _blob(values: NDArray[np.float32], own: NDArray[np.bool_], x: int, y: int) -> tuple[NDArray[np.float64], float, float]:
    """(centre (2,) px, diameter px, elongation) of the pixels ``own`` (H, W) of a window ``values`` (H, W) whose
    top-left pixel is (``x``, ``y``)."""
    win = values * own
    peak = float(win.max())
    # Diameter from the half-maximum footprint: a sphere's chord profile falls to half at 0.866 r.
    half = np.count_nonzero(win > 0.5 * peak)
    d_half = 2.0 * np.sqrt(half / np.pi) / 0.866
    yy, xx = np.mgrid[y : y + win.shape[0], x : x + win.shape[1]]
    wsum = win.sum()
    centre = np.array([(xx * win).sum() / wsum, (yy * win).sum() / wsum])
    return centre, d_half, _elongation(xx[win > 0.5 * peak] - centre[0], yy[win > 0.5 * peak] - centre[1])


def _elongation(dx: NDArray[np.float64], dy: NDArray[np.float64]) -> float:
    """Ratio of the principal axes (>= 1) of the pixels at offsets (dx, dy) (N,) from a centre; 1 under 3 pixels."""
    if len(dx) < 3:
        return 1.0
    low, high = np.linalg.eigvalsh(np.cov(np.stack([dx, dy])))
    return float(np.sqrt(high / max(low, 1e-9)))


def magnification_range(view: CArmView) -> tuple[float, float]:
    """The magnifications (low, high) markers on the patient can have in ``view``: ``MAGNIFICATION_SPAN`` times
    the magnification at the isocentre (frame C's origin), never under 1; ``DEFAULT_MAGNIFICATION_RANGE`` when the
    origin does not lie between the source and the detector."""
    m = float(view.magnification(np.zeros((1, 3)))[0])
    if not 1.0 < m < 10.0:
        return DEFAULT_MAGNIFICATION_RANGE
    return max(1.0, MAGNIFICATION_SPAN[0] * m), max(1.0, MAGNIFICATION_SPAN[1] * m)


def detect_markers(
    image_log: NDArray[np.float32],
    marker_set: MarkerSet,
    *,
    pixel_spacing_mm: float = 0.304,
    magnification_range: tuple[float, float] | None = None,
) -> FluoroDetections:
    """Find, measure and identify every marker in one view.

    A detector coarser than :data:`WORKING_PIXEL_MM` (binned, or a small matrix over a large field) is looked at
    on a grid that many times finer (bilinear), and every position and size is given back in its own pixels.
    ``magnification_range``: the markers' magnifications, which size the kernels and the rings looked for
    (:func:`magnification_range` of the view; None: ``DEFAULT_MAGNIFICATION_RANGE``).
    """
    if magnification_range is None:
        magnification_range = DEFAULT_MAGNIFICATION_RANGE
    img = np.asarray(image_log, dtype=np.float32)
    if img.ndim != 2:
        raise ValueError(f"expected a 2D image, got shape {img.shape}")
    if not (np.isfinite(pixel_spacing_mm) and pixel_spacing_mm > 0):
        raise ValueError(f"pixel_spacing_mm must be a positive number, got {pixel_spacing_mm}")
    factor = int(round(pixel_spacing_mm / WORKING_PIXEL_MM))
    if factor >= 2:
        fine = cv2.resize(img, (img.shape[1] * factor, img.shape[0] * factor), interpolation=cv2.INTER_LINEAR)
        found = detect_markers(fine, marker_set, pixel_spacing_mm=pixel_spacing_mm / factor, magnification_range=magnification_range)
        return _coarsened(found, factor)
    ring_r = marker_set.markers[0].ring_radius_mm
    big_bb_px = 3.5 * magnification_range[1] / pixel_spacing_mm
    k = int(2 * big_bb_px + 7) | 1
    smooth = cv2.GaussianBlur(img, (0, 0), 0.8)
    tophat = cv2.morphologyEx(smooth, cv2.MORPH_TOPHAT, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    wire_px = 0.8 * magnification_range[1] / pixel_spacing_mm
    open_k = int(wire_px + 1) | 1
    bb_image = cv2.morphologyEx(tophat, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (open_k, open_k)))
    wire_image = tophat - bb_image
    noise = 1.4826 * float(np.median(np.abs(tophat - np.median(tophat))))
    result = None
    for level, (bb_floor, wire_floor) in enumerate(CONTRAST_FLOORS):
        wire_threshold = max(wire_floor, 5 * noise)
        found = _find_markers(img, bb_image, wire_image, marker_set, bb_threshold=max(bb_floor, 6 * noise), wire_threshold=wire_threshold,
                              wire_low=wire_threshold if WIRE_HYSTERESIS is None else max(WIRE_HYSTERESIS * wire_threshold, 2.5 * noise),
                              ring_r=ring_r, wire_px=wire_px, magnification_range=magnification_range, pixel_spacing_mm=pixel_spacing_mm)
        result = found if result is None else _add_new_markers(result, found, marker_set)
        # See CONTRAST_FLOORS: lower floors only for a view the first level left with at most one marker, and only
        # while rings are left unidentified for a contrast reason.
        if (level == 0 and len(result.markers) > 1) or (result.markers and all(r.reason.startswith(_NOT_CONTRAST) for r in found.rejected)):
            break
    return result


def detect_in_view(image_log: NDArray[np.float32], view: CArmView, marker_set: MarkerSet) -> FluoroDetections:
    """:func:`detect_markers` in one view as the product runs it: at the view's own pixel size, with the markers'
    magnifications that its geometry allows (:func:`magnification_range`), the image kept with them
    (:attr:`FluoroDetections.image_log`). Every caller with a view uses this."""
    found = detect_markers(image_log, marker_set, pixel_spacing_mm=float(view.pixel_spacing_mm[1]), magnification_range=magnification_range(view))
    return replace(found, image_log=image_log)


def _coarsened(found: FluoroDetections, factor: int) -> FluoroDetections:
    """Detections on a grid ``factor`` times finer (cv2.resize's pixel centres) given back in the image's own pixels."""

    def px(p):
        return (np.asarray(p, dtype=np.float64) + 0.5) / factor - 0.5

    def bb(b: DetectedBB) -> DetectedBB:
        return replace(b, center_px=px(b.center_px), diameter_px=b.diameter_px / factor)

    def marker(m: DetectedMarker) -> DetectedMarker:
        (cx, cy), (d1, d2), angle = m.ring_ellipse
        ellipse = (tuple(float(v) for v in px([cx, cy])), (d1 / factor, d2 / factor), angle)
        return replace(m, bbs=tuple(bb(b) for b in m.bbs), ring_ellipse=ellipse)

    return FluoroDetections(markers=tuple(marker(m) for m in found.markers),
                            rejected=tuple(replace(r, center_px=px(r.center_px), candidate=None if r.candidate is None else marker(r.candidate),
                                                   loose=tuple(marker(m) for m in r.loose)) for r in found.rejected),
                            blobs=tuple(bb(b) for b in found.blobs))


def _fits_its_plane(marker: DetectedMarker, marker_set: MarkerSet, *, min_bbs: int = 5, max_rms_px: float = 3.0) -> bool:
    """Whether the BBs matched to the design lie where one view of the marker's plane puts them.

    The design BBs lie in the marker's plane (z = 0) within 15 mm of its centre, hundreds of millimetres from the
    source: their images are an affine map of their (x, y) to within ~2 px of perspective at the steepest tilt.
    Fitted to at least ``min_bbs`` (six unknowns, 2 x 5 equations), its RMS residual shows BBs taken from clutter
    or a neighbour (tens of pixels); a homography would fit five wrong BBs nearly exactly. It cannot see the marker's
    own BBs assigned in mirror image (a reflection is affine).
    """
    ok = np.asarray(marker.bb_index) >= 0
    if ok.sum() < min_bbs:
        return False
    plane = marker_set.by_id(marker.marker_id).bb_centers_mm[np.asarray(marker.bb_index)[ok], :2]
    img = np.array([b.center_px for b, keep in zip(marker.bbs, ok) if keep])
    design = np.column_stack([plane, np.ones(len(plane))])
    coef, *_ = np.linalg.lstsq(design, img, rcond=None)
    return float(np.sqrt(np.mean(np.sum((design @ coef - img) ** 2, axis=1)))) <= max_rms_px


def _add_new_markers(found: FluoroDetections, lower: FluoroDetections, marker_set: MarkerSet, *, same_bb_px: float = 2.0,
                     same_ring_px: float = 30.0) -> FluoroDetections:
    """``found`` with the markers a lower threshold identified that it had not, on BBs none of its markers uses, whose
    BBs fit one view of their plane (:func:`_fits_its_plane`).

    A marker found at a higher threshold keeps its detection as it was (a lower one can let clutter into its BBs).
    The blobs are the lower level's (more of the unidentified markers' BBs), each of ``found``'s markers' BBs in
    place of its lower-level twin, so that a marker's BBs are among the view's blobs exactly as
    :func:`.marker_pose.register_markers` expects; the unidentified rings are the lower level's, less those of a
    marker now identified.
    """
    markers = {m.marker_id: m for m in found.markers}
    taken = [b.center_px for m in found.markers for b in m.bbs]
    for m in lower.markers:
        centres = np.array([b.center_px for b in m.bbs])
        if m.marker_id in markers or (taken and np.min(np.linalg.norm(centres[:, None] - np.array(taken)[None], axis=2)) < same_bb_px):
            continue
        if not _fits_its_plane(m, marker_set):
            continue
        markers[m.marker_id] = m
        taken += list(centres)
    if len(markers) == len(found.markers):
        return found
    kept_bbs = [b for m in found.markers for b in m.bbs]
    own = np.array([b.center_px for b in kept_bbs]).reshape(-1, 2)
    blobs = tuple(kept_bbs) + tuple(b for b in lower.blobs if not len(own) or np.min(np.linalg.norm(own - b.center_px, axis=1)) >= same_bb_px)
    centres = np.array([m.ring_ellipse[0] for m in markers.values()])
    rejected = tuple(r for r in lower.rejected if np.min(np.linalg.norm(centres - r.center_px, axis=1)) >= same_ring_px)
    return FluoroDetections(markers=tuple(sorted(markers.values(), key=lambda m: m.marker_id)), rejected=rejected, blobs=blobs)


# Scatter compresses tungsten's contrast in the log image: behind an anti-scatter grid a pelvis still scatters 20-100 %
# of the primary, which takes a 2 mm BB's top-hat peak from ~5.8 (no scatter) to ~1.25 (50 %) and ~0.8 (100 %) over a
# real radiograph's anatomy (tests/test_real_anatomy_background.py). Floors (log units, BBs / wire) that keep
# anatomy's texture out of a low-scatter view would then lose every marker. So when the first level leaves a view
# with at most one marker and a ring unidentified for a contrast reason, lower floors are tried (the noise-relative
# thresholds, 6 and 5 sigma, still hold); the markers they identify are added when their BBs are new and fit their
# plane (_add_new_markers), and a marker found at a higher level keeps that detection. Views with markers found keep
# what they have: in a cluttered view a lower floor can let a neighbour's or the hardware's blobs into a ring (a
# wrongly assigned pattern was seen on the twin's operating room).
CONTRAST_FLOORS = ((0.8, 0.5), (0.4, 0.25), (0.2, 0.12))
# The markers' magnification sizes the detector's kernels and the rings it looks for. A fixed 1.2-2.2 held the
# twin's C-arm (SDD 1164 mm, SAD 624 mm: 1.87 at the isocentre, markers at 1.74-2.03) but not one whose isocentre
# magnifies 2.5 (SDD 1200, SAD 480: markers at 2.28-2.79, 25 of 60 identified in benchmarks/detector_sweep.py's
# scenes): the range now follows the view, 0.65-1.18 times the isocentre's magnification (1.21-2.20 on the twin).
DEFAULT_MAGNIFICATION_RANGE = (1.2, 2.2)
MAGNIFICATION_SPAN = (0.65, 1.18)
# The detector's kernels are whole pixels sized for 0.3 mm pixels (the BB/wire opening, the smoothing): on a detector
# binned to 0.6 mm the opening is 3 px, about a BB's width. Such an image is looked at on a grid
# round(spacing / WORKING_PIXEL_MM) times finer. benchmarks/detector_sweep.py, binned 2x2: 28 -> 55 of 60 markers,
# with the known-component DRR's wire (a whole number of pixels wide, faint at 0.61 mm); the twin's own shots binned
# 2x2 lost little before (74 -> 76 of 90, docs/identity_and_error.md).
WORKING_PIXEL_MM = REFERENCE_PIXEL_MM
# The wire is traced by hysteresis: pixels over WIRE_HYSTERESIS x its threshold (and over 2.5 sigma of noise) that
# connect to one over the threshold. A 0.8 mm wire is a thin ridge as noisy as the pixels under it; with no detector
# blur, or dense anatomy behind it, a single threshold broke each ring into arcs that fit flat ellipses ("edge-on")
# holding no BBs (tests/test_real_anatomy_background.py: on 12 seeds each, a single threshold failed 8 sharp scenes
# and 7 dense ones, hysteresis 1 of each).
WIRE_HYSTERESIS = 0.5
# A ring whose ellipse is flatter than this (minor over major axis: about the cosine of its tilt to the beam, 83 deg
# at 0.12) is edge-on: too little of its BB pattern is left across the ellipse to identify. Markers on the anterior
# skin lie 60-89 deg to a lateral beam. Rectified through the ellipse alone, a flat ring's BBs are stretched too far to
# identify (the limit was 0.2, 78 deg: the lateral views of 18 seeds of the study identified 21 of 85 markers in the
# field at 0.25, 29 at 0.2). Matched in the image's own measure (FLAT_MINOR_RATIO), the lateral views of study seeds
# 10400-11800 (16 seeds, AP+lateral) identify 19 markers at 0.2, 21 with that measure alone, 26 with it at 0.15, 28 at
# 0.12 (22 at 0.12 without it) and no more at 0.1 or 0.07; none wrongly. Their random and inlet/outlet pairs: 103 ->
# 106 and 109 -> 109, the one wrong identity among them unchanged (counted with the measure applied below 0.5; the
# rings it identified there lie under 0.3, its limit now).
EDGE_ON_MINOR_RATIO = 0.12
# A ring flatter than this whose rectified BBs match no marker is matched again with each difference measured as the
# image shows it: the stretched axis shrunk back by the ellipse's minor over major (identify's ``metric``). Stretched
# by major / minor, a flat ring's BB noise and its ellipse's error grow with it: seed 10901's lateral view, a marker
# 81 deg to the beam with all 7 BBs found, costs 0.25 mm rectified through its true ellipse and 0.06 mm so measured.
# So measured, a pattern also tells its two faces apart less well across the ellipse; a ring 61 deg to the beam (0.49)
# took the wrong face (seed 11901's random pair: the registration 0.76 -> 28 mm off). The rings this identifies on the
# study's seeds lie 0.12-0.27.
FLAT_MINOR_RATIO = 0.3
# A ring flatter than this identifies its marker only on five paired BBs or more: nearly edge-on, four BBs lie close to
# one line across the ellipse, merged shadows displace them, and the pose they give can lie tens of mm off (seed
# 10400's random view p-83s+18: a ring at 0.12 on four BBs, two 4.9 px off, posed 40 mm off, the registration 12.4 mm
# off). Over 48 study seeds (M = 5) this moved 5 registrations: 3 nearer the truth (12.4 -> 2.41 mm, 1.57 -> 0.33 mm),
# 2 farther (1.31 -> 1.41 and 1.10 -> 1.24 mm, within their bounds), no refusal changed; with M = 3 and 4 on the
# three seeds of docs/accuracy.md, AP+lateral single views refused 84 -> 88 over all configurations.
FEW_BB_EDGE_ON_RATIO = 0.15
_OVERLAP = "rings overlap in projection"
_EDGE_ON = "marker seen edge-on (ring ellipse too flat to identify)"
_OUTSIDE = "ring mostly outside the field of view"
# Rejections of a ring's BB pattern: too many BBs inside one ellipse can be two rings' (_one_ellipse).
_NO_MATCH = ("no marker matches", "ambiguous BB pattern")
# Rejections that a lower threshold cannot change: geometry, not contrast.
_NOT_CONTRAST = (_OVERLAP, _EDGE_ON, _OUTSIDE, "marker id ")


def _find_markers(img, bb_image, wire_image, marker_set: MarkerSet, *, bb_threshold: float, wire_threshold: float, wire_low: float, ring_r: float, wire_px: float,
                  magnification_range: tuple[float, float], pixel_spacing_mm: float) -> FluoroDetections:
    """The rings, BBs and identified markers at one pair of thresholds (log units above the top-hat's background)."""
    blobs = _blobs(bb_image, bb_threshold)
    min_ring_px = 2 * ring_r * magnification_range[0] / pixel_spacing_mm * 0.3
    max_ring_px = 2 * ring_r * magnification_range[1] / pixel_spacing_mm * 1.1
    markers: list[DetectedMarker] = []
    rejected: list[RejectedRing] = []
    ring = dict(blobs=blobs, marker_set=marker_set, ring_r=ring_r, wire_px=wire_px, min_ring_px=min_ring_px, max_ring_px=max_ring_px, shape=img.shape)
    for group in _arcs_of_one_ring(_wire_components(wire_image, high=wire_threshold, low=wire_low, min_extent_px=min_ring_px),
                                   wire_px=wire_px, max_ring_px=max_ring_px):
        if len(group) > 1:
            # Arcs that one ellipse joins: the ring whole, when that identifies its marker; else each arc as it is.
            whole = _piece_markers(_joined(group), ring)
            if any(isinstance(r, DetectedMarker) for r in whole):
                markers += [r for r in whole if isinstance(r, DetectedMarker)]
                rejected += [r for r in whole if isinstance(r, RejectedRing)]
                continue
        for piece in group:
            found = _piece_markers(piece, ring)
            markers += [r for r in found if isinstance(r, DetectedMarker)]
            rejected += [r for r in found if isinstance(r, RejectedRing)]
    markers, twice = _merge_split_rings(markers)
    rejected += twice
    every = tuple(DetectedBB(center_px=c, diameter_px=float(d), large=False, elongation=e) for c, d, e in blobs)
    return FluoroDetections(markers=tuple(sorted(markers, key=lambda m: m.marker_id)), rejected=tuple(rejected), blobs=every)


def _piece_markers(component, ring: dict) -> list:
    """The markers and rejected rings of one piece of wire ((piece, its pieces over the high threshold alone), as
    :func:`_wire_components` gives it)."""
    piece, strong_pieces = component
    found = _ring_marker(*piece, **ring)
    if isinstance(found, RejectedRing) and strong_pieces:
        # What hysteresis grew did not identify a marker (two rings joined, anatomy's texture bent its
        # ellipse): the pieces over the high threshold alone, as a single threshold would have found them.
        alone = [_ring_marker(*p, **ring) for p in strong_pieces]
        if any(isinstance(r, DetectedMarker) for r in alone):
            return [r for r in alone if r is not None]
    if isinstance(found, RejectedRing) and (found.reason == _OVERLAP or (found.reason.startswith(_NO_MATCH) and not _one_ellipse(piece[1], ring["wire_px"]))):
        split = _split_overlap(piece[1], **ring)
        if any(isinstance(r, DetectedMarker) for r in split):
            return split
    return [] if found is None else [found]


def _arcs_of_one_ring(components: list, *, wire_px: float, max_ring_px: float) -> list[list]:
    """``components`` (:func:`_wire_components`) grouped: pieces whose union one ellipse follows
    (:func:`_one_ellipse`), no larger than a ring, and each within ``2 wire_px`` of another of its group, in one group;
    every other piece alone.

    A flat ring's BBs lie along its wire, and the BB image's opening takes the wire with them where they touch it: the
    ring breaks into arcs. Each arc fits an ellipse of its own, shorter than the ring and off along it; an arc holding
    the BBs of its half can then identify its marker on a pattern slid by one BB (twin seed 13502, AP+lateral, markers
    flat: the lateral ring of marker 11 at 0.11 broke in two halves, the upper one identified marker 11 with its centre
    22 px off along the ring and two of six BBs paired with their neighbours' design places)."""
    groups = [[c] for c in components]
    while True:
        pair = next(((a, b) for a in range(len(groups)) for b in range(a + 1, len(groups))
                     if _arcs_join(groups[a], groups[b], wire_px=wire_px, max_ring_px=max_ring_px)), None)
        if pair is None:
            return groups
        a, b = pair
        groups[a] = groups[a] + groups.pop(b)


def _box(group: list) -> NDArray[np.float64]:
    """(x0, y0, x1, y1) px: the bounding box of a group of pieces (their connected-component stats)."""
    s = np.array([c[0][0][:4] for c in group], dtype=np.float64)
    return np.concatenate([s[:, :2].min(axis=0), (s[:, :2] + s[:, 2:4] - 1).max(axis=0)])


def _arcs_join(first: list, second: list, *, wire_px: float, max_ring_px: float) -> bool:
    ba, bb = _box(first), _box(second)
    # No larger than a ring together, and their boxes within 2 wire widths; then their nearest pixels so.
    if float(np.max(np.maximum(ba[2:], bb[2:]) - np.minimum(ba[:2], bb[:2]))) > max_ring_px:
        return False
    if np.any(np.maximum(ba[:2], bb[:2]) - np.minimum(ba[2:], bb[2:]) > 2 * wire_px):
        return False
    pa = np.concatenate([c[0][1] for c in first])
    pb = np.concatenate([c[0][1] for c in second])
    if float(cKDTree(pa).query(pb, k=1)[0].min()) > 2 * wire_px:
        return False
    return _one_ellipse(np.concatenate([pa, pb]), wire_px)


def _joined(group: list):
    """One piece of wire (as :func:`_wire_components` gives it) from a group of arcs (:func:`_arcs_of_one_ring`)."""
    pts = np.concatenate([c[0][1] for c in group])
    x, y = pts.min(axis=0)
    w, h = pts.max(axis=0) - pts.min(axis=0) + 1
    return ((int(x), int(y), int(w), int(h), len(pts)), pts), [p for c in group for p in c[1]]


def _one_ellipse(pts, wire_px: float, *, share: float = 0.85) -> bool:
    """Whether at least ``share`` of a piece's pixels (N, 2) lie within ``wire_px`` of the one ellipse fitted to them:
    two rings crossing within one ring's size make a piece no larger than a ring, whose single ellipse runs between
    them, and whose BBs (both markers') match no marker."""
    d, _theta = ellipse_distance(np.asarray(pts, dtype=np.float64), cv2.fitEllipse(pts))
    return float(np.mean(d < wire_px)) >= share


def _split_overlap(pts, *, blobs, **ring) -> list:
    """The markers (and rejected rings) of a piece of wire made of rings crossing in projection: too large to be one
    ring, or fitted by one ellipse its pixels do not follow (:func:`_one_ellipse`) whose BBs matched no marker.

    The piece is split into its ellipses (:func:`.ring_split.split_rings`) and each is taken as a ring of its own.
    Where the ellipses overlap, one ring's BBs lie inside another: a ring that identifies no marker among every
    blob inside it is tried again without the BBs the piece's identified markers matched.
    """
    rings = split_rings(pts, min_major_px=ring["min_ring_px"], max_major_px=ring["max_ring_px"], wire_px=ring["wire_px"], min_minor_ratio=EDGE_ON_MINOR_RATIO,
                        shape=ring["shape"])
    found: list = [None] * len(rings)
    for _ in range(2):
        taken = {blob_key(b.center_px) for m in found if isinstance(m, DetectedMarker) for b, i in zip(m.bbs, m.bb_index) if i >= 0}
        free = [b for b in blobs if blob_key(b[0]) not in taken]
        for k, own in enumerate(rings):
            if isinstance(found[k], DetectedMarker):
                continue
            x, y = own.min(axis=0)
            w, h = own.max(axis=0) - own.min(axis=0) + 1
            found[k] = _ring_marker((int(x), int(y), int(w), int(h), len(own)), own, blobs=free if taken else blobs, **ring)
        if not taken and not any(isinstance(m, DetectedMarker) for m in found):
            break
    return [f for f in found if f is not None]


# identify's own limit on a pattern's mean alignment cost, and the looser one for a ring whose identity the camera
# corroborates (its tag seen in the frame): on the operating-room twin (seeds 6400-6405 and 6500-6505, every
# pair) 12 rings rejected for cost with their best marker not identified elsewhere in the view matched within
# 0.91-1.20 mm, every one the true marker; the wrong matches of such rings cost 1.53 mm and more (0.97 mm for one
# whose best marker the view had already identified). With identify's margin over the runner-up applied, the
# candidates kept there are 7, one of them wrong, on 3 BBs (too few for register_markers to pose).
IDENTIFY_MAX_COST_MM = 0.9
CORROBORATED_MAX_COST_MM = 1.2
# A ring that identifies no marker is matched against each marker of the set alone, up to this cost: in low dose and
# behind dense bone the true marker's pattern costs 0.7-2.2 mm, often with no margin over the others (seeds 6200-6201,
# every view, measured). Such a match names nothing by itself; the camera's constellation settles it (video_claims).
LOOSE_MAX_COST_MM = 2.0


def _ring_marker(stats, pts, *, blobs, marker_set: MarkerSet, ring_r: float, wire_px: float, min_ring_px: float, max_ring_px: float,
                 shape: tuple[int, int]) -> "DetectedMarker | RejectedRing | None":
    """One piece of wire: the marker its ring identifies, why it identifies none, or None (too small to be a ring)."""
    x, y, w, h, area = stats
    rows, cols = shape
    if max(w, h) < min_ring_px or area < 100:
        return None
    centre = pts.mean(axis=0)
    if max(w, h) > max_ring_px:
        return RejectedRing(reason=_OVERLAP, center_px=centre.astype(float))
    if x <= 1 or y <= 1 or x + w >= cols - 1 or y + h >= rows - 1:
        # A ring cut by the field's edge still gives an ellipse from its arc, and its BBs inside the field
        # still count: reject only when too little of the wire is left to fit.
        inner = pts[(pts[:, 0] > 2) & (pts[:, 1] > 2) & (pts[:, 0] < cols - 3) & (pts[:, 1] < rows - 3)]
        if len(inner) < 0.4 * np.pi * min_ring_px * wire_px or _arc_span_deg(inner) < 180.0:
            return RejectedRing(reason=_OUTSIDE, center_px=centre.astype(float))
        pts = inner
    ellipse = cv2.fitEllipse(pts)
    (cx, cy), (d1, d2), angle = ellipse
    major, minor = max(d1, d2) / 2.0, min(d1, d2) / 2.0
    if minor < EDGE_ON_MINOR_RATIO * major:
        return RejectedRing(reason=_EDGE_ON, center_px=np.array([cx, cy]))
    inside = [b for b in blobs if _inside(b[0], ellipse, 0.9)]
    if len(inside) < 3:
        return RejectedRing(reason=f"only {len(inside)} BBs inside the ring", center_px=np.array([cx, cy]))
    scale = major / ring_r  # px per mm at the marker
    centers = np.array([b[0] for b in inside])
    diam_px = np.array([b[1] for b in inside])
    elong = np.array([b[2] for b in inside])
    plane = _rectify(centers, ellipse) / scale
    ident, diam_mm, last_error = _identify_ring(plane, diam_px, marker_set, max_cost_mm=IDENTIFY_MAX_COST_MM)
    no_match = isinstance(last_error, MarkerNotIdentified) and str(last_error).startswith("no marker matches")
    if ident is None and no_match and minor < FLAT_MINOR_RATIO * major:
        # _rectify stretched each ellipse axis d to the major (2 major): d / (2 major) measures it as the image does.
        image_measure = (d1 / (2 * major), d2 / (2 * major))
        flat, flat_mm, _ = _identify_ring(plane, diam_px, marker_set, max_cost_mm=IDENTIFY_MAX_COST_MM, metric=image_measure)
        if flat is not None:
            ident, diam_mm = flat, flat_mm
    if ident is None:
        reason = str(last_error) if last_error else "no central BB found inside the ring"
        candidate = None
        if isinstance(last_error, MarkerNotIdentified) and str(last_error).startswith("no marker matches"):
            loose, loose_mm, _ = _identify_ring(plane, diam_px, marker_set, max_cost_mm=CORROBORATED_MAX_COST_MM)
            if loose is not None:
                candidate = _detected(loose, centers, diam_px, loose_mm, ellipse, elong)
        return RejectedRing(reason=reason, center_px=np.array([cx, cy]), candidate=candidate,
                            loose=_loose(plane, diam_px, centers, ellipse, marker_set, elong) if isinstance(last_error, MarkerNotIdentified) else ())
    if minor < FEW_BB_EDGE_ON_RATIO * major and int(np.count_nonzero(ident.bb_index >= 0)) < 5:
        return RejectedRing(reason=_EDGE_ON, center_px=np.array([cx, cy]))
    return _detected(ident, centers, diam_px, diam_mm, ellipse, elong)


def _detected(ident, centers, diam_px, diam_mm, ellipse, elongation) -> DetectedMarker:
    bbs = tuple(DetectedBB(center_px=c, diameter_px=float(d), large=bool(dm > 2.75), elongation=float(e))
                for c, d, dm, e in zip(centers, diam_px, diam_mm, elongation))
    return DetectedMarker(marker_id=ident.marker_id, bbs=bbs, bb_index=ident.bb_index, ring_ellipse=ellipse, mirrored=ident.mirrored, identification_cost_mm=ident.cost,
                          alternative_bb_index=ident.alternative_bb_index)


def _loose(plane, diam_px, centers, ellipse, marker_set: MarkerSet, elongation) -> tuple[DetectedMarker, ...]:
    """The ring's BBs (4 or more) matched against each marker of the set alone, those within LOOSE_MAX_COST_MM."""
    if len(plane) < 4:
        return ()
    out = []
    for marker_id in marker_set.ids:
        ident, diam_mm, _ = _identify_ring(plane, diam_px, marker_set.subset([marker_id]), max_cost_mm=LOOSE_MAX_COST_MM)
        if ident is not None and int((ident.bb_index >= 0).sum()) >= 4:
            out.append(_detected(ident, centers, diam_px, diam_mm, ellipse, elongation))
    return tuple(out)


def _identify_ring(plane, diam_px, marker_set: MarkerSet, *, max_cost_mm: float, metric: tuple[float, float] | None = None):
    """(identification or None, BB diameters mm, the last identification error or None) of a ring's BBs rectified
    into its plane (N, 2) mm, identified at ``max_cost_mm`` (and identify's ``metric``)."""
    ident, diam_mm, last_error = None, None, None
    order = np.argsort(np.linalg.norm(plane, axis=1))
    # Every marker's smallest BB is 2.0 mm (the central one), so the smallest blob calibrates the sizes. A
    # blob smaller than any BB inside the ring (a K-wire's end, a clamp's corner, a BB half under metal)
    # makes every BB look large: only then each candidate, as the 2.0 mm central BB, calibrates them
    # itself; identify's cost and margin still decide.
    for own_scale in (False, True):
        for c in order[:3]:
            sizes_mm = diam_px * (2.0 / (diam_px[c] if own_scale else diam_px.min()))
            if sizes_mm[c] > 2.75 or np.linalg.norm(plane[c]) > 6.0:
                continue
            try:
                candidate = identify(plane - plane[c], sizes_mm, marker_set, max_cost_mm=max_cost_mm, metric=metric)
            except MarkerNotIdentified as exc:
                last_error = exc
                continue
            if ident is None or candidate.cost < ident.cost:
                ident, diam_mm = candidate, sizes_mm
        if ident is not None:
            break
    if ident is None and len(plane) >= 4:
        # No blob where the central BB belongs (dense bone, a K-wire or the dose hid it), or none of the small blobs
        # near the centre, each taken for it, gave a match: the ring's centre stands in for it (weak perspective:
        # within a fraction of a mm in the plane at these tilts), the smallest blob is one of the code's 2.0 mm BBs,
        # and the central BB is the pattern's one missing BB. After the blobs near the centre failed, the lateral
        # views of the study's 16 seeds (below, EDGE_ON_MINOR_RATIO) identify 2 markers more, none wrongly; their
        # random and inlet/outlet pairs identify the same (measured before touching blobs were split, which
        # identifies both of those markers too).
        sizes_mm = diam_px * (2.0 / diam_px.min())
        try:
            centred = identify(plane, sizes_mm, marker_set, max_cost_mm=max_cost_mm, metric=metric)
        except MarkerNotIdentified as exc:
            last_error = last_error or exc
        else:
            if not np.any(centred.bb_index == 0):  # a blob taken for the central BB after all: not the case this is for
                ident, diam_mm = centred, sizes_mm
    return ident, diam_mm, last_error


def _wire_components(wire_image: NDArray[np.float32], *, high: float, low: float, min_extent_px: float):
    """The wire's connected pieces, each as (piece, the pieces over ``high`` alone within it); a piece is
    ((x, y, w, h, area), pixels (N, 2) float32 column, row).

    Hysteresis keeps a thin, noisy wire whole: its pixels over ``low`` that connect to one over ``high``. It can
    also join two rings, or a ring and anatomy, through their weak pixels; the pieces over ``high`` alone (what a
    single threshold finds) are then tried instead (``_find_markers``). Pieces under ``min_extent_px`` across
    (no ring) are left out.
    """
    close = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    strong = cv2.morphologyEx((wire_image > high).astype(np.uint8), cv2.MORPH_CLOSE, close)
    grown = cv2.morphologyEx(_hysteresis(wire_image, high=high, low=low), cv2.MORPH_CLOSE, close)
    out = []
    n, labels, stats, _ = cv2.connectedComponentsWithStats(grown, connectivity=8)
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        if max(w, h) < min_extent_px:
            continue
        own = labels[y : y + h, x : x + w] == i
        pts = np.column_stack(np.nonzero(own)[::-1]).astype(np.float32) + np.float32([x, y])
        pieces = []
        sub = strong[y : y + h, x : x + w] * own.astype(np.uint8)
        if low < high and np.count_nonzero(sub) < area:
            m, sub_labels, sub_stats, _ = cv2.connectedComponentsWithStats(sub, connectivity=8)
            for j in range(1, m):
                sx, sy, sw, sh, sarea = sub_stats[j]
                pieces.append(((x + sx, y + sy, sw, sh, sarea), np.column_stack(np.nonzero(sub_labels == j)[::-1]).astype(np.float32) + np.float32([x, y])))
        out.append((((x, y, w, h, area), pts), pieces))
    return out


def _hysteresis(image: NDArray[np.float32], *, high: float, low: float) -> NDArray[np.uint8]:
    """Mask (uint8 0/1) of the pixels over ``low`` that are connected (8-neighbours) to a pixel over ``high``."""
    weak = (image > low).astype(np.uint8)
    if low >= high:
        return weak
    n, labels = cv2.connectedComponents(weak, connectivity=8)
    keep = np.zeros(n, bool)
    keep[np.unique(labels[image > high])] = True
    keep[0] = False
    return keep[labels].astype(np.uint8)


def _one_ring(found: list[DetectedMarker]) -> DetectedMarker | None:
    """Detections of one id: the best-fitting one when all are pieces of one ring (each shares at least 3 BB centres
    with it), None when they lie on different BBs (two rings claiming one identity)."""
    best = min(found, key=lambda m: m.identification_cost_mm)
    own = {blob_key(b.center_px) for b in best.bbs}
    return best if all(len(own & {blob_key(b.center_px) for b in m.bbs}) >= 3 for m in found) else None


# Two rings on different BBs that one id identifies: the one whose pattern fits it better by at least this (mm) is
# that marker, the other is not. Over 16 seeds of the accuracy study (flat and default markers, every view of
# the three pairs, 639 identifications), 4 were wrong, all at 0.73-0.86 mm, and the two that claimed an id another
# ring holds lost to the true ring by 0.58 and 0.81 mm (seeds 10400 and 10900, flat, outlet views; the true rings
# at 0.23 and 0.05 mm). Correct identifications cost up to 0.89 mm, so a closer pair is not settled.
DUPLICATE_MARGIN_MM = 0.3


def _merge_split_rings(markers: list[DetectedMarker]) -> tuple[list[DetectedMarker], list[RejectedRing]]:
    """One detection per id: the pieces of one ring, each identified alike, kept once; of two rings with one id,
    the one that fits it by DUPLICATE_MARGIN_MM better, else neither.

    Metal crossing a ring (a clamp's jaw, a K-wire) cuts its wire into arcs, each fitted and identified on
    its own from the same BBs. Pieces that share at least 3 BB centres are one marker: the best-fitting
    identification is kept. Two detections of one id on different BBs are two rings claiming one identity:
    a ring whose pattern matches the design by the margin better is that marker and the others are rejected, named
    as beaten; closer than that, which is which is not guessed and every one is rejected.
    """
    by_id: dict[int, list[DetectedMarker]] = {}
    for m in markers:
        by_id.setdefault(m.marker_id, []).append(m)
    kept: list[DetectedMarker] = []
    rejected: list[RejectedRing] = []
    for marker_id, found in by_id.items():
        best = _one_ring(found)
        if best is not None:
            kept.append(best)
            continue
        best = min(found, key=lambda m: m.identification_cost_mm)
        rivals = [m for m in found if m is not best]
        if all(m.identification_cost_mm - best.identification_cost_mm >= DUPLICATE_MARGIN_MM for m in rivals):
            kept.append(best)
            x, y = best.ring_ellipse[0]
            for m in rivals:
                rejected.append(RejectedRing(reason=f"marker id {marker_id} found twice; the ring at ({x:.0f}, {y:.0f}) px fits it "
                                                    f"better ({best.identification_cost_mm:.2f} against {m.identification_cost_mm:.2f} mm)",
                                             center_px=np.array(m.ring_ellipse[0])))
            continue
        for m in found:
            rejected.append(RejectedRing(reason=f"marker id {marker_id} found twice", center_px=np.array(m.ring_ellipse[0])))
    return kept, rejected


def _arc_span_deg(points: NDArray[np.float32]) -> float:
    """Angular span (deg) of wire pixels about their bounding box centre: 360 for a whole ring."""
    c = (points.min(axis=0) + points.max(axis=0)) / 2.0
    ang = np.sort(np.degrees(np.arctan2(points[:, 1] - c[1], points[:, 0] - c[0])))
    gaps = np.diff(np.concatenate([ang, ang[:1] + 360.0]))
    return float(360.0 - gaps.max())


def _inside(p, ellipse, factor: float) -> bool:
    (cx, cy), (d1, d2), angle = ellipse
    a = np.radians(angle)
    dx, dy = p[0] - cx, p[1] - cy
    u = dx * np.cos(a) + dy * np.sin(a)
    v = -dx * np.sin(a) + dy * np.cos(a)
    return (u / (d1 / 2 * factor)) ** 2 + (v / (d2 / 2 * factor)) ** 2 <= 1.0


def _rectify(points: NDArray[np.float64], ellipse) -> NDArray[np.float64]:
    """Map image points into the circle's frame: stretch the ellipse's minor axis to the major (weak perspective)."""
    (cx, cy), (d1, d2), angle = ellipse
    a = np.radians(angle)
    rot = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    local = (points - [cx, cy]) @ rot.T
    major = max(d1, d2)
    local[:, 0] *= major / d1
    local[:, 1] *= major / d2
    return local
