"""How far an edge-on marker is turned about its own line: its whole shadow matched in the image.

Edge-on, a marker's ring is a stroke. Turned about the stroke's own line (its roll), the ring opens into a thin
ellipse and its BBs move across the line, each by its distance along the beam: the ring's near and far sides, 24 mm
from its centre, move 0.4 mm each way per degree. A face-on view hardly shows that turn (it is second order there),
the stroke's position across its line (:mod:`.edge_on_ring`) does not, and two markers the camera sees along one line
leave their constellation free to turn about it: flat markers in an AP+lateral pair, where the lateral view sees
every marker edge-on, came out turned 1-4 deg about that line (the axis 3-10 mm off at the entry).

The marker's shadow (:func:`.kcr.render_marker_drr`, blurred as the detector blurs) is rendered at the pose turned
about its line through the ring's centre by each of a range of angles and matched with the image by normalised
correlation over shifts of a few pixels both ways; the best angle, refined by a parabola, is the roll. The BBs, off
the line by different amounts, tell a turn one way from the same turn the other way, which the ring alone cannot.
The measurement is where the ring's near and far sides lie apart across the line at the turned pose, a difference of
two points of one marker, so it says nothing of where the marker lies.

Pure math: numpy and OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .carm import CArmView
from .edge_on_ring import EDGE_ON_STROKE_RATIO
from .kcr import render_marker_drr
from .markers import MarkerDesign
from .transforms import apply, make_transform

__all__ = ["RingRoll", "measure_ring_roll", "rolled_about", "ROLL_SIGMA_DEG"]

# How far either way the roll is looked for (deg), in steps of ROLL_STEP_DEG refined by a parabola.
ROLL_REACH_DEG = 10.0
ROLL_STEP_DEG = 0.5
# How far the shadow is slid both ways in the image (px) at each angle: the solve's pose places the marker within a
# few millimetres, though a marker held in a lateral view by BBs claimed along a wrong line (no stroke taken there) lay
# 3 mm (21 px) across it (seed 12000 flat, second pose).
SHIFT_PX = 30
# The rendered shadow is blurred by this (px, 1 sigma) before it is matched: the focal spot and the detector.
BLUR_PX = 1.0
# The rendered window's margin around the ring's image (px).
MARGIN_PX = 6
# Below this normalised correlation at its best angle, the image does not show the marker's shadow plainly enough (a
# neighbour's over it, bone or metal): of 107 rolls measured in the flat-marker twin's lateral views from the joint
# solve's poses, 8 of the 14 at 0.3-0.4 were over 1 deg off the truth, 2 of the 7 at 0.40-0.45 (with no rival peak),
# 3 of the 83 at 0.45 or more (two of them where the turn the other way matched about as well). The roll is not
# measured.
MIN_CORRELATION = 0.45
# The roll's noise (deg, 1 sigma): those 107 rolls, less the 15 over 0.5 deg off (the turn the other way matched, or
# a weak match), were off by 0.13 deg RMS (0.21 deg at the 90th percentile); stated larger for what the twin does not
# draw.
ROLL_SIGMA_DEG = 0.3


@dataclass(frozen=True, kw_only=True)
class RingRoll:
    """An edge-on marker's roll about its line in one view, as the image shows it.

    near_mm, far_mm : (3,) the ring's two points, in the marker frame, that lie apart along the beam (both image to
        the middle of the stroke).
    normal : (2,) the unit image direction across the stroke.
    apart_px : ``normal @ (uv(near) - uv(far))`` at the pose the image matches best.
    sigma_px : its noise (``ROLL_SIGMA_DEG`` through the ring's opening per degree there).
    roll_deg : how far that pose is turned from the given one, about the marker's in-plane axis ``axis_mm`` (3,).
    correlation : the normalised correlation of shadow and image at the best angle; ``runner_up`` at the best other
        peak more than two steps away (0 where there is none), ``runner_up_apart_px`` the separation at its angle
        (refined alike; NaN where there is none), ``runner_up_deg`` its turn from the given pose (NaN where there is
        none): nearly edge-on, the same turn the other way can match about as well.
    slide_px : how far across the line the shadow at the best angle lay from where the given pose puts it (px).
    """

    near_mm: NDArray[np.float64]
    far_mm: NDArray[np.float64]
    normal: NDArray[np.float64]
    apart_px: float
    sigma_px: float
    roll_deg: float
    axis_mm: NDArray[np.float64]
    correlation: float
    runner_up: float
    runner_up_apart_px: float
    runner_up_deg: float
    slide_px: float


def rolled_about(carm_from_marker: NDArray[np.float64], axis_mm: NDArray[np.float64], centre_mm: NDArray[np.float64], deg: float) -> NDArray[np.float64]:
    """``carm_from_marker`` (4, 4) turned by ``deg`` about the marker-frame axis ``axis_mm`` (3,) through ``centre_mm`` (3,)."""
    rot = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis_mm, dtype=np.float64)).as_matrix()
    c = np.asarray(centre_mm, dtype=np.float64)
    return carm_from_marker @ make_transform(rot, c - rot @ c)


def measure_ring_roll(image_log: NDArray[np.floating], view: CArmView, carm_from_marker: NDArray[np.float64], design: MarkerDesign, *,
                      min_correlation: float = MIN_CORRELATION) -> RingRoll | None:
    """The roll of ``design``'s marker about its ring's line where ``carm_from_marker`` (4, 4) puts it edge-on in
    ``view`` (its ring's image under :data:`.edge_on_ring.EDGE_ON_STROKE_RATIO` as wide as long), as ``image_log``
    (H, W; log attenuation, bright where dense) shows it; None where the ring is not edge-on, its window with the
    shifts leaves the image, the match is weaker than ``min_correlation``, or its best angle or slide is at the
    search's end (seed 14000's random pair on the default twin: a shadow matched 30 px aside, 8 deg off)."""
    ring_mm = design.ring_points_mm(256)
    centre_mm = np.asarray(design.ring_center_mm, dtype=np.float64)
    ring_px = view.project(apply(carm_from_marker, ring_mm))
    centre = ring_px.mean(axis=0)
    _, sv, vt = np.linalg.svd(ring_px - centre, full_matrices=False)
    if not sv[0] > 0 or sv[1] > EDGE_ON_STROKE_RATIO * sv[0]:
        return None
    along = vt[0] if vt[0][np.argmax(np.abs(vt[0]))] > 0 else -vt[0]  # one sense for poses near each other
    normal = np.array([-along[1], along[0]])
    reach = (ring_px - centre) @ along
    axis = ring_mm[int(np.argmax(reach))] - ring_mm[int(np.argmin(reach))]
    axis /= np.linalg.norm(axis)
    side = np.cross(np.asarray(design.ring_normal, dtype=np.float64), axis)
    side /= np.linalg.norm(side)
    near, far = centre_mm + design.ring_radius_mm * side, centre_mm - design.ring_radius_mm * side
    image = np.ascontiguousarray(image_log, dtype=np.float32)
    rows, cols = image.shape
    angles = np.arange(-ROLL_REACH_DEG, ROLL_REACH_DEG + 1e-9, ROLL_STEP_DEG)
    scores = np.full(len(angles), -np.inf)
    slides = np.zeros((len(angles), 2))
    for k, deg in enumerate(angles):
        pose = rolled_about(carm_from_marker, axis, centre_mm, float(deg))
        px = view.project(apply(pose, ring_mm))
        c0, r0 = np.floor(px.min(axis=0)).astype(int) - MARGIN_PX
        c1, r1 = np.ceil(px.max(axis=0)).astype(int) + MARGIN_PX
        if c0 - SHIFT_PX < 0 or r0 - SHIFT_PX < 0 or c1 + SHIFT_PX > cols or r1 + SHIFT_PX > rows:
            return None
        shadow = cv2.GaussianBlur(render_marker_drr(design, pose, view, (int(c0), int(r0), int(c1), int(r1))), (0, 0), BLUR_PX)
        window = image[r0 - SHIFT_PX : r1 + SHIFT_PX, c0 - SHIFT_PX : c1 + SHIFT_PX]
        _, scores[k], _, at = cv2.minMaxLoc(cv2.matchTemplate(window, shadow, cv2.TM_CCOEFF_NORMED))
        slides[k] = (at[0] - SHIFT_PX, at[1] - SHIFT_PX)
    k = int(np.argmax(scores))
    best = float(scores[k])
    if best < min_correlation or k in (0, len(angles) - 1) or np.max(np.abs(slides[k])) >= SHIFT_PX:
        return None  # no peak inside the search: the turn or the slide

    def refined(j: int) -> float:
        a, b, c = scores[j - 1], scores[j], scores[j + 1]
        frac = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) < 0 else 0.0
        return float(angles[j] + np.clip(frac, -0.5, 0.5) * ROLL_STEP_DEG)

    roll = refined(k)
    peaks = [j for j in range(1, len(angles) - 1) if scores[j] >= scores[j - 1] and scores[j] >= scores[j + 1] and abs(j - k) > 2]
    second = max(peaks, key=lambda j: scores[j]) if peaks else None
    runner_up = float(scores[second]) if second is not None else 0.0

    def apart(deg: float) -> float:
        uv = view.project(apply(rolled_about(carm_from_marker, axis, centre_mm, deg), np.stack([near, far])))
        return float(normal @ (uv[0] - uv[1]))

    slope = (apart(roll + 0.05) - apart(roll - 0.05)) / 0.1  # px per degree
    return RingRoll(near_mm=near, far_mm=far, normal=normal, apart_px=apart(roll), sigma_px=abs(slope) * ROLL_SIGMA_DEG, roll_deg=roll, axis_mm=axis,
                    correlation=best, runner_up=runner_up, runner_up_apart_px=apart(refined(second)) if second is not None else float("nan"),
                    runner_up_deg=refined(second) if second is not None else float("nan"),
                    slide_px=float(abs(normal @ slides[k])))
