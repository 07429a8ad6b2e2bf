"""The drill camera calibration's uncertainty, as camera.json states it, for the joint solve's priors.

The joint solve holds the camera's focal scale, principal point and distortion coefficients by priors of the
calibration's size (``registration/joint_solve.py``), and the predicted error carries them. The defaults are a
typical calibration's actual error (and the twin's: ``drivers/sim/scene.py`` draws its calibrated camera at
exactly these sizes). A calibration may state its own (camera.json's ``intrinsics_sigma``, which ``drillnav
calibrate camera`` writes from OpenCV's standard deviations of the focal length and principal point); the priors
take the larger of the stated and the default for each term: OpenCV's figures are formal (the residuals' scatter
only) and understate what a board's flatness and the detector's bias add, so a calibration can widen the priors,
never narrow them. On the twin's 15 board views OpenCV states 0.019 % and 0.17 px against an actual error of
0.036 % and 0.12 px: the defaults (0.2 %, 0.8 px) hold; a calibration from a few poorly spread views states more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["IntrinsicsUncertainty", "DEFAULT_INTRINSICS_UNCERTAINTY", "camera_priors"]


@dataclass(frozen=True, kw_only=True)
class IntrinsicsUncertainty:
    """1-sigma uncertainty of a calibrated camera's intrinsics.

    focal_rel : relative, of fx and fy together (0.002 = 0.2 %).
    principal_px : of the principal point, per axis, px.
    distortion : (5,) of k1, k2, p1, p2, k3 (OpenCV's order); None: not stated. A calibration's own figures for
        these are no use as independent sigmas: k1, k2 and k3 trade off against each other (OpenCV's standard
        deviations of k2 and k3 run to 0.03 and 0.14 on the twin's 15 board views, whose combined effect within
        the image is a fraction of a pixel), so ``drillnav calibrate camera`` does not state them.
    """

    focal_rel: float
    principal_px: float
    distortion: tuple[float, float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.distortion is None:
            d: tuple[float, ...] = ()
        else:
            d = tuple(float(v) for v in self.distortion)
        if self.distortion is not None and len(d) != 5:
            raise ValueError(f"intrinsics uncertainty: distortion needs 5 sigmas (k1, k2, p1, p2, k3), got {len(d)}")
        for name, v in (("focal_rel", self.focal_rel), ("principal_px", self.principal_px), *((f"distortion[{i}]", x) for i, x in enumerate(d))):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"intrinsics uncertainty: {name} must be a finite number >= 0, got {v!r}")
        object.__setattr__(self, "distortion", d if self.distortion is not None else None)

    def at_least(self, other: IntrinsicsUncertainty) -> IntrinsicsUncertainty:
        """Each term the larger of this and ``other``'s (a term not stated here: ``other``'s)."""
        if self.distortion is None or other.distortion is None:
            distortion = other.distortion if self.distortion is None else self.distortion
        else:
            distortion = tuple(max(a, b) for a, b in zip(self.distortion, other.distortion))
        return IntrinsicsUncertainty(focal_rel=max(self.focal_rel, other.focal_rel), principal_px=max(self.principal_px, other.principal_px),
                                     distortion=distortion)


DEFAULT_INTRINSICS_UNCERTAINTY = IntrinsicsUncertainty(focal_rel=0.002, principal_px=0.8, distortion=(0.003, 0.004, 0.0002, 0.0002, 0.002))


def camera_priors(stated: IntrinsicsUncertainty | None) -> IntrinsicsUncertainty:
    """The joint solve's priors for a camera whose calibration states ``stated`` (None: the defaults)."""
    return DEFAULT_INTRINSICS_UNCERTAINTY if stated is None else stated.at_least(DEFAULT_INTRINSICS_UNCERTAINTY)
