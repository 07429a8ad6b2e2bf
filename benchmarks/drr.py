"""DRR speed (and agreement with DiffDRR when it is installed), beside the bars.

Bars on 2 cores: 256x256 from a 512x512x300 CT <= 300 ms; 128x128 from the half-resolution volume <= 30 ms;
64x64 from the quarter-resolution volume <= 5 ms; same-geometry DRR agrees with DiffDRR's (correlation >= 0.99).

Side by side with DiffDRR (when it is installed: the `bench` extra, in its own venv): DiffDRR renders the
real chest CT with its own reader, density and Siddon ray tracer at its tutorial pose; its detector's rays
(source and per-pixel target points) give the 3x4 projection matrix by DLT, and drillnav renders the very
same density volume on the same rays. Both are timed on the same 2 cores (torch.set_num_threads(2)).
Volumes: the twin pelvis at 0.703x0.703x1.0 mm (512x512x300) and the real chest CT in ../shared/data/ct
(512x512x133, if present). The detector is the paper's C-arm (976 x 0.304 mm) resampled to N x N pixels.
Run: .venv/bin/python benchmarks/drr.py   (with DiffDRR: .venv-bench/bin/python benchmarks/drr.py)
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


def projection_from_rays(source: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """3x4 P (world mm -> pixel column, row) from a pinhole's source (3,) and per-pixel targets (rows, columns, 3), by DLT."""
    rows, cols = targets.shape[:2]
    uu, vv = np.meshgrid(np.arange(cols, dtype=float), np.arange(rows, dtype=float))
    x0 = targets.reshape(-1, 3)
    x = np.vstack([x0, source + 0.6 * (x0 - source)])[::5]  # two depths: a planar set alone leaves P undetermined
    u, v = np.r_[uu.ravel(), uu.ravel()][::5], np.r_[vv.ravel(), vv.ravel()][::5]
    one, zero = np.ones_like(u), np.zeros((u.size, 4))
    xh = np.column_stack([x, one])
    a = np.vstack([np.hstack([xh, zero, -u[:, None] * xh]), np.hstack([zero, xh, -v[:, None] * xh])])
    return np.linalg.svd(a, full_matrices=False)[2][-1].reshape(3, 4)


def diffdrr_side_by_side(path: Path) -> list:
    """Image agreement and speed against DiffDRR on ``path`` (NIfTI); [] when DiffDRR is not installed."""
    try:
        import torch
        from diffdrr.data import read
        from diffdrr.drr import DRR
        from diffdrr.pose import convert
    except ImportError:
        print("DiffDRR: not installed (pip install -e .[bench] in a separate venv), side-by-side skipped")
        return []
    torch.set_num_threads(2)
    subject = read(str(path), orientation="AP", center_volume=True)
    figs = []
    for n, delx in ((256, 1.6), (128, 3.2)):
        drr = DRR(subject, sdd=1020.0, height=n, delx=delx)
        pose = convert(torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[0.0, 850.0, 0.0]]), parameterization="euler_angles", convention="ZXY")
        with torch.no_grad():
            theirs = drr(pose)[0, 0].numpy()
            ts = []
            for _ in range(5):
                t = time.perf_counter()
                drr(pose)
                ts.append(time.perf_counter() - t)
            source, target = drr.detector(pose, None)
        p = projection_from_rays(source[0].numpy().reshape(-1, 3)[0].astype(float), target[0].numpy().reshape(n, n, 3).astype(float))
        view = CArmView(projection_matrix=p, rows=n, columns=n, pixel_spacing_mm=(delx, delx))
        density = drr.density.numpy()  # (i, j, k) as torchio holds it; ours wants (k, j, i)
        vol = DrrVolume(mu=np.ascontiguousarray(np.transpose(density, (2, 1, 0)), dtype=np.float32), patient_from_voxel=drr.affine.matrix[0].numpy().astype(float))
        ours = render_drr(vol, view, np.eye(4))
        ms_ours = time_ms(vol, view, np.eye(4), repeats=10)
        r = float(np.corrcoef(ours.ravel(), theirs.ravel())[0, 1])
        ms_theirs = 1000 * float(np.median(ts))
        print(f"DiffDRR side by side, {path.name} {density.shape}, {n}x{n}: correlation {r:.4f}; drillnav {ms_ours:.1f} ms, DiffDRR {ms_theirs:.0f} ms (CPU, 2 threads)")
        figs.append(figure(f"correlation with DiffDRR {n}x{n}", r, "", 0.99, lower_is_better=False))
        figs.append(figure(f"drillnav vs DiffDRR time {n}x{n} full volume", ms_ours, "ms", ms_theirs))
    return figs


def main() -> None:
    # DiffDRR first, in a fresh process state: its Siddon tracer needs several GB at 256x256 on the full volume.
    figs = diffdrr_side_by_side(SHARED_CT) if SHARED_CT.is_file() else []
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
            vol = DrrVolume.from_ct(ct.downsampled(FACTOR[n]))  # the literal half / quarter volume the bars name
            prep = time.perf_counter() - t
            ms = time_ms(vol, detector(n, 0.0, -25.0), pose)
            print(f"{label}: {n}x{n} from {vol.mu.shape[::-1]} voxels: {ms:.1f} ms (volume prepared once in {prep:.2f} s)")
            figs.append(figure(f"{label.split(' ')[1]} {n}x{n} DRR from 1/{FACTOR[n]} volume", ms, "ms", BARS_MS[n]))
    report("drr", figs)


if __name__ == "__main__":
    main()
