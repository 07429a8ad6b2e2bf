"""The C-arm as a projective camera: ``P = K [R | t]``.

Frame C (C-arm): origin at the isocentre, axes of the patient (DICOM LPS: +x to
the patient's left, +y posterior, +z superior). Every view of one C-arm session
shares this frame, so markers registered in several views are in one frame.

Frame S (x-ray source) of one view: origin at the focal spot, +z along the
central ray towards the detector, +x along detector columns, +y along rows.
``source_from_carm = [R | t]`` and ``K = [[f/ps_col, 0, u0], [0, f/ps_row, v0], [0, 0, 1]]``
with ``f`` the source-to-detector distance. Pixels are (column, row), (0, 0) at
the centre of the first pixel. ``docs/geometry.md`` derives ``R`` from the DICOM
positioner angles; a calibrated 3x4 matrix per image overrides them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from .errors import DegenerateInput
from .transforms import check_points, invert, make_transform

__all__ = [
    "CArmView",
    "IMAGE_INTENSIFIER_DISTORTION_PX",
    "REFERENCE_PIXEL_MM",
    "intensifier_distortion_sigma_px",
    "intensifier_shift_px",
    "positioner_rotation",
    "triangulate",
]


def positioner_rotation(primary_deg: float, secondary_deg: float) -> NDArray[np.float64]:
    """Rotation (3, 3) whose rows are the source-frame axes (column, row, beam) in frame C.

    ``primary_deg`` is the DICOM Positioner Primary Angle (LAO +, RAO -) and
    ``secondary_deg`` the Positioner Secondary Angle (CRA +, CAU -), both giving
    the direction from the isocentre to the detector. At (0, 0) the detector is
    anterior, the beam runs posterior to anterior (-y), columns run to the
    patient's right (-x) and rows run to the feet (-z): the image as seen from
    the source, head up.
    """
    a, b = np.radians(primary_deg), np.radians(secondary_deg)
    if not (-180.0 <= primary_deg <= 180.0) or not (-90.0 <= secondary_deg <= 90.0):
        raise ValueError(
            f"positioner angles out of range: primary {primary_deg} (must be -180..180), "
            f"secondary {secondary_deg} (must be -90..90)"
        )
    beam = np.array([np.sin(a) * np.cos(b), -np.cos(a) * np.cos(b), np.sin(b)])
    # Columns: the AP column direction (-x) turned with the primary angle; it stays
    # in the transaxial plane, so it is orthogonal to the beam for any secondary angle.
    col = np.array([-np.cos(a), -np.sin(a), 0.0])
    row = np.cross(beam, col)
    return np.stack([col, row, beam])


# An image intensifier's electron optics bend the image: pincushion (radial, growing with r^3) and S distortion
# (the earth's and the room's magnetic field twisting it, tangential, changing with the C-arm's orientation). An
# uncorrected 9-inch intensifier moves a point at the field's edge by a few mm, 1-2 % of the radius; 10 px
# (3 mm at 0.3 mm/px) at the field's corner is the 1-sigma size assumed for each of the two terms when a view
# comes from an intensifier without a dewarp calibration. A flat panel (and a dewarped image) has none.
IMAGE_INTENSIFIER_DISTORTION_PX = 10.0
# The reference's detector pixel (mm): the fluoroscopy side's sizes in pixels (the marker detector's kernels, a
# claim's search and tolerance, the intensifier's prior) are stated in it and converted by a view's own spacing.
REFERENCE_PIXEL_MM = 0.304


def intensifier_distortion_sigma_px(pixel_spacing_mm: float) -> float:
    """:data:`IMAGE_INTENSIFIER_DISTORTION_PX` (a size in mm at the detector) in pixels of ``pixel_spacing_mm``:
    10 px at 0.304 mm, 5 px on the same intensifier read out binned 2 x 2."""
    p = float(pixel_spacing_mm)
    if not (np.isfinite(p) and p > 0):
        raise ValueError(f"pixel spacing must be a positive number of mm, got {pixel_spacing_mm}")
    return IMAGE_INTENSIFIER_DISTORTION_PX * REFERENCE_PIXEL_MM / p


def intensifier_shift_px(uv_px: NDArray[np.float64], center_px: NDArray[np.float64], corner_radius_px: float,
                         coefficients_px: NDArray[np.float64]) -> NDArray[np.float64]:
    """Where an image intensifier moves ideal pixels (..., 2): the shift (..., 2), px.

    coefficients_px : (..., 2) pincushion (radial) and S (tangential) shifts at ``corner_radius_px`` from
        ``center_px``; both grow with the cube of the radius, the leading terms of an intensifier's distortion.
    """
    d = uv_px - center_px
    r2 = np.sum(d * d, axis=-1, keepdims=True) / corner_radius_px**3
    perp = np.stack([-d[..., 1], d[..., 0]], axis=-1)
    return (coefficients_px[..., :1] * d + coefficients_px[..., 1:2] * perp) * r2


@dataclass(frozen=True, kw_only=True)
class CArmView:
    """One fluoroscopy view: its projection matrix and detector size.

    Parameters
    ----------
    projection_matrix : array, shape (3, 4)
        Maps homogeneous points in frame C (mm) to homogeneous pixels (column, row).
    rows, columns : int
        Detector size in pixels.
    pixel_spacing_mm : tuple of float
        (row spacing, column spacing) at the detector, mm (DICOM Imager Pixel Spacing order).
    distortion_sigma_px : float
        1-sigma size, in pixels at the field's corner, of the detector's uncorrected distortion
        (:func:`intensifier_shift_px`): 0 for a flat panel or a dewarped image (the projection is exact);
        :data:`IMAGE_INTENSIFIER_DISTORTION_PX` for an image intensifier without a dewarp calibration.
        The joint solve then estimates each such view's distortion, held by a prior of this size.
    """

    projection_matrix: NDArray[np.float64]
    rows: int
    columns: int
    pixel_spacing_mm: tuple[float, float]
    distortion_sigma_px: float = 0.0

    def __post_init__(self) -> None:
        # A copy no caller holds, read-only: the view's decomposition is computed once and kept.
        p = np.array(self.projection_matrix, dtype=np.float64)
        p.setflags(write=False)
        if p.shape != (3, 4) or not np.all(np.isfinite(p)):
            raise ValueError(f"projection_matrix must be a finite 3x4 matrix, got shape {p.shape}")
        if abs(np.linalg.det(p[:, :3])) < 1e-12:
            raise ValueError("projection_matrix has a singular left 3x3 block (no finite source)")
        if self.rows <= 0 or self.columns <= 0:
            raise ValueError(f"detector size must be positive, got {self.rows}x{self.columns}")
        ps = tuple(float(v) for v in self.pixel_spacing_mm)
        if len(ps) != 2 or min(ps) <= 0:
            raise ValueError(f"pixel_spacing_mm must be two positive numbers, got {self.pixel_spacing_mm}")
        if not (np.isfinite(self.distortion_sigma_px) and self.distortion_sigma_px >= 0):
            raise ValueError(f"distortion_sigma_px must be a finite number >= 0, got {self.distortion_sigma_px}")
        object.__setattr__(self, "projection_matrix", p)
        object.__setattr__(self, "pixel_spacing_mm", ps)

    @classmethod
    def from_positioner(
        cls,
        *,
        primary_deg: float,
        secondary_deg: float,
        source_to_detector_mm: float,
        source_to_isocenter_mm: float,
        pixel_spacing_mm: tuple[float, float],
        rows: int,
        columns: int,
        principal_point_px: tuple[float, float] | None = None,
        distortion_sigma_px: float = 0.0,
    ) -> "CArmView":
        """View from DICOM positioner attributes (PS3.3 C.8.7.5).

        ``source_to_isocenter_mm`` is Distance Source to Patient (0018,1111),
        ``source_to_detector_mm`` Distance Source to Detector (0018,1110),
        ``pixel_spacing_mm`` Imager Pixel Spacing (0018,1164) as (row, column).
        The principal point defaults to the detector centre.
        """
        sdd, sad = float(source_to_detector_mm), float(source_to_isocenter_mm)
        if not (0 < sad < sdd):
            raise ValueError(
                f"need 0 < source-to-isocenter ({sad} mm) < source-to-detector ({sdd} mm)"
            )
        r = positioner_rotation(primary_deg, secondary_deg)
        source_carm = -sad * r[2]
        t = -r @ source_carm
        ps_row, ps_col = float(pixel_spacing_mm[0]), float(pixel_spacing_mm[1])
        if principal_point_px is None:
            principal_point_px = ((columns - 1) / 2.0, (rows - 1) / 2.0)
        k = np.array([[sdd / ps_col, 0.0, principal_point_px[0]], [0.0, sdd / ps_row, principal_point_px[1]], [0.0, 0.0, 1.0]])
        p = k @ np.hstack([r, t[:, None]])
        return cls(projection_matrix=p, rows=rows, columns=columns, pixel_spacing_mm=(ps_row, ps_col), distortion_sigma_px=distortion_sigma_px)

    def binned(self, factor: int) -> "CArmView":
        """The same view on a detector binned ``factor`` x ``factor`` (multi-resolution).

        A binned pixel's centre is the mean of the centres of the pixels it covers.
        """
        f = int(factor)
        if f < 1:
            raise ValueError(f"binning factor must be a positive integer, got {factor}")
        off = (1.0 / f - 1.0) / 2.0
        s = np.array([[1.0 / f, 0.0, off], [0.0, 1.0 / f, off], [0.0, 0.0, 1.0]])
        return CArmView(
            projection_matrix=s @ self.projection_matrix,
            rows=self.rows // f,
            columns=self.columns // f,
            pixel_spacing_mm=(self.pixel_spacing_mm[0] * f, self.pixel_spacing_mm[1] * f),
            distortion_sigma_px=self.distortion_sigma_px / f,
        )

    # -- decomposition -----------------------------------------------------------------
    def decompose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Split into (K (3, 3) with K[2, 2] = 1 and positive diagonal, source_from_carm (4, 4)): copies the caller
        may change."""
        k, source_from_carm = self._decomposition
        return k.copy(), source_from_carm.copy()

    @cached_property
    def _decomposition(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:meth:`decompose`'s (K, source_from_carm), computed once (read-only): a view's magnification and depths
        are asked for at every rendered pose of a marker's shadow."""
        p = self.projection_matrix
        m = p[:, :3]
        # RQ decomposition via QR of the flipped transpose.
        flip = np.flipud(np.eye(3))
        q, r = np.linalg.qr((flip @ m).T)
        k = flip @ r.T @ flip
        rot = flip @ q.T
        signs = np.diag(np.sign(np.diag(k)))
        k, rot = k @ signs, signs @ rot
        scale = k[2, 2]
        k = k / scale
        t = np.linalg.solve(k, p[:, 3] / scale)
        if np.linalg.det(rot) < 0:
            # A mirrored detector: flip the source frame's x (F = diag(-1, 1, 1)) so R is proper, and put the
            # flip into K's first column, as K F F R = K R. The depth row is untouched, so depths stay positive.
            flip = np.diag([-1.0, 1.0, 1.0])
            rot, t, k = flip @ rot, flip @ t, k @ flip
        source_from_carm = make_transform(rot, t)
        k.setflags(write=False)
        source_from_carm.setflags(write=False)
        return k, source_from_carm

    @property
    def source_position_mm(self) -> NDArray[np.float64]:
        """Focal spot (3,) in frame C: the null vector of P."""
        m = self.projection_matrix[:, :3]
        return -np.linalg.solve(m, self.projection_matrix[:, 3])

    @property
    def carm_from_source(self) -> NDArray[np.float64]:
        return invert(self.decompose()[1])

    @property
    def source_to_detector_mm(self) -> float:
        k, _ = self._decomposition
        return float(k[0, 0] * self.pixel_spacing_mm[1])

    # -- projection ----------------------------------------------------------------------
    @property
    def center_px(self) -> NDArray[np.float64]:
        """(2,) the detector's centre (column, row), about which an intensifier distorts."""
        return np.array([(self.columns - 1) / 2.0, (self.rows - 1) / 2.0])

    @property
    def corner_radius_px(self) -> float:
        """Distance from the detector's centre to its corner pixel, px."""
        return float(np.hypot((self.columns - 1) / 2.0, (self.rows - 1) / 2.0))

    def distorted_px(self, uv_px: ArrayLike, coefficients_px: ArrayLike | None) -> NDArray[np.float64]:
        """Ideal pixels (N, 2) where an image intensifier with distortion ``coefficients_px`` (2,: pincushion and S
        shift at the field's corner, px; :func:`intensifier_shift_px`) shows them; as given for None (a flat panel)."""
        uv = np.asarray(uv_px, dtype=np.float64)
        if coefficients_px is None:
            return uv
        return uv + intensifier_shift_px(uv, self.center_px, self.corner_radius_px, np.asarray(coefficients_px, dtype=np.float64))

    def project(self, points_carm_mm: ArrayLike) -> NDArray[np.float64]:
        """Project points (N, 3) in frame C, mm, to pixels (N, 2) (column, row)."""
        p = check_points(points_carm_mm)
        h = p @ self.projection_matrix[:, :3].T + self.projection_matrix[:, 3]
        return h[:, :2] / h[:, 2:3]

    def depth_mm(self, points_carm_mm: ArrayLike) -> NDArray[np.float64]:
        """Distance (N,) of points from the source along the central ray, mm."""
        _, source_from_carm = self._decomposition
        p = check_points(points_carm_mm)
        return p @ source_from_carm[2, :3] + source_from_carm[2, 3]

    def magnification(self, points_carm_mm: ArrayLike) -> NDArray[np.float64]:
        """Geometric magnification (N,) of objects at the given points: SDD / depth."""
        return self.source_to_detector_mm / self.depth_mm(points_carm_mm)

    def backproject(self, pixels: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Rays through pixels (N, 2): (source (3,) in frame C, unit directions (N, 3) in frame C)."""
        px = check_points(pixels, dim=2)
        m = self.projection_matrix[:, :3]
        h = np.concatenate([px, np.ones((px.shape[0], 1))], axis=1)
        d = np.linalg.solve(m, h.T).T
        # Orient towards the detector: positive depth.
        _, source_from_carm = self._decomposition
        sign = np.sign(d @ source_from_carm[2, :3])
        d = d * sign[:, None]
        return self.source_position_mm, d / np.linalg.norm(d, axis=1, keepdims=True)

    def contains(self, pixels: ArrayLike, *, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """Whether pixels (N, 2) lie on the detector, at least ``margin_px`` from its edge."""
        px = check_points(pixels, dim=2)
        return (
            (px[:, 0] >= margin_px) & (px[:, 0] <= self.columns - 1 - margin_px)
            & (px[:, 1] >= margin_px) & (px[:, 1] <= self.rows - 1 - margin_px)
        )


def triangulate(views: list[CArmView], pixels: ArrayLike, *, refine: bool = True) -> NDArray[np.float64]:
    """Point (3,) in frame C seen at ``pixels[i]`` (column, row) in ``views[i]``.

    Linear (DLT) solution refined by minimising reprojection error in pixels.
    Needs at least two views whose rays are not parallel.
    """
    px = check_points(pixels, dim=2)
    if len(views) != px.shape[0] or len(views) < 2:
        raise DegenerateInput(f"triangulation needs one pixel per view and at least 2 views, got {len(views)} views, {px.shape[0]} pixels")
    rows = []
    for view, (u, v) in zip(views, px):
        p = view.projection_matrix / np.linalg.norm(view.projection_matrix[2, :3])
        rows.append(u * p[2] - p[0])
        rows.append(v * p[2] - p[1])
    a = np.asarray(rows)
    _, s, vt = np.linalg.svd(a)
    if s[-2] < 1e-9 * s[0]:
        raise DegenerateInput("triangulation is degenerate: the rays are parallel")
    x = vt[-1]
    x = x[:3] / x[3]
    if not refine:
        return x

    def residual(point: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.concatenate([view.project(point)[0] - uv for view, uv in zip(views, px)])

    return least_squares(residual, x, method="lm").x
