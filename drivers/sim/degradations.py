"""What an operating room does to the twin's images and scene, each a named switch (issue 17, part 4).

The twin's default scene is clean enough to make a study look good; the
product will be judged on scenes it has never seen. Each switch here adds
one thing an operating room does, at a size seen in practice:

placement
    ``surgeon_markers``: markers where a surgeon sticks them, on the anterior
    skin about the incision, spread unevenly 40-95 mm out, tilted 10-40 deg from
    the AP beam with the skin (so edge-on in a lateral view, and some rings
    partly outside the fluoroscopy field).
fluoroscopy
    ``low_dose`` (2,000-5,000 quanta per pixel, Poisson), ``ct_anatomy`` (the
    real chest/abdomen CT as the patient instead of the analytic pelvis; the
    caller loads it, see ``benchmarks/accuracy.py``), ``hardware`` (two retractor
    blades, a second K-wire and a clamp, dense metal in 3D projected by the same
    X-ray model), ``collimator`` (lead shutters and iris cutting the field),
    ``ii_distortion`` (image-intensifier pincushion and S distortion).
camera
    ``motion_blur`` (a line kernel: the drill moving during the exposure),
    ``defocus`` (a disc kernel), ``tag_glare`` (a saturated specular highlight
    on a glossy tag), ``glove`` (a glove-coloured polygon over one tag's
    corner), ``blood`` (dark red specks on tags and drape), ``mjpeg`` (JPEG at
    quality 50-70, as a USB camera streams), ``colour`` (BGR frames under a warm
    OR light), ``auto_exposure`` (a step of the camera's gain).

Every function draws from the generator it is handed, so a scene stays
deterministic per seed; a switch that is off draws nothing, so the default
twin renders exactly as it did before these switches existed.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "Degradations", "PLACEMENT", "XRAY", "CAMERA", "Hardware", "Cylinder", "Box",
    "collimator_mask", "ii_distortion_maps", "make_hardware", "degrade_camera_frame",
    "GLOVE_BGR", "BLOOD_BGR", "WARM_LIGHT_BGR", "LEAD_LINE_INTEGRAL",
]

PLACEMENT = ("surgeon_markers",)
XRAY = ("low_dose", "ct_anatomy", "hardware", "collimator", "ii_distortion")
CAMERA = ("motion_blur", "defocus", "tag_glare", "glove", "blood", "mjpeg", "colour", "auto_exposure")

# A latex/nitrile glove under OR light, blood, and the warm light's gain per channel (B, G, R).
GLOVE_BGR = (150.0, 185.0, 215.0)
BLOOD_BGR = (25.0, 20.0, 105.0)
WARM_LIGHT_BGR = (0.82, 0.97, 1.12)
# Collimator lead: leaves 0.1 % of the primary (a few mm of lead at fluoroscopy energies leaves less).
LEAD_LINE_INTEGRAL = 7.0


class DegradationError(ValueError):
    """An unknown degradation name or an impossible magnitude."""


@dataclass(frozen=True, kw_only=True)
class Degradations:
    """One switch per degradation (all off: the clean default twin) and the magnitudes they use."""

    surgeon_markers: bool = False
    low_dose: bool = False
    ct_anatomy: bool = False
    hardware: bool = False
    collimator: bool = False
    ii_distortion: bool = False
    motion_blur: bool = False
    defocus: bool = False
    tag_glare: bool = False
    glove: bool = False
    blood: bool = False
    mjpeg: bool = False
    colour: bool = False
    auto_exposure: bool = False
    # Magnitudes (each drawn uniformly per shot or frame from its range).
    marker_tilt_deg: tuple[float, float] = (10.0, 40.0)
    marker_radius_mm: tuple[float, float] = (40.0, 95.0)
    dose_quanta: tuple[float, float] = (2000.0, 5000.0)
    jpeg_quality: tuple[int, int] = (50, 70)
    motion_blur_px: tuple[float, float] = (4.0, 12.0)
    defocus_px: tuple[float, float] = (1.5, 3.0)
    exposure_gain: tuple[float, float] = (0.6, 1.6)
    ii_pincushion_px: float = 8.0   # outward shift at the field's corner
    ii_s_px: float = 3.0            # tangential shift at the field's edge

    def __post_init__(self) -> None:
        lo, hi = self.dose_quanta
        if not 0 < lo <= hi:
            raise DegradationError(f"dose_quanta must be 0 < low <= high, got {self.dose_quanta}")
        lo, hi = self.marker_tilt_deg
        if not 0 <= lo <= hi < 80:
            raise DegradationError(f"marker_tilt_deg must be 0 <= low <= high < 80, got {self.marker_tilt_deg}")
        lo, hi = self.jpeg_quality
        if not 1 <= lo <= hi <= 100:
            raise DegradationError(f"jpeg_quality must be 1 <= low <= high <= 100, got {self.jpeg_quality}")

    @staticmethod
    def names() -> tuple[str, ...]:
        return PLACEMENT + XRAY + CAMERA

    @classmethod
    def parse(cls, text: str) -> "Degradations":
        """'all', 'none' or 'name,name' (see :meth:`names`)."""
        text = text.strip()
        if text == "all":
            return cls(**{n: True for n in cls.names()})
        if text in ("none", ""):
            return cls()
        chosen = [t.strip() for t in text.split(",") if t.strip()]
        unknown = [n for n in chosen if n not in cls.names()]
        if unknown:
            raise DegradationError(f"unknown degradation(s) {', '.join(unknown)}: use all, none or any of {', '.join(cls.names())}")
        return cls(**{n: True for n in chosen})

    def only(self, name: str) -> "Degradations":
        """These magnitudes with ``name`` the only switch on."""
        if name not in self.names():
            raise DegradationError(f"unknown degradation '{name}'")
        return dataclasses.replace(self, **{n: n == name for n in self.names()})

    @property
    def enabled(self) -> tuple[str, ...]:
        return tuple(n for n in self.names() if getattr(self, n))

    @property
    def camera(self) -> bool:
        return any(getattr(self, n) for n in CAMERA)

    def label(self) -> str:
        on = self.enabled
        return "none" if not on else "all" if len(on) == len(self.names()) else ",".join(on)


# --- fluoroscopy ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class Cylinder:
    """A solid steel rod in frame C (a K-wire, a clamp's jaw)."""

    start_mm: tuple[float, float, float]
    end_mm: tuple[float, float, float]
    radius_mm: float
    name: str


@dataclass(frozen=True, kw_only=True)
class Box:
    """A solid steel box in frame C (a retractor blade, a clamp's hinge): centre, axes as columns, half sizes."""

    centre_mm: tuple[float, float, float]
    axes: tuple[tuple[float, float, float], ...]  # (3, 3): carm_from_box rotation, columns = box x, y, z
    half_size_mm: tuple[float, float, float]
    name: str


Hardware = tuple[Cylinder | Box, ...]


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.linalg.norm(v)


def _frame_about(z: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """A rotation (3, 3) whose third column is ``z`` and whose first is random about it."""
    z = _unit(z)
    a = _unit(np.cross(z, rng.normal(size=3)))
    return np.stack([a, np.cross(z, a), z], axis=1)


def make_hardware(rng: np.random.Generator, *, site_carm_mm: NDArray[np.float64], anterior_carm: NDArray[np.float64]) -> Hardware:
    """Retractor blades either side of the incision, a second K-wire and a clamp, about ``site_carm_mm`` (frame C).

    ``anterior_carm``: the outward skin direction at the site (unit, frame C). The
    blades go through the skin beside the incision, the second wire enters at a
    slant 20-50 mm away, the clamp's jaws lie over the field above the skin.
    """
    site = np.asarray(site_carm_mm, dtype=np.float64)
    up = _unit(np.asarray(anterior_carm, dtype=np.float64))
    across = _frame_about(up, rng)[:, 0]
    along = np.cross(up, across)
    parts: list[Cylinder | Box] = []
    for side in (-1.0, 1.0):
        # A blade 25 mm wide, 1.5 mm thick, 70 mm deep below the skin and 50 mm above it, leaning outwards.
        lean = np.radians(rng.uniform(10, 30))
        depth_dir = _unit(-np.cos(lean) * up + side * np.sin(lean) * across)
        centre = site + side * rng.uniform(18, 30) * across + rng.normal(scale=5.0) * along + 10.0 * depth_dir
        width_dir = _unit(along + rng.normal(scale=0.15, size=3))
        thick_dir = _unit(np.cross(depth_dir, width_dir))
        width_dir = np.cross(thick_dir, depth_dir)
        parts.append(Box(centre_mm=tuple(centre), axes=tuple(map(tuple, np.stack([width_dir, thick_dir, depth_dir], axis=1))),
                         half_size_mm=(12.5, 0.75, 60.0), name=f"retractor{'LR'[side > 0]}"))
    lateral = rng.normal(size=3)
    lateral -= (lateral @ up) * up
    tip = site + rng.uniform(20, 50) * _unit(lateral) - 25.0 * up  # 25 mm into the patient
    wire_dir = _unit(up + rng.uniform(0.3, 0.9) * _unit(np.cross(up, rng.normal(size=3))))
    parts.append(Cylinder(start_mm=tuple(tip), end_mm=tuple(tip + 160.0 * wire_dir), radius_mm=1.0, name="second K-wire"))
    hinge = site + rng.uniform(60, 90) * _unit(across + rng.normal(scale=0.4) * along) + rng.uniform(15, 35) * up
    jaw_dir = _unit(site + 10.0 * up - hinge)
    for k in (-1.0, 1.0):
        spread = 6.0 * k * _unit(np.cross(jaw_dir, up))
        parts.append(Cylinder(start_mm=tuple(hinge + spread), end_mm=tuple(hinge + spread + 70.0 * jaw_dir), radius_mm=3.0, name="clamp jaw"))
    parts.append(Box(centre_mm=tuple(hinge - 10.0 * jaw_dir), axes=tuple(map(tuple, _frame_about(jaw_dir, rng))), half_size_mm=(8.0, 4.0, 12.0), name="clamp hinge"))
    return tuple(parts)


def collimator_mask(rng: np.random.Generator, rows: int, columns: int) -> NDArray[np.float64]:
    """Where lead covers the detector (rows, columns), 1 = fully covered, with a 2 px penumbra.

    Two shutter leaves come in from opposite sides at a random angle, each
    covering 4-15 % of the width, inside a circular iris of 0.9-1.0 of the
    half diagonal, as a technician collimates to the region of interest.
    """
    yy, xx = np.mgrid[0:rows, 0:columns].astype(np.float64)
    cx, cy = (columns - 1) / 2.0, (rows - 1) / 2.0
    theta = rng.uniform(0, np.pi)
    s = (xx - cx) * np.cos(theta) + (yy - cy) * np.sin(theta)
    half = min(rows, columns) / 2.0
    lo = -half * (1.0 - 2.0 * rng.uniform(0.04, 0.15))
    hi = half * (1.0 - 2.0 * rng.uniform(0.04, 0.15))
    iris = np.hypot(columns, rows) / 2.0 * rng.uniform(0.9, 1.0)
    covered = (s < lo) | (s > hi) | (np.hypot(xx - cx, yy - cy) > iris)
    return cv2.GaussianBlur(covered.astype(np.float32), (0, 0), 2.0).astype(np.float64)


@functools.lru_cache(maxsize=4)
def ii_distortion_maps(rows: int, columns: int, *, pincushion_px: float, s_px: float) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """cv2.remap maps (each (rows, columns), read-only) that distort an ideal detector image like an image intensifier.

    Pincushion: a point at radius r moves outwards by ``pincushion_px`` (r / r_corner)^3;
    S distortion (the earth's field on the electron optics): it turns by an angle
    growing with r^2, moving the field's edge ``s_px`` tangentially. The last few are kept (every shot of a detector
    uses the same maps; 70 ms each).
    """
    yy, xx = np.mgrid[0:rows, 0:columns].astype(np.float64)
    cx, cy = (columns - 1) / 2.0, (rows - 1) / 2.0
    dx, dy = xx - cx, yy - cy
    r = np.hypot(dx, dy)
    r_corner = np.hypot(cx, cy)
    r_edge = min(cx, cy)
    # Inverse map: the output pixel at r shows the ideal image at r - shift(r) (first order is enough at <1 %).
    radial = 1.0 - pincushion_px * (r / r_corner) ** 3 / np.maximum(r, 1e-9)
    angle = -s_px / r_edge * (r / r_edge) ** 2
    c, s = np.cos(angle), np.sin(angle)
    src_x = cx + radial * (c * dx - s * dy)
    src_y = cy + radial * (s * dx + c * dy)
    maps = src_x.astype(np.float32), src_y.astype(np.float32)
    for m in maps:
        m.setflags(write=False)
    return maps


# --- camera --------------------------------------------------------------------------------------------------


def _inside_tags(tags_px: list[NDArray[np.float64]], width: int, height: int) -> list[NDArray[np.float64]]:
    return [t for t in tags_px if np.all((t[:, 0] > 2) & (t[:, 0] < width - 3) & (t[:, 1] > 2) & (t[:, 1] < height - 3))]


def _glove(img: NDArray[np.float32], tags: list[NDArray[np.float64]], rng: np.random.Generator) -> None:
    """A gloved finger over one tag's corner: a quadrilateral covering the corner and 35-55 % of its two edges."""
    tag = tags[rng.integers(len(tags))]
    k = int(rng.integers(4))
    corner, nxt, prv, centre = tag[k], tag[(k + 1) % 4], tag[(k - 1) % 4], tag.mean(axis=0)
    f = rng.uniform(0.35, 0.55)
    poly = np.array([corner + 0.8 * (corner - centre), corner + f * (nxt - corner) + 0.4 * (corner - centre),
                     corner + f * (nxt - corner), corner + 0.5 * (centre - corner), corner + f * (prv - corner),
                     corner + f * (prv - corner) + 0.4 * (corner - centre)])
    mask = np.zeros(img.shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.round(poly * 16).astype(np.int32)], 1, lineType=cv2.LINE_AA, shift=4)
    shade = rng.uniform(0.85, 1.05)
    img[mask > 0] = np.asarray(GLOVE_BGR, np.float32) * shade


def _blood(img: NDArray[np.float32], tags: list[NDArray[np.float64]], rng: np.random.Generator) -> None:
    """15-40 dark red specks of 1-4 px radius, half of them on tags."""
    h, w = img.shape[:2]
    n = int(rng.integers(15, 41))
    for i in range(n):
        if tags and i % 2 == 0:
            t = tags[rng.integers(len(tags))]
            wts = rng.dirichlet(np.ones(4))
            c = wts @ t
        else:
            c = rng.uniform([0, 0], [w, h])
        axes = rng.uniform(1.0, 4.0, size=2)
        cv2.ellipse(img, (int(c[0]), int(c[1])), (int(np.ceil(axes[0])), int(np.ceil(axes[1]))), float(rng.uniform(0, 180)), 0, 360,
                    tuple(float(v * rng.uniform(0.7, 1.2)) for v in BLOOD_BGR), -1, lineType=cv2.LINE_AA)


def _tag_glare(img: NDArray[np.float32], tags: list[NDArray[np.float64]], rng: np.random.Generator) -> None:
    """A specular highlight on one glossy tag: a saturating Gaussian ellipse inside the tag."""
    tag = tags[rng.integers(len(tags))]
    c = rng.dirichlet(np.ones(4) * 3.0) @ tag
    size = float(np.sqrt(cv2.contourArea(tag.astype(np.float32))))
    sx, sy = size * rng.uniform(0.12, 0.25, size=2)
    a = rng.uniform(0, np.pi)
    h, w = img.shape[:2]
    r0, r1 = max(int(c[1] - 4 * max(sx, sy)), 0), min(int(c[1] + 4 * max(sx, sy)) + 1, h)
    c0, c1 = max(int(c[0] - 4 * max(sx, sy)), 0), min(int(c[0] + 4 * max(sx, sy)) + 1, w)
    yy, xx = np.mgrid[r0:r1, c0:c1].astype(np.float32)
    u = (xx - c[0]) * np.cos(a) + (yy - c[1]) * np.sin(a)
    v = -(xx - c[0]) * np.sin(a) + (yy - c[1]) * np.cos(a)
    g = np.exp(-0.5 * ((u / sx) ** 2 + (v / sy) ** 2))
    img[r0:r1, c0:c1] += (400.0 * g)[..., None]


def _line_kernel(length_px: float, angle_rad: float) -> NDArray[np.float32]:
    n = int(np.ceil(length_px)) | 1
    k = np.zeros((n, n), np.float32)
    c = n // 2
    d = np.array([np.cos(angle_rad), np.sin(angle_rad)]) * (length_px - 1) / 2
    cv2.line(k, (int(round(16 * (c - d[0]))), int(round(16 * (c - d[1])))), (int(round(16 * (c + d[0]))), int(round(16 * (c + d[1])))),
             1.0, 1, lineType=cv2.LINE_AA, shift=4)
    return k / k.sum()


def _disc_kernel(radius_px: float) -> NDArray[np.float32]:
    n = int(np.ceil(radius_px)) * 2 + 1
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32) - n // 2
    k = np.clip(radius_px + 0.5 - np.hypot(xx, yy), 0.0, 1.0)
    return (k / k.sum()).astype(np.float32)


def degrade_camera_frame(
    img: NDArray[np.float32],
    *,
    degradations: Degradations,
    rng: np.random.Generator,
    tags_px: list[NDArray[np.float64]],
    noise_sigma: float,
    blur_sigma_px: float,
) -> NDArray[np.uint8]:
    """Finish a rendered grey frame (height, width) float into what the camera delivers, with ``degradations``.

    ``tags_px``: each visible tag's four corners (4, 2) in pixels. Order of
    events: scene content (glare, glove, blood) under the OR light, then the
    lens (defocus) and motion, then the sensor (exposure gain, noise,
    saturation), then the stream's JPEG. Returns (height, width) uint8, or
    (height, width, 3) BGR when ``colour`` is on.
    """
    d = degradations
    h, w = img.shape
    bgr = np.repeat(img[..., None], 3, axis=2).astype(np.float32)
    if d.colour:
        bgr *= np.asarray(WARM_LIGHT_BGR, np.float32)
    tags = _inside_tags(tags_px, w, h)
    if d.tag_glare and tags:
        _tag_glare(bgr, tags, rng)
    if d.glove and tags:
        _glove(bgr, tags, rng)
    if d.blood:
        _blood(bgr, tags, rng)
    if d.defocus:
        bgr = cv2.filter2D(bgr, -1, _disc_kernel(rng.uniform(*d.defocus_px)), borderType=cv2.BORDER_REFLECT)
    if d.motion_blur:
        bgr = cv2.filter2D(bgr, -1, _line_kernel(rng.uniform(*d.motion_blur_px), rng.uniform(0, np.pi)), borderType=cv2.BORDER_REFLECT)
    if blur_sigma_px > 0:
        bgr = cv2.GaussianBlur(bgr, (0, 0), blur_sigma_px)
    if d.auto_exposure:
        bgr *= rng.uniform(*d.exposure_gain)
    bgr += rng.normal(scale=noise_sigma, size=bgr.shape if d.colour else (h, w, 1)).astype(np.float32)
    out = np.clip(bgr, 0, 255).astype(np.uint8)
    if not d.colour:
        out = cv2.cvtColor(out, cv2.COLOR_BGR2GRAY)
    if d.mjpeg:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(d.jpeg_quality[0], d.jpeg_quality[1] + 1))])
        if not ok:
            raise DegradationError("cv2 could not JPEG-encode the frame")
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR if d.colour else cv2.IMREAD_GRAYSCALE)
    return out
