"""DRR speed (and agreement with DiffDRR when it is installed), beside the bars.

Bars on 2 cores: 256x256 from a 512x512x300 CT <= 300 ms; 128x128 from the half-resolution volume <= 30 ms;
64x64 from the quarter-resolution volume <= 5 ms. (The side-by-side with DiffDRR is not built yet; the
kernel's accuracy is checked against exact analytic line integrals in tests/test_ct_registration.py.)
Volumes: the twin pelvis at 0.703x0.703x1.0 mm (512x512x300) and the real chest CT in ../shared/data/ct
(512x512x133, if present). The detector is the paper's C-arm (976 x 0.304 mm) resampled to N x N pixels.
Run: .venv/bin/python benchmarks/drr.py
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

from drillnav.drivers.ct_volume import read_ct
from drillnav.drivers.sim.ct_phantom import make_pelvis_ct
from drillnav.drivers.sim.scene import PAPER_CARM, make_scene
from drillnav.registration.carm import CArmView
from drillnav.registration.drr import DrrVolume, render_drr
from drillnav.registration.transforms import make_transform

SHARED_CT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ct" / "cxr.nii.gz"
BARS_MS = {256: 300.0, 128: 30.0, 64: 5.0}
FACTOR = {256: 1, 128: 2, 64: 4}


def detector(n: int, primary=0.0, secondary=0.0) -> CArmView:
    side = PAPER_CARM["columns"] * PAPER_CARM["pixel_spacing_mm"][0]
    return CArmView.from_positioner(primary_deg=primary, secondary_deg=secondary, source_to_detector_mm=PAPER_CARM["source_to_detector_mm"],
                                    source_to_isocenter_mm=PAPER_CARM["source_to_isocenter_mm"], pixel_spacing_mm=(side / n, side / n), rows=n, columns=n)


def time_ms(volume, view, pose, repeats=20) -> float:
    render_drr(volume, view, pose)  # compile / warm
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        render_drr(volume, view, pose)
        ts.append(time.perf_counter() - t)
    return 1000 * float(np.median(ts))


def main() -> None:
    figs = []
    volumes = [("twin pelvis 512x512x300", make_pelvis_ct(seed=0, voxel_mm=(0.703, 0.703, 1.0)))]
    if SHARED_CT.is_file():
        volumes.append(("real chest CT 512x512x133", read_ct(SHARED_CT)))
    else:
        print("real chest CT: ../shared/data/ct/cxr.nii.gz not present, skipped")
    scene = make_scene(seed=0, render=False)
    for label, ct in volumes:
        pose = scene.carm_from_ct if "twin" in label else make_transform(np.eye(3), -ct.centre_mm())
        for n in (256, 128, 64):
            t = time.perf_counter()
            vol = DrrVolume.from_ct(ct, downsample=FACTOR[n])
            prep = time.perf_counter() - t
            ms = time_ms(vol, detector(n, 0.0, -25.0), pose)
            print(f"{label}: {n}x{n} from {vol.mu.shape[::-1]} voxels: {ms:.1f} ms (volume prepared once in {prep:.2f} s)")
            figs.append(figure(f"{label.split(' ')[1]} {n}x{n} DRR from 1/{FACTOR[n]} volume", ms, "ms", BARS_MS[n]))
    report("drr", figs)


if __name__ == "__main__":
    main()
