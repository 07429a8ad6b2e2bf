"""Draw docs/img/slicer_scene.png: what docs/slicer.md's recipe loads into 3D Slicer, in Slicer's RAS world.

Run: .venv/bin/python docs/figures/slicer_scene.py
3D Slicer cannot run on the build machines, so this renders the very messages the
OpenIGTLink server sends for the reference recording (recordings/twin-seed21.mcap):
each shot as an IMAGE on its detector plane (schemas/igtl.fluoro_image_message's
geometry), the DrillModel POLYDATA placed by DrillToCArm (the twin's true
carm_from_drill of the first frame, converted to RAS as the server does), and the
isocentre's RAS axes. It is a rendering of the data, not a Slicer screenshot.
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.overlay import to_display
from drillnav.schemas import igtl
from drillnav.schemas import messages as msg
from drillnav.service.replay import iter_recording

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "img" / "slicer_scene.png"
STEP = 16  # image pixels per rendered quad


def main() -> None:
    shots, carm_from_drill = [], None
    for topic, _, data in iter_recording(ROOT / "recordings" / "twin-seed21.mcap"):
        if topic.endswith("fluoro/shot"):
            shot = msg.FluoroShot.from_bytes(data)
            shots.append((shot.image_log, shot.carm_view, shot.stamp_ns, shot.view))
        elif topic.endswith("twin/truth") and carm_from_drill is None:
            carm_from_drill = np.asarray(msg.decode_json(data)["carm_from_drill"])
    axis_drill = make_scene(seed=21, render=False).calibrated_axis_drill
    fig = plt.figure(figsize=(16, 8))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    zoom = fig.add_subplot(1, 2, 2, projection="3d")
    for image, view, _, name in shots:
        ras_from_ijk = igtl.RAS_FROM_LPS @ igtl.fluoro_image_lps_from_ijk(view)
        jj, ii = np.mgrid[0 : view.rows : STEP, 0 : view.columns : STEP]
        pts = ras_from_ijk @ np.stack([ii.ravel(), jj.ravel(), np.zeros(ii.size), np.ones(ii.size)])
        grey = to_display(image)[::STEP, ::STEP]
        grey = (grey if grey.ndim == 2 else grey[..., 0]) / 255.0
        ax.plot_surface(*(pts[k].reshape(ii.shape) for k in range(3)), facecolors=plt.cm.gray(grey), shade=False, rstride=1, cstride=1)
        centre = ras_from_ijk @ [(view.columns - 1) / 2, (view.rows - 1) / 2, 0, 1]
        ax.text(*centre[:3], f"IMAGE Fluoro-{name}", color="tab:blue")
        source = igtl.RAS_FROM_LPS[:3, :3] @ view.source_position_mm
        for a in (ax, zoom):
            a.plot(*np.stack([source, centre[:3]]).T, color="tab:blue", lw=0.8, ls=":")
    points, polygons = igtl.drill_cylinder(axis_drill, start_mm=60.0, length_mm=200.0, radius_mm=1.5)
    ras_from_drill = igtl.ras_transform(carm_from_drill, source_is_patient=False)
    p = (ras_from_drill @ np.c_[points, np.ones(len(points))].T)[:3].T
    for a, lim, title in [(ax, 700, "the shots on their detectors and the drill"), (zoom, 150, "around the isocentre: the drill model (K-wire)")]:
        a.plot_trisurf(p[:, 0], p[:, 1], p[:, 2], color="tab:green")
        a.text(*p[-1], "DrillModel under DrillToCArm", color="tab:green")
        for vec, label in [([1, 0, 0], "R"), ([0, 1, 0], "A"), ([0, 0, 1], "S")]:
            a.quiver(0, 0, 0, *(lim / 8 * np.asarray(vec)), color="tab:red")
            a.text(*(lim / 6.5 * np.asarray(vec)), label, color="tab:red")
        a.set_xlabel("R (mm)")
        a.set_ylabel("A (mm)")
        a.set_zlabel("S (mm)")
        a.set_title(title)
        a.set_box_aspect((1, 1, 1))
        a.set(xlim=(-lim, lim), ylim=(-lim, lim), zlim=(-lim, lim))
        a.view_init(elev=20, azim=-60)
    fig.suptitle("What Slicer loads over OpenIGTLink: rendered from the messages drillnav sends (RAS, C-arm isocentre at the origin); not a Slicer screenshot")
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.savefig(OUT, dpi=110)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
