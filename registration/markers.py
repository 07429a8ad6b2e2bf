"""The multimodal marker set: ArUco tag + tungsten BBs + wire ring.

Marker frame m: origin at the central BB, +z along the normal towards the tag
(camera) side, BBs and ring in the plane z = 0, the 30 mm tag centred at
(0, 0, +2) mm with the marker's x/y axes.

Outer BBs sit on a polar grid of 8 rays x 2 radii. A BB is only placed on a
line through the centre that carries at least two outer BBs, so every BB is
collinear with at least two others (the centre and its partner), which lets
fluoroscopy feature extraction reject false candidates. Each grid site is
empty, small (2.0 mm) or large (3.5 mm); the 48 codes are chosen so that any
two differ in at least ``MIN_CODE_DISTANCE`` sites under every rotation of the
grid and under mirroring, and no code is within that distance of its own
rotations or mirror image (so the orientation is unambiguous too). That holds
for the whole pattern: a part of it (BBs lost, a ring nearly edge-on) may pair
with the design two ways, which :func:`identify` reports.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from .errors import DrillnavError

__all__ = [
    "BB",
    "MarkerDesign",
    "MarkerSet",
    "Identification",
    "UnknownMarker",
    "MarkerNotIdentified",
    "default_marker_set",
    "identify",
    "code_distance",
    "GRID_RADII_MM",
    "N_RAYS",
    "MIN_CODE_DISTANCE",
]

N_RAYS = 8
GRID_RADII_MM = (8.0, 15.0)
SMALL_MM, LARGE_MM = 2.0, 3.5
CENTRAL_BB_MM = 2.0
MIN_CODE_DISTANCE = 3
N_MARKERS = 48
DESIGN_SEED = 20210121


class UnknownMarker(DrillnavError, KeyError):
    """A marker id outside the configured marker set."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0]) if self.args else "unknown marker"


class MarkerNotIdentified(DrillnavError):
    """An observed BB pattern matches no marker, or two markers equally well."""


@dataclass(frozen=True, kw_only=True)
class BB:
    """A tungsten ball bearing: centre (3,) in the marker frame, mm, and diameter, mm."""

    center_mm: NDArray[np.float64]
    diameter_mm: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center_mm", np.asarray(self.center_mm, dtype=np.float64).reshape(3))


@dataclass(frozen=True, kw_only=True)
class MarkerDesign:
    """One multimodal marker, all lengths in mm in the marker frame."""

    marker_id: int
    aruco_id: int
    bbs: tuple[BB, ...]
    aruco_dictionary: str = "DICT_6X6_250"
    tag_size_mm: float = 30.0
    tag_center_mm: NDArray[np.float64] = field(default_factory=lambda: np.array([0.0, 0.0, 2.0]))
    ring_center_mm: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    ring_normal: NDArray[np.float64] = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    ring_radius_mm: float = 24.0
    ring_wire_diameter_mm: float = 0.8
    code: tuple[int, ...] = ()

    @property
    def bb_centers_mm(self) -> NDArray[np.float64]:
        """(N, 3) BB centres, central BB first."""
        return np.stack([b.center_mm for b in self.bbs])

    @property
    def bb_diameters_mm(self) -> NDArray[np.float64]:
        return np.array([b.diameter_mm for b in self.bbs])

    def tag_corners_mm(self) -> NDArray[np.float64]:
        """(4, 3) tag corners in the marker frame, OpenCV order (TL, TR, BR, BL)."""
        h = self.tag_size_mm / 2.0
        return np.asarray(self.tag_center_mm) + np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)

    def ring_points_mm(self, n: int = 256) -> NDArray[np.float64]:
        """(n, 3) points on the wire ring's centre line."""
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.asarray(self.ring_center_mm) + self.ring_radius_mm * np.stack([np.cos(t), np.sin(t), np.zeros(n)], axis=1)

    def with_bb_errors(self, rng: np.random.Generator, sigma_mm: float) -> "MarkerDesign":
        """The marker as manufactured: every BB moved by N(0, sigma_mm) per axis."""
        moved = tuple(BB(center_mm=b.center_mm + rng.normal(scale=sigma_mm, size=3), diameter_mm=b.diameter_mm) for b in self.bbs)
        return replace(self, bbs=moved)


@dataclass(frozen=True, kw_only=True)
class MarkerSet:
    markers: tuple[MarkerDesign, ...]

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(m.marker_id for m in self.markers)

    def by_id(self, marker_id: int) -> MarkerDesign:
        for m in self.markers:
            if m.marker_id == marker_id:
                return m
        raise UnknownMarker(f"unknown marker id {marker_id}: the set holds ids {_ranges(self.ids)}")

    def subset(self, ids) -> "MarkerSet":
        return MarkerSet(markers=tuple(self.by_id(int(i)) for i in ids))


def _ranges(ids: tuple[int, ...]) -> str:
    if not ids:
        return "none"
    s = sorted(ids)
    if s == list(range(s[0], s[-1] + 1)):
        return f"{s[0]}-{s[-1]}"
    return ", ".join(map(str, s))


# -- codes ------------------------------------------------------------------------------
# Site index = ray * 2 + radius_index; value 0 empty, 1 small, 2 large.

def _site_xy() -> NDArray[np.float64]:
    ang = 2 * np.pi * np.arange(N_RAYS) / N_RAYS
    return np.array([[r * np.cos(a), r * np.sin(a)] for a in ang for r in GRID_RADII_MM])


def _transform_code(code: NDArray[np.int64], rotation: int, mirror: bool) -> NDArray[np.int64]:
    c = code.reshape(N_RAYS, len(GRID_RADII_MM))
    if mirror:  # reflect about the x axis: ray k -> -k
        c = c[(-np.arange(N_RAYS)) % N_RAYS]
    return np.roll(c, rotation, axis=0).reshape(-1)


def code_distance(a: NDArray[np.int64], b: NDArray[np.int64]) -> int:
    """Minimum number of differing sites between code ``a`` and any rotation/mirror of ``b``."""
    return min(int(np.count_nonzero(a != _transform_code(b, r, m))) for r in range(N_RAYS) for m in (False, True))


def _self_distance(a: NDArray[np.int64]) -> int:
    return min(int(np.count_nonzero(a != _transform_code(a, r, m))) for r in range(N_RAYS) for m in (False, True) if (r, m) != (0, False))


def _collinear_ok(code: NDArray[np.int64]) -> bool:
    c = code.reshape(N_RAYS, -1)
    half = N_RAYS // 2
    for k in range(half):
        n = np.count_nonzero(c[k]) + np.count_nonzero(c[k + half])
        if n == 1:
            return False
    return True


def _design_codes() -> list[NDArray[np.int64]]:
    rng = np.random.default_rng(DESIGN_SEED)
    n_sites = N_RAYS * len(GRID_RADII_MM)
    codes: list[NDArray[np.int64]] = []
    while len(codes) < N_MARKERS:
        code = np.zeros(n_sites, dtype=np.int64)
        # 3 of the 4 lines through the centre carry 2 BBs each: 6 outer BBs, readable yet sparse.
        for line in rng.choice(N_RAYS // 2, size=3, replace=False):
            sites = [line * 2, line * 2 + 1, (line + N_RAYS // 2) * 2, (line + N_RAYS // 2) * 2 + 1]
            for s in rng.choice(sites, size=2, replace=False):
                code[s] = rng.integers(1, 3)
        if not _collinear_ok(code) or _self_distance(code) < MIN_CODE_DISTANCE:
            continue
        if all(code_distance(code, c) >= MIN_CODE_DISTANCE for c in codes):
            codes.append(code)
    return codes


def _design_from_code(marker_id: int, code: NDArray[np.int64]) -> MarkerDesign:
    xy = _site_xy()
    bbs = [BB(center_mm=np.zeros(3), diameter_mm=CENTRAL_BB_MM)]
    for site, value in enumerate(code):
        if value:
            bbs.append(BB(center_mm=np.array([xy[site, 0], xy[site, 1], 0.0]), diameter_mm=SMALL_MM if value == 1 else LARGE_MM))
    return MarkerDesign(marker_id=marker_id, aruco_id=marker_id, bbs=tuple(bbs), code=tuple(int(v) for v in code))


_DEFAULT: MarkerSet | None = None


def default_marker_set() -> MarkerSet:
    """The 48 markers (ids 0-47, ArUco DICT_6X6_250 ids 0-47). Deterministic."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = MarkerSet(markers=tuple(_design_from_code(i, c) for i, c in enumerate(_design_codes())))
    return _DEFAULT


# -- identification ---------------------------------------------------------------------

@dataclass(frozen=True, kw_only=True)
class Identification:
    """Best match of an observed BB pattern to the marker set.

    bb_index : (N,) index into the design's ``bbs`` for each observed BB, -1 if unmatched.
    rotation_rad, mirrored : the in-plane rotation (after mirroring about x) taking design to observation.
    cost : mean alignment cost of the match; margin : runner-up cost minus cost.
    alternative_bb_index : (N,) the same marker's next best assignment when it costs within
        :data:`ASSIGNMENT_TIE_MM` of the best and pairs some BB with another design BB (None: none does). A part
        of the pattern that a reflection about a line through its centre, or a half-turn about it, maps onto
        itself (a marker seen nearly edge-on, BBs lost) matches that way as well: the two pairings' poses are a
        half-turn apart (about that line, or about the normal), and only another view or the camera's view of
        the tag tells which is right (:func:`.marker_pose.register_markers`).
    """

    marker_id: int
    rotation_rad: float
    mirrored: bool
    bb_index: NDArray[np.int64]
    cost: float
    margin: float
    alternative_bb_index: NDArray[np.int64] | None = None


# A second assignment of the same marker's BBs whose cost is within this of the best (mm) is kept as an
# alternative. The two pairings of a symmetric part of a pattern cost the same but for the noise (twin seed 7000,
# marker 38 on five BBs in a lateral view: 0.0002 mm apart), so either may win.
ASSIGNMENT_TIE_MM = 0.1


def _match_costs(obs_xy, obs_large, design: MarkerDesign, angles, mirrored: bool, tol: float, metric: tuple[float, float] | None = None):
    """Alignment cost (A,) and assignment (A, N) of the observation to the design at each angle. ``metric`` (2,):
    weights of the two plane axes' differences (None: 1, 1)."""
    d_xy = design.bb_centers_mm[:, :2].copy()
    if mirrored:
        d_xy[:, 1] *= -1
    c, s = np.cos(angles), np.sin(angles)
    rot_x = c[:, None] * d_xy[None, :, 0] - s[:, None] * d_xy[None, :, 1]
    rot_y = s[:, None] * d_xy[None, :, 0] + c[:, None] * d_xy[None, :, 1]
    d_large = design.bb_diameters_mm > 2.75
    wx, wy = (1.0, 1.0) if metric is None else metric
    dist = np.hypot(wx * (obs_xy[None, :, None, 0] - rot_x[:, None, :]), wy * (obs_xy[None, :, None, 1] - rot_y[:, None, :]))
    dist = dist + np.where(obs_large[:, None] != d_large[None, :], tol, 0.0)[None]
    idx = np.argmin(dist, axis=2)
    best = np.take_along_axis(dist, idx[:, :, None], axis=2)[:, :, 0]
    matched = best < tol
    m = len(d_xy)
    seen = np.zeros((len(angles), m), dtype=bool)
    rows = np.repeat(np.arange(len(angles)), obs_xy.shape[0])
    seen[rows[matched.ravel()], idx.ravel()[matched.ravel()]] = True
    n_unseen = m - seen.sum(axis=1)
    # Unmatched observations and unseen design BBs both cost a full tolerance.
    cost = (np.minimum(best, tol).sum(axis=1) + tol * n_unseen) / (obs_xy.shape[0] + m)
    return cost, np.where(matched, idx, -1)


def identify(
    points_plane_mm: NDArray[np.float64],
    diameters_mm: NDArray[np.float64],
    marker_set: MarkerSet,
    *,
    tolerance_mm: float = 2.5,
    max_cost_mm: float = 0.9,
    min_margin_mm: float = 0.15,
    metric: tuple[float, float] | None = None,
) -> Identification:
    """Identify a marker from BB centres (N, 2) rectified into its plane (central BB near the origin).

    Tolerates a missing or spurious BB and noise of about 1 mm; tries every
    in-plane rotation (1 deg steps, then refined) and both faces. ``metric``: weights (2,) of the differences along
    the plane's two axes in every distance (None: both 1), e.g. a flat ring's stretched axis measured as the image
    shows it (:data:`.fluoro_markers.FLAT_MINOR_RATIO`).
    """
    obs = np.asarray(points_plane_mm, dtype=np.float64).reshape(-1, 2)
    large = np.asarray(diameters_mm, dtype=np.float64).reshape(-1) > 2.75
    if obs.shape[0] < 3:
        raise MarkerNotIdentified(f"only {obs.shape[0]} BBs observed; at least 3 are needed to identify a marker")
    angles = np.radians(np.arange(0.0, 360.0, 1.0))
    results, matches = [], {}
    for design in marker_set.markers:
        best = (np.inf, None, 0.0, False)
        for mirrored in (False, True):
            costs, idx = _match_costs(obs, large, design, angles, mirrored, tolerance_mm, metric)
            matches[design.marker_id, mirrored] = (costs, idx)
            k = int(np.argmin(costs))
            if costs[k] < best[0]:
                best = (float(costs[k]), idx[k], float(angles[k]), mirrored)
        results.append((best[0], design.marker_id, best[1], best[2], best[3]))
    results.sort(key=lambda r: r[0])
    cost, marker_id, idx, angle, mirrored = results[0]
    margin = results[1][0] - cost if len(results) > 1 else np.inf
    if cost > max_cost_mm:
        raise MarkerNotIdentified(f"no marker matches the observed {len(obs)} BBs (best: marker {marker_id}, cost {cost:.2f} mm)")
    if margin < min_margin_mm:
        raise MarkerNotIdentified(f"ambiguous BB pattern: markers {marker_id} and {results[1][1]} match almost equally")
    return Identification(marker_id=int(marker_id), rotation_rad=float(angle), mirrored=bool(mirrored), bb_index=idx.astype(np.int64), cost=float(cost), margin=float(margin),
                          alternative_bb_index=_alternative(idx, cost, [matches[marker_id, m] for m in (False, True)]))


def _alternative(best_idx: NDArray[np.int64], best_cost: float, matches) -> NDArray[np.int64] | None:
    """The cheapest assignment among ``matches`` ([(costs (A,), assignments (A, N))] per face) that pairs some BB
    with another design BB than ``best_idx`` (N,) does (one only leaving a BB unpaired is the same pairing), when it
    costs within ASSIGNMENT_TIE_MM of ``best_cost``; else None."""
    alt, alt_cost = None, best_cost + ASSIGNMENT_TIE_MM
    for costs, idx in matches:
        differs = np.any((idx != best_idx[None]) & (idx >= 0) & (best_idx[None] >= 0), axis=1)
        if np.any(differs):
            k = int(np.flatnonzero(differs)[np.argmin(costs[differs])])
            if costs[k] <= alt_cost:
                alt, alt_cost = idx[k].astype(np.int64), float(costs[k])
    return alt
