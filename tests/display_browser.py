"""Headless Chromium for the display tests and benchmark: Debian's browser, driven by Playwright, never downloaded.

Tests skip (with the reason) only where Chromium is missing AND the ``CI`` variable is unset: on CI a missing
browser is a failure, since ``.ci/run`` installs it.
"""

from __future__ import annotations

import os
import shutil

import numpy as np

__all__ = ["chromium_path", "require_chromium", "launch", "axis_pixels_js", "fit_line_px", "line_distance_px"]

# The flags the machine notes ask for: no sandbox as root, and no background connections of the browser's own
# (on a closed network they fail, many at a time, and they would pollute the request log).
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--disable-default-apps", "--disable-extensions"]


def chromium_path() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def require_chromium() -> str:
    import pytest

    path = chromium_path()
    if path is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing on CI: .ci/run installs it with apt-get install -y chromium")
        pytest.skip("chromium is not installed (apt-get install -y chromium); CI installs it")
    pytest.importorskip("playwright.sync_api", reason="the test extra installs playwright")
    return path


def launch(playwright, executable_path: str):
    return playwright.chromium.launch(executable_path=executable_path, headless=True, args=CHROMIUM_ARGS)


# Every overlay pixel of the axis colour (#F0E442, antialiased edges excluded), per view, with the page's own record
# of what it drew, read in one task so they belong to the same frame.
axis_pixels_js = """() => {
  const out = {};
  for (const [name, v] of Object.entries(window.drillnav.views)) {
    if (!v.drawn || !v.overlay.width) continue;
    const W = v.overlay.width, H = v.overlay.height, d = v.overlay.getContext('2d').getImageData(0, 0, W, H).data, px = [];
    for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) {
      const q = (y * W + x) * 4;
      if (d[q + 3] === 255 && Math.abs(d[q] - 240) < 12 && Math.abs(d[q + 1] - 228) < 12 && Math.abs(d[q + 2] - 66) < 20) px.push([x, y]);
    }
    out[name] = {drawn: v.drawn, pixels: px, columns: v.columns, rows: v.rows};
  }
  return out;
}"""


def fit_line_px(pixels: list[list[int]]) -> tuple[np.ndarray, np.ndarray]:
    """Centre and unit direction (image pixel coordinates) of the line through the axis pixels (PCA)."""
    p = np.asarray(pixels, dtype=np.float64)
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    return c, vt[0]


def line_distance_px(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (N,) of points (N, 2) from the infinite line through a and b."""
    d = (b - a) / np.linalg.norm(b - a)
    r = np.atleast_2d(points) - a
    return np.abs(r[:, 0] * d[1] - r[:, 1] * d[0])
