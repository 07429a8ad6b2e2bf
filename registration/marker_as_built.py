"""A marker's BBs as built, measured in fluoroscopy views of it from several angles.

markers.json holds each marker's design; its BBs sit where manufacturing put them, a few hundredths of a millimetre
off. In one view, and on one or two markers in any view, a marker's orientation in the C-arm frame comes from its BB
pattern alone, so those hundredths tilt it by tenths of a degree, about a millimetre 290 mm down the drill axis
(``benchmarks/error_sources.py``). Shot from several angles while it lies still, each BB is seen along several rays
and its position in the marker can be measured.

The fit: the marker's pose in C (6) and each BB's offset from the design (3 per BB) by least squares over every
identified BB in every view (``fluoro_sigma_px``), the offsets held by a prior of the manufacturing tolerance
(``tolerance_mm``, 1 sigma per axis). X-ray does not see the paper tag, so the BBs' common rigid displacement
against it cannot be measured: the result is expressed in the frame that best fits the design (the rigid part left
at the design's). A BB seen in fewer than two views keeps what the prior says, and its stated uncertainty shows it.

Views with an image intensifier's uncorrected distortion (``CArmView.distortion_sigma_px`` > 0) are refused: the
fit would take the distortion for the BBs' offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .errors import DegenerateInput
from .horn import absolute_orientation
from .marker_pose import MarkerPose
from .markers import MarkerDesign

__all__ = ["AsBuiltMarker", "measure_as_built", "DEFAULT_TOLERANCE_MM"]

# The manufacturing tolerance of a BB's place (1 sigma per axis, mm) the offsets are held by: a pocket drilled to a
# tenth of a millimetre. The twin builds its markers at 0.05 mm.
DEFAULT_TOLERANCE_MM = 0.1


@dataclass(frozen=True, kw_only=True)
class AsBuiltMarker:
    """One marker's BBs as measured.

    bb_centers_mm : (n, 3) every BB of the design (in its order) as built, in the frame that best fits the design.
    sigma_mm : (n,) each BB's stated 1-sigma placement (RMS over the three axes): near ``tolerance_mm`` for a BB the
        views did not measure.
    views_per_bb : (n,) in how many views each BB was identified.
    moved_mm : (n,) each BB's distance from its design place.
    residual_px : RMS reprojection residual of the fit over every identified BB (a marker that moved between the
        shots, or a wrong correspondence, shows here).
    n_views : the views the marker was identified in.
    """

    marker_id: int
    bb_centers_mm: NDArray[np.float64]
    sigma_mm: NDArray[np.float64]
    views_per_bb: NDArray[np.int64]
    moved_mm: NDArray[np.float64]
    residual_px: float
    n_views: int


def measure_as_built(pose: MarkerPose, design: MarkerDesign, *, tolerance_mm: float = DEFAULT_TOLERANCE_MM,
                     fluoro_sigma_px: float = 0.35) -> AsBuiltMarker:
    """The BBs of ``design`` as built, from the observations of ``pose`` (:func:`.marker_pose.register_markers` over
    views of the marker from several angles; each observation (view, design BB centres (k, 3), detected centres (k, 2))).

    Raises :class:`.errors.DegenerateInput` with fewer than two views, or a view with uncorrected distortion.
    """
    if not (np.isfinite(tolerance_mm) and tolerance_mm > 0) or not (np.isfinite(fluoro_sigma_px) and fluoro_sigma_px > 0):
        raise ValueError(f"tolerance_mm and fluoro_sigma_px must be > 0, got {tolerance_mm}, {fluoro_sigma_px}")
    obs = [o for o in pose.observations if len(o[1])]
    if len(obs) < 2:
        raise DegenerateInput(f"marker {pose.marker_id}: identified in {len(obs)} view(s); measuring its BBs needs at least 2 from different angles")
    bad = [i for i, (view, _, _) in enumerate(obs) if view.distortion_sigma_px > 0]
    if bad:
        raise DegenerateInput(f"marker {pose.marker_id}: view(s) {bad} come from an image intensifier with uncorrected distortion, "
                              "which the fit would take for the BBs' offsets; dewarp them first")
    plan = np.asarray(design.bb_centers_mm, dtype=np.float64)                           # (n, 3)
    n = len(plan)
    rows, img, proj = [], [], []
    for view, model, centres in obs:
        model = np.asarray(model, dtype=np.float64).reshape(-1, 3)
        idx = np.argmin(np.linalg.norm(plan[None] - model[:, None], axis=2), axis=1)     # each observed BB's design row
        rows.append(idx)
        img.append(np.asarray(centres, dtype=np.float64).reshape(-1, 2))
        proj.append(np.repeat(view.projection_matrix[None], len(idx), axis=0))
    row, seen_px, p_mat = np.concatenate(rows), np.concatenate(img), np.concatenate(proj)
    views_per_bb = np.array([sum(int(np.any(r == k)) for r in rows) for k in range(n)], dtype=np.int64)
    r0, t0 = pose.carm_from_marker[:3, :3], pose.carm_from_marker[:3, 3]

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        rot = Rotation.from_rotvec(x[:3]).as_matrix()
        built = plan + x[6:].reshape(n, 3)
        pc = (built[row] @ r0.T) @ rot.T + t0 + x[3:6]                                # (N, 3) in C, turned about the marker's place
        h = np.einsum("nij,nj->ni", p_mat[:, :, :3], pc) + p_mat[:, :, 3]
        uv = h[:, :2] / h[:, 2:3]
        return np.concatenate([((uv - seen_px) / fluoro_sigma_px).ravel(), x[6:] / tolerance_mm])

    fit = least_squares(residuals, np.zeros(6 + 3 * n), method="trf", x_scale="jac", xtol=1e-10, ftol=1e-10)
    n_obs = 2 * len(row)
    res_obs = fit.fun[:n_obs]
    residual_px = float(np.sqrt(np.mean(res_obs**2))) * fluoro_sigma_px
    # The BBs' noise as their residuals show it (never below the stated one), for the stated uncertainty.
    scale = max(1.0, float(np.sqrt(np.sum(res_obs**2) / max(n_obs - 6, 1))))
    cov = np.linalg.pinv(fit.jac.T @ fit.jac) * scale**2
    built = plan + fit.x[6:].reshape(n, 3)
    # X-ray cannot see the BBs' common rigid displacement against the tag: expressed in the frame that fits the design.
    fit_t = absolute_orientation(built, plan).target_from_source
    aligned = built @ fit_t[:3, :3].T + fit_t[:3, 3]
    # The offsets' covariance less their rigid modes (the frame fitted to the design takes those out, to first order).
    rel = plan - plan.mean(axis=0)
    modes = np.zeros((3 * n, 6))
    for k in range(3):
        unit = np.zeros(3)
        unit[k] = 1.0
        modes[k::3, k] = 1.0                                                          # a translation along axis k
        modes[:, 3 + k] = np.cross(unit, rel).ravel()                                 # a small turn about axis k
    q, _ = np.linalg.qr(modes)
    keep = np.eye(3 * n) - q @ q.T
    var = np.diag(keep @ cov[6:, 6:] @ keep.T).reshape(n, 3)
    return AsBuiltMarker(marker_id=pose.marker_id, bb_centers_mm=aligned, sigma_mm=np.sqrt(var.mean(axis=1)), views_per_bb=views_per_bb,
                         moved_mm=np.linalg.norm(aligned - plan, axis=1), residual_px=residual_px, n_views=len(obs))
