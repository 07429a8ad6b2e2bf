"""Fluoroscopy-to-CT 3D-2D registration: DRRs of the CT, gradient correlation, CMA-ES, coarse to fine.

As in the reference: the CT is rigidly moved (``carm_from_ct``) to maximise
gradient correlation (GC: the mean of the normalised cross-correlations of
the horizontal and vertical gradients, insensitive to gradient magnitude and
to content one image has and the other lacks) between each fluoroscopy view
and the CT's DRR, summed over views, by CMA-ES. Each level halves the pixel
and voxel size and narrows the search. Pixels under markers, tools or
the collimator edge are excluded.

The pose is searched as a rotation (rotation vector, rad) about a fixed
centre in the C-arm frame (where the views' central rays meet, the
isocentre for an isocentric C-arm) and a translation (mm), applied on the
left of the initial ``carm_from_ct``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from .carm import CArmView
from .ct_prealign import prealign_translation
from .drr import DrrVolume, render_drr
from .errors import DegenerateInput
from .transforms import from_rotvec, make_transform
from .volume import Volume

__all__ = ["FluoroShot", "Level", "DEFAULT_LEVELS", "SINGLE_VIEW_LEVELS", "LevelOutcome", "CtRegistration", "gradient_correlation", "register_ct", "rotation_centre_mm"]


@dataclass(frozen=True, kw_only=True, eq=False)
class FluoroShot:
    """One view to register against: its geometry, log-attenuation image (rows, columns), pixels to exclude."""

    view: CArmView
    image_log: NDArray[np.float32]
    exclude: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        if self.image_log.shape != (self.view.rows, self.view.columns):
            raise DegenerateInput(f"image is {self.image_log.shape}, its view is {self.view.rows}x{self.view.columns}")
        if self.exclude is not None and self.exclude.shape != self.image_log.shape:
            raise DegenerateInput(f"exclusion mask is {self.exclude.shape}, the image {self.image_log.shape}")


@dataclass(frozen=True, kw_only=True)
class Level:
    """One resolution level: volume downsampling, detector binning, CMA-ES spread and budget."""

    volume_factor: int
    detector_bin: int
    sigma_mm: float
    sigma_deg: float
    popsize: int
    max_evaluations: int
    tol_x: float = 0.02  # stop when CMA-ES's spread falls under this fraction of the initial one
    step_voxels: float = 1.0  # DRR ray step in units of the level volume's smallest voxel


# Pixel sizes at the isocentre for the paper's C-arm: about 2.6, 1.3 and 0.65 mm.
COARSE = Level(volume_factor=4, detector_bin=16, sigma_mm=8.0, sigma_deg=3.0, popsize=14, max_evaluations=1100, tol_x=0.1)
MEDIUM = Level(volume_factor=2, detector_bin=8, sigma_mm=1.5, sigma_deg=0.5, popsize=8, max_evaluations=800, tol_x=0.05)
# The full-resolution volume: a coarser one biases one view's depth by +0.3 mm (its blurred edges
# trade magnification against pose); steps of 1.5 voxels and a small local search keep it fast.
FINE = Level(volume_factor=1, detector_bin=4, sigma_mm=0.4, sigma_deg=0.1, popsize=6, max_evaluations=200, tol_x=0.15, step_voxels=1.5)
# Two or more views fix depth at the medium level; one view needs the fine level's magnification cue.
DEFAULT_LEVELS: tuple[Level, ...] = (COARSE, MEDIUM)
SINGLE_VIEW_LEVELS: tuple[Level, ...] = (COARSE, replace(MEDIUM, max_evaluations=600, tol_x=0.1), FINE)


@dataclass(frozen=True, kw_only=True)
class LevelOutcome:
    level: Level
    similarity: float
    evaluations: int
    stop: str
    seconds: float


@dataclass(frozen=True, kw_only=True)
class CtRegistration:
    """Result: ``carm_from_ct`` (4, 4), final GC in [-1, 1] (mean over views), and how it got there."""

    carm_from_ct: NDArray[np.float64]
    similarity: float
    initial_similarity: float
    converged: bool
    evaluations: int
    runtime_s: float
    levels: tuple[LevelOutcome, ...] = field(default_factory=tuple)

    @property
    def residual(self) -> float:
        """1 - GC: 0 for a perfect match of gradients."""
        return 1.0 - self.similarity


def _gradients(image: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    s = cv2.GaussianBlur(image, (0, 0), 0.7)
    return cv2.Sobel(s, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(s, cv2.CV_32F, 0, 1, ksize=3)


def _normalised(values: NDArray[np.float32]) -> NDArray[np.float32]:
    v = values - values.mean()
    n = float(np.sqrt(np.dot(v, v)))
    return v / n if n > 1e-12 else v * 0.0


def gradient_correlation(fixed: NDArray[np.float32], moving: NDArray[np.float32], valid: NDArray[np.bool_] | None = None) -> float:
    """GC of two images (rows, columns) over ``valid`` pixels: (NCC(dx) + NCC(dy)) / 2."""
    fx, fy = _gradients(np.asarray(fixed, np.float32))
    mx, my = _gradients(np.asarray(moving, np.float32))
    sel = np.ones(fixed.shape, bool) if valid is None else valid
    return 0.5 * (float(np.dot(_normalised(fx[sel]), _normalised(mx[sel]))) + float(np.dot(_normalised(fy[sel]), _normalised(my[sel]))))


def rotation_centre_mm(views: list[CArmView]) -> NDArray[np.float64]:
    """(3,) point nearest every view's central ray (one view: its ray's point nearest the C-arm origin)."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for v in views:
        centre_px = np.array([(v.columns - 1) / 2.0, (v.rows - 1) / 2.0])
        origin, direction = v.backproject(centre_px[None])
        o, d = np.asarray(origin).reshape(-1, 3)[0], np.asarray(direction).reshape(-1, 3)[0]
        d = d / np.linalg.norm(d)
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ o
    if len(views) == 1:
        a += 1e-3 * np.eye(3)  # regularise towards the origin along the single ray
    return np.linalg.solve(a, b)


class _LevelProblem:
    """The fixed images' gradients at one level, and the cost of a pose."""

    def __init__(self, shots: list[FluoroShot], volume: DrrVolume, level: Level, border_px: int) -> None:
        self.volume = volume
        self.step_mm = level.step_voxels * float(np.min(volume.spacing_mm))
        self.views: list[CArmView] = []
        self.fixed: list[tuple[NDArray[np.float32], NDArray[np.float32]]] = []
        self.valid: list[NDArray[np.bool_]] = []
        self.buffers: list[NDArray[np.float32]] = []
        self.images: list[NDArray[np.float32]] = []
        b = level.detector_bin
        for shot in shots:
            view = shot.view.binned(b)
            rows, cols = view.rows, view.columns
            img = shot.image_log[: rows * b, : cols * b].astype(np.float32)
            binned = img.reshape(rows, b, cols, b).mean(axis=(1, 3))
            excl = np.zeros((rows, cols), bool) if shot.exclude is None else shot.exclude[: rows * b, : cols * b].reshape(rows, b, cols, b).any(axis=(1, 3))
            excl = cv2.dilate(excl.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)  # the gradient's reach
            edge = max(2, border_px // b)
            excl[:edge] = excl[-edge:] = True
            excl[:, :edge] = excl[:, -edge:] = True
            valid = ~excl
            if valid.sum() < 50:
                raise DegenerateInput(f"fewer than 50 usable pixels at {rows}x{cols} once markers, tools and borders are excluded")
            gx, gy = _gradients(binned)
            self.views.append(view)
            self.fixed.append((_normalised(gx[valid]), _normalised(gy[valid])))
            self.valid.append(valid)
            self.images.append(binned)
            self.buffers.append(np.empty((rows, cols), np.float32))

    def similarity(self, carm_from_ct: NDArray[np.float64]) -> float:
        total = 0.0
        for view, (fx, fy), valid, buf in zip(self.views, self.fixed, self.valid, self.buffers):
            drr = render_drr(self.volume, view, carm_from_ct, out=buf, step_mm=self.step_mm)
            mx, my = _gradients(drr)
            total += 0.5 * (float(np.dot(fx, _normalised(mx[valid]))) + float(np.dot(fy, _normalised(my[valid]))))
        return total / len(self.views)


def _search_scale(level: Level, learnt: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """(6, 6) map from CMA-ES's isotropic search space to pose parameters.

    Diagonal (the level's sigmas) on the first level; afterwards the previous
    level's covariance, rescaled to this level's overall spread, so that
    correlated directions need not be learnt again.
    """
    d = np.array([np.radians(level.sigma_deg)] * 3 + [level.sigma_mm] * 3)
    if learnt is None:
        return np.diag(d)
    s = learnt / np.outer(d, d)
    s = 0.5 * (s + s.T)
    w, v = np.linalg.eigh(s)
    w = np.clip(w, w.max() * 1e-3, None)
    w /= np.exp(np.mean(np.log(w)))  # unit geometric mean: the level's sigmas set the size
    return np.diag(d) @ v @ np.diag(np.sqrt(w))


def _pose(x: NDArray[np.float64], centre: NDArray[np.float64], initial: NDArray[np.float64]) -> NDArray[np.float64]:
    """carm_from_ct for parameters x = (rotation vector rad (3), translation mm (3)) about ``centre``."""
    r = from_rotvec(x[:3])[:3, :3]
    delta = make_transform(r, centre - r @ centre + x[3:])
    return delta @ initial


def register_ct(
    ct: Volume | dict[int, DrrVolume],
    shots: list[FluoroShot],
    carm_from_ct_initial: NDArray[np.float64],
    *,
    levels: tuple[Level, ...] | None = None,
    seed: int = 0,
    border_px: int = 16,
    min_similarity: float = 0.5,
    search_mm: float | None = None,
) -> CtRegistration:
    """Register the CT to 1+ fluoroscopy shots, starting from ``carm_from_ct_initial`` (4, 4).

    ``ct`` is the HU volume or a ready pyramid {downsampling factor: DrrVolume}
    (build it once with :func:`drillnav.registration.drr.drr_pyramid` when
    registering repeatedly). ``levels`` defaults to :data:`SINGLE_VIEW_LEVELS`
    for one shot and :data:`DEFAULT_LEVELS` for more. ``converged`` requires the last level to stop on
    its tolerance (not its budget) with GC at least ``min_similarity``.
    ``search_mm`` first translates the CT by matching the views in DRRs
    widened by that much (:mod:`ct_prealign`), for starts that are off by
    more than CMA-ES's capture range (a few centimetres).
    """
    import cma  # ~2 s of matplotlib and scipy.stats on import: only when a CT is registered

    if not shots:
        raise DegenerateInput("CT registration needs at least one fluoroscopy view")
    t_start = time.perf_counter()
    if levels is None:
        levels = SINGLE_VIEW_LEVELS if len(shots) == 1 else DEFAULT_LEVELS
    pyramid = ct if isinstance(ct, dict) else {lv.volume_factor: DrrVolume.from_ct(ct, downsample=lv.volume_factor) for lv in levels}
    missing = sorted({lv.volume_factor for lv in levels} - set(pyramid))
    if missing:
        raise DegenerateInput(f"the DRR pyramid holds factors {sorted(pyramid)}, these levels also need {missing} (drr_pyramid(ct, {tuple(sorted({lv.volume_factor for lv in levels}))}))")
    centre = rotation_centre_mm([s.view for s in shots])
    current = np.asarray(carm_from_ct_initial, dtype=np.float64)
    outcomes: list[LevelOutcome] = []
    initial_similarity = float("nan")
    total_evals = 0
    stop = ""
    similarity = float("nan")
    shape: NDArray[np.float64] | None = None
    for n, level in enumerate(levels):
        t0 = time.perf_counter()
        problem = _LevelProblem(shots, pyramid[level.volume_factor], level, border_px)
        if n == 0:
            if search_mm:
                pre = prealign_translation(problem.volume, problem.views, problem.images, problem.valid, current, search_mm=search_mm)
                current = pre.carm_from_ct
            initial_similarity = problem.similarity(current)
        scale = _search_scale(level, shape)
        es = cma.CMAEvolutionStrategy(
            np.zeros(6), 1.0,
            {"popsize": level.popsize, "maxfevals": level.max_evaluations, "tolx": level.tol_x, "tolfun": 1e-5,
             "seed": int(seed) * 100 + n + 1, "verbose": -9},
        )
        base = current
        best_y, best_f = np.zeros(6), -problem.similarity(base)
        evals = 1
        while not es.stop():
            ys = es.ask()
            fs = [-problem.similarity(_pose(scale @ np.asarray(y), centre, base)) for y in ys]
            evals += len(ys)
            es.tell(ys, fs)
            i = int(np.argmin(fs))
            if fs[i] < best_f:
                best_f, best_y = fs[i], np.asarray(ys[i])
        # CMA-ES's mean is the better estimate once the spread is small; keep whichever scores higher.
        mean_y = np.asarray(es.mean)
        mean_f = -problem.similarity(_pose(scale @ mean_y, centre, base))
        evals += 1
        if mean_f <= best_f:
            best_y, best_f = mean_y, mean_f
        best_x = scale @ best_y
        # The next level starts with the correlations this level learnt (e.g. depth against rotation).
        shape = scale @ (es.sigma**2 * np.asarray(es.C)) @ scale.T
        current = _pose(best_x, centre, base)
        similarity = -best_f
        stop = ",".join(sorted(es.stop().keys()))
        total_evals += evals
        outcomes.append(LevelOutcome(level=level, similarity=similarity, evaluations=evals, stop=stop, seconds=time.perf_counter() - t0))
    converged = ("maxfevals" not in stop) and similarity >= min_similarity
    return CtRegistration(carm_from_ct=current, similarity=similarity, initial_similarity=initial_similarity, converged=converged,
                          evaluations=total_evals, runtime_s=time.perf_counter() - t_start, levels=tuple(outcomes))
