"""The drill pose's covariance from one frame's tag corners, the markers held fixed: what a tracked frame adds.

A live frame between joint solves is registered by corner PnP on markers the last solve refined
(:mod:`.pipeline`); its drill pose carries the solve's covariance (the markers' uncertainty) and, on top, the
noise of its own corners on the markers it sees. One tag alone fixes the drill's tilt only through perspective,
so a frame tracked on one marker is much less certain than the solve's frame on three.

The covariance is in the parametrisation :func:`.video_fluoro.predicted_axis_error` draws from: a rotation
vector (rad) applied in frame C about the pivot ``pivot_carm_mm``, then a translation (mm) in frame C.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .camera import PinholeCamera
from .joint_solve import N_FRAME_MODES, frame_shape_modes
from .transforms import invert

__all__ = ["corner_pnp_covariance"]

_STEP = (1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4)  # rad, rad, rad, mm, mm, mm


def _perturbed(carm_from_drill: NDArray[np.float64], delta: NDArray[np.float64], pivot_carm_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    r = Rotation.from_rotvec(delta[:3]).as_matrix()
    out = carm_from_drill.copy()
    out[:3, :3] = r @ carm_from_drill[:3, :3]
    out[:3, 3] = r @ (carm_from_drill[:3, 3] - pivot_carm_mm) + pivot_carm_mm + delta[3:]
    return out


def _project(carm_from_drill: NDArray[np.float64], points_carm_mm: NDArray[np.float64], camera: PinholeCamera) -> NDArray[np.float64]:
    drill_from_carm = invert(carm_from_drill)
    rvec, _ = cv2.Rodrigues(drill_from_carm[:3, :3])
    px, _ = cv2.projectPoints(points_carm_mm, rvec, drill_from_carm[:3, 3].reshape(3, 1), camera.camera_matrix, camera.distortion)
    return px.reshape(-1)


def corner_pnp_covariance(carm_from_drill: NDArray[np.float64], *, points_carm_mm: NDArray[np.float64], sigma_px: NDArray[np.float64],
                          camera: PinholeCamera, pivot_carm_mm: NDArray[np.float64], frame_shape_sigma_px: float = 0.0) -> NDArray[np.float64]:
    """(6, 6) covariance of ``carm_from_drill`` (4, 4) from its corner PnP, the points fixed.

    ``points_carm_mm`` (N, 3): the tag corners in frame C, four per tag in turn; ``sigma_px`` (N,): each corner's noise
    (1 sigma per image coordinate). Central differences of the projections give the Jacobian (2N, 6); the covariance
    is the inverse of its weighted normal matrix (a pseudo-inverse where the corners leave a direction free).
    ``frame_shape_sigma_px``: the shape modes every tag of the frame shares (:data:`.joint_solve.FRAME_CORNER_PER_EDGE_SIGMA`),
    carried as the joint solve carries them: what a draw of them at this size does to the PnP's pose.
    """
    points = np.ascontiguousarray(points_carm_mm, dtype=np.float64).reshape(-1, 3)
    sigma = np.repeat(np.asarray(sigma_px, dtype=np.float64).reshape(-1), 2)
    if points.shape[0] * 2 != sigma.size:
        raise ValueError(f"{points.shape[0]} points but {sigma.size // 2} corner sigmas")
    jac = np.empty((points.shape[0] * 2, 6))
    for k, h in enumerate(_STEP):
        step = np.zeros(6)
        step[k] = h
        jac[:, k] = (_project(_perturbed(carm_from_drill, step, pivot_carm_mm), points, camera)
                     - _project(_perturbed(carm_from_drill, -step, pivot_carm_mm), points, camera)) / (2 * h)
    weighted = jac / sigma[:, None]
    cov = np.linalg.pinv(weighted.T @ weighted)
    if frame_shape_sigma_px > 0:
        if points.shape[0] % 4:
            raise ValueError(f"the frame's shared tag shape needs each tag's four corners in turn, got {points.shape[0]} points")
        at = _project(carm_from_drill, points, camera).reshape(-1, 4, 2)
        modes = frame_shape_modes(list(at)).reshape(-1, N_FRAME_MODES) / sigma[:, None]
        sens = cov @ (weighted.T @ modes)
        cov = cov + float(frame_shape_sigma_px) ** 2 * (sens @ sens.T)
    return cov
