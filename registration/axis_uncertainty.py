"""The drill axis's calibration uncertainty, as drill.json states it, for the predicted error.

drill.json's ``residual_mm`` is taken as the standard deviation of the calibrated axis's point along each axis
of frame D, and ``residual_deg`` as the RMS tilt of its direction (a 2-D quantity: ``residual_deg / sqrt(2)``
along each of the two directions that tilt it). A calibration that states neither (or 0: a calibration held
as an object, whose residuals are unknown) gets the defaults, those of the twin's and of a typical jig
calibration: 0.1 mm and 0.12 deg.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["AxisUncertainty", "DEFAULT_SIGMA_MM", "DEFAULT_RMS_TILT_DEG"]

DEFAULT_SIGMA_MM = 0.1
DEFAULT_RMS_TILT_DEG = 0.12


@dataclass(frozen=True, kw_only=True)
class AxisUncertainty:
    """sigma_mm: standard deviation of the axis's point per axis of frame D, mm; rms_tilt_deg: RMS tilt of its direction, deg."""

    sigma_mm: float = DEFAULT_SIGMA_MM
    rms_tilt_deg: float = DEFAULT_RMS_TILT_DEG

    def __post_init__(self) -> None:
        for name in ("sigma_mm", "rms_tilt_deg"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"the drill axis's calibration uncertainty: {name} must be a finite number >= 0, got {v!r}")

    @property
    def per_direction_deg(self) -> float:
        """The tilt's standard deviation along each of the two directions across the axis, deg."""
        return self.rms_tilt_deg / math.sqrt(2.0)

    @classmethod
    def from_residuals(cls, *, residual_mm: float | None, residual_deg: float | None) -> AxisUncertainty:
        """From drill.json's residuals; one that is absent or 0 (unknown) takes its default."""
        return cls(sigma_mm=residual_mm if residual_mm else DEFAULT_SIGMA_MM, rms_tilt_deg=residual_deg if residual_deg else DEFAULT_RMS_TILT_DEG)
