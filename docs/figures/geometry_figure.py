"""Draw docs/img/geometry.png: the frames C, S, D, m and V in an AP view and a lateral view.

Run: .venv/bin/python docs/figures/geometry_figure.py
The C-arm geometry comes from drillnav.registration.carm, so the figure cannot drift from the code.
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from drillnav.registration.carm import CArmView

OUT = Path(__file__).resolve().parents[1] / "img" / "geometry.png"
PAPER = dict(source_to_detector_mm=1164.0, source_to_isocenter_mm=624.0, pixel_spacing_mm=(0.304, 0.304), rows=976, columns=976)


def arrow(ax, origin, vec, color, label):
    ax.annotate("", xy=origin + vec, xytext=origin, arrowprops=dict(arrowstyle="->", color=color, lw=2))
    ax.text(*(origin + 1.15 * vec), label, color=color, ha="center", va="center", fontsize=9)


def main() -> None:
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    for ax, (name, primary) in zip(axes, [("AP (primary 0, secondary 0), seen from the feet", 0.0), ("LAO 90 (primary +90), seen from the feet", 90.0)]):
        view = CArmView.from_positioner(primary_deg=primary, secondary_deg=0.0, **PAPER)
        _, source_from_carm = view.decompose()
        src = view.source_position_mm
        beam = source_from_carm[2, :3]
        col = source_from_carm[0, :3]
        det_centre = src + 1164.0 * beam
        # Axial plane seen from the feet: horizontal = patient's right on the left? We draw +x (patient left) to the right
        # and +y (posterior) downwards, i.e. looking from the feet with the patient supine.
        xy = lambda p: np.array([p[0], -p[1]])
        ax.plot(*xy(src), "o", color="orange")
        ax.text(*(xy(src) + [15, -40]), "source S", color="orange")
        half = 150.0
        a, b = xy(det_centre - half * col), xy(det_centre + half * col)
        ax.plot([a[0], b[0]], [a[1], b[1]], color="black", lw=4)
        ax.text(*(xy(det_centre) + [20, 30]), "detector (30 cm)", fontsize=9)
        ax.plot([xy(src)[0], xy(det_centre)[0]], [xy(src)[1], xy(det_centre)[1]], "--", color="orange", lw=1)
        ax.add_patch(plt.Circle((0, 0), 150, fill=False, color="tab:gray", lw=1))
        ax.text(0, 160, "patient (supine)", ha="center", color="tab:gray", fontsize=9)
        o = np.zeros(2)
        arrow(ax, o, np.array([260.0, 0.0]), "tab:red", "+x left (L)")
        arrow(ax, o, np.array([0.0, -260.0]), "tab:green", "+y posterior (P)")
        ax.text(10, 10, "C: isocentre, +z head (out of page)", fontsize=8)
        arrow(ax, xy(det_centre), xy(col) * 200 - xy(np.zeros(3)), "tab:blue", "+column")
        ax.set_title(name, fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlim(-800, 800)
        ax.set_ylim(-800, 800)
        ax.axis("off")
    fig.suptitle("drillnav frames: C-arm C (isocentre, patient LPS axes), source S per view", fontsize=12)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=90, bbox_inches="tight")
    print(OUT)


if __name__ == "__main__":
    main()
