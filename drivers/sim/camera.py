"""The twin's drill camera: printed ArUco tags on marker bases, imaged through the TRUE lens.

Each output pixel inside a marker's footprint is traced backwards: distorted
pixel -> undistorted ray (true distortion) -> intersection with the tag plane
-> tag texture, supersampled. The product is later handed a camera.json with
calibration error, so the renderer and the product never share a lens model.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from drillnav.registration.camera import PinholeCamera
from drillnav.registration.markers import MarkerDesign
from drillnav.registration.transforms import apply, invert

from .degradations import Degradations, degrade_camera_frame

__all__ = ["render_markers", "tag_texture"]

_TEXTURES: dict[tuple[int, int, str], NDArray[np.float32]] = {}
TEXTURE_PX = 240  # texture pixels across the tag


def tag_texture(aruco_id: int, *, px: int = TEXTURE_PX, dictionary: str = "DICT_6X6_250") -> NDArray[np.float32]:
    key = (aruco_id, px, dictionary)
    if key not in _TEXTURES:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        _TEXTURES[key] = cv2.aruco.generateImageMarker(d, aruco_id, px).astype(np.float32)
    return _TEXTURES[key]


def _background(camera: PinholeCamera, rng: np.random.Generator) -> NDArray[np.float32]:
    h, w = camera.height, camera.width
    low = rng.normal(size=(h // 40 + 2, w // 40 + 2)).astype(np.float32)
    drape = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC) * 12.0 + 95.0
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    # Uneven OR lighting: brighter towards one corner.
    gx, gy = rng.uniform(-0.25, 0.25, size=2)
    light = 1.0 + gx * (xx / w - 0.5) + gy * (yy / h - 0.5)
    return drape * light


def render_markers(
    *,
    camera: PinholeCamera,
    camera_from_marker: dict[int, NDArray[np.float64]],
    markers: dict[int, MarkerDesign],
    rng: np.random.Generator,
    noise_sigma: float = 2.0,
    blur_sigma_px: float = 0.7,
    glare: bool = True,
    supersample: int = 2,
    occlusion: tuple[float, float, float] | None = None,
    degradations: Degradations | None = None,
) -> NDArray[np.uint8]:
    """Render a grayscale frame (height, width) uint8 of the given markers.

    With camera ``degradations`` (``drivers/sim/degradations.py``) the frame gets
    those too, and is (height, width, 3) BGR when ``colour`` is on.

    camera : the TRUE intrinsics and distortion.
    camera_from_marker : marker id -> (4, 4) pose of the marker frame in frame D.
    occlusion : optional (column, row, radius_px) disc of a glove in front of the field.
    """
    img = _background(camera, rng)
    h, w = camera.height, camera.width
    s = supersample
    tags_px: list[NDArray[np.float64]] = []
    for marker_id, pose in camera_from_marker.items():
        design = markers[marker_id]
        base_r = design.ring_radius_mm + 2.0
        t = np.linspace(0, 2 * np.pi, 32, endpoint=False)
        outline = np.stack([base_r * np.cos(t), base_r * np.sin(t), np.full(32, design.tag_center_mm[2]), np.ones(32)], axis=1)
        pts_d = (outline @ pose.T)[:, :3]
        if np.any(pts_d[:, 2] <= 1.0):
            continue
        px = camera.project(pts_d)
        c0, r0 = np.floor(px.min(axis=0)).astype(int) - 2
        c1, r1 = np.ceil(px.max(axis=0)).astype(int) + 3
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, w), min(r1, h)
        if c0 >= c1 or r0 >= r1:
            continue
        tags_px.append(camera.project(apply(pose, design.tag_corners_mm())))
        offs = (np.arange(s) + 0.5) / s - 0.5
        u = (np.arange(c0, c1)[:, None] + offs).reshape(-1)
        v = (np.arange(r0, r1)[:, None] + offs).reshape(-1)
        uu, vv = np.meshgrid(u, v)
        rays = camera.backproject(np.stack([uu.ravel(), vv.ravel()], axis=1))
        marker_from_camera = invert(pose)
        # Intersect rays from the optical centre with the tag plane z = tag_z in the marker frame.
        o_m = marker_from_camera[:3, 3]
        d_m = rays @ marker_from_camera[:3, :3].T
        tag_z = design.tag_center_mm[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (tag_z - o_m[2]) / d_m[:, 2]
        hit = o_m + lam[:, None] * d_m
        valid = (lam > 0) & np.isfinite(lam)
        x, y = hit[:, 0] - design.tag_center_mm[0], hit[:, 1] - design.tag_center_mm[1]
        half = design.tag_size_mm / 2.0
        tex = tag_texture(design.aruco_id, dictionary=design.aruco_dictionary)
        # Texture coordinates: tag x right -> column, tag y up -> row decreasing.
        tu = ((x + half) / design.tag_size_mm * TEXTURE_PX - 0.5).astype(np.float32)
        tv = ((half - y) / design.tag_size_mm * TEXTURE_PX - 0.5).astype(np.float32)
        shape = (len(v), len(u))
        sampled = cv2.remap(tex, tu.reshape(shape), tv.reshape(shape), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=235.0).reshape(-1)
        on_base = valid & (x * x + y * y <= base_r * base_r)
        patch_ss = np.where(on_base, sampled, np.nan).reshape(len(v), len(u))
        region = img[r0:r1, c0:c1]
        patch_ss_full = np.where(np.isnan(patch_ss), np.repeat(np.repeat(region, s, axis=0), s, axis=1), patch_ss)
        # Printed label: the tag is darker than pure black/white would be, under the same light.
        light = region.mean() / 95.0
        on = ~np.isnan(patch_ss)
        patch_ss_full = np.where(on, (patch_ss_full * 0.85 + 15.0) * light, patch_ss_full)
        img[r0:r1, c0:c1] = patch_ss_full.reshape(r1 - r0, s, c1 - c0, s).mean(axis=(1, 3))
    if glare:
        gc, gr = rng.uniform(0, w), rng.uniform(0, h)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        img += 60.0 * np.exp(-((xx - gc) ** 2 + (yy - gr) ** 2) / (2 * (0.06 * w) ** 2))
    if occlusion is not None:
        oc, orow, orad = occlusion
        yy, xx = np.mgrid[0:h, 0:w]
        img[(xx - oc) ** 2 + (yy - orow) ** 2 < orad**2] = 140.0
    if degradations is not None and degradations.camera:
        return degrade_camera_frame(img, degradations=degradations, rng=rng, tags_px=tags_px, noise_sigma=noise_sigma, blur_sigma_px=blur_sigma_px)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    img += rng.normal(scale=noise_sigma, size=img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


_RAYS: dict[tuple, NDArray[np.float64]] = {}


def _full_rays(camera: PinholeCamera, s: int) -> NDArray[np.float64]:
    """Rays through every sub-pixel of the camera (cached: undistorting a full frame is the slow part)."""
    k = (camera.width, camera.height, camera.camera_matrix.tobytes(), camera.distortion.tobytes(), s)
    if k not in _RAYS:
        offs = (np.arange(s) + 0.5) / s - 0.5
        uu, vv = np.meshgrid((np.arange(camera.width)[:, None] + offs).reshape(-1), (np.arange(camera.height)[:, None] + offs).reshape(-1))
        _RAYS.clear()
        _RAYS[k] = camera.backproject(np.stack([uu.ravel(), vv.ravel()], axis=1))
    return _RAYS[k]


def render_plane(
    *,
    camera: PinholeCamera,
    camera_from_plane: NDArray[np.float64],
    texture: NDArray[np.uint8],
    size_mm: tuple[float, float],
    rng: np.random.Generator,
    noise_sigma: float = 1.5,
    blur_sigma_px: float = 0.6,
    supersample: int = 2,
) -> NDArray[np.uint8]:
    """A flat textured board (calibration target, jig) seen through the TRUE lens.

    The board's x runs along texture columns and y down its rows, origin at the
    texture's top-left corner, ``size_mm`` = (width, height).
    """
    h, w = camera.height, camera.width
    s = supersample
    offs = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(w)[:, None] + offs).reshape(-1)
    v = (np.arange(h)[:, None] + offs).reshape(-1)
    rays = _full_rays(camera, s)
    plane_from_camera = invert(camera_from_plane)
    o = plane_from_camera[:3, 3]
    d = rays @ plane_from_camera[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -o[2] / d[:, 2]
    hit = o + lam[:, None] * d
    th, tw = texture.shape
    tu = (hit[:, 0] / size_mm[0] * tw - 0.5).astype(np.float32).reshape(len(v), len(u))
    tv = (hit[:, 1] / size_mm[1] * th - 0.5).astype(np.float32).reshape(len(v), len(u))
    tu[~(lam > 0).reshape(tu.shape)] = -10
    img = cv2.remap(texture.astype(np.float32), tu, tv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=90.0)
    img = img.reshape(h, s, w, s).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px) + rng.normal(scale=noise_sigma, size=(h, w))
    return np.clip(img, 0, 255).astype(np.uint8)


def checkerboard_texture(cols: int, rows: int, *, px_per_square: int = 40, margin_squares: int = 1) -> NDArray[np.uint8]:
    """A checkerboard with ``cols`` x ``rows`` inner corners and a white margin, as a texture."""
    nx, ny = cols + 1 + 2 * margin_squares, rows + 1 + 2 * margin_squares
    yy, xx = np.mgrid[0:ny, 0:nx]
    board = np.where((xx + yy) % 2 == 0, 30, 225).astype(np.uint8)
    board[:margin_squares], board[-margin_squares:] = 225, 225
    board[:, :margin_squares], board[:, -margin_squares:] = 225, 225
    return cv2.resize(board, (nx * px_per_square, ny * px_per_square), interpolation=cv2.INTER_NEAREST)
