"""Fluoroscopy marker detection under imaging settings the twin does not use (issue 17: scenes the team never sees).

The background is the shared real radiograph (../shared/data/xray); the markers' tungsten is the known-component
model's DRR (``kcr.render_marker_drr``), not the twin's X-ray simulator; then scatter, Poisson quanta and a
detector blur, as in ``tests/test_real_anatomy_background.py``. Each setting changes one thing from the default
(6,000 quanta, 20 % scatter, 0.7 px blur, anatomy line integrals to 5.5, the twin's 0.304 mm pixels): the
detector's pixel size (binned), its blur, the dose, the anatomy's density, scatter. Per setting: markers
identified of those in the field, false identities, markers posed (``register_markers``, both views) and their
position error. Scenes: seeds 21-23 (default), inlet + outlet and AP + lateral.

There is no reference figure for this (the paper used one C-arm); each count is printed beside the default
setting's as a ratio.
Run: .venv/bin/python benchmarks/detector_sweep.py [--seeds 3 --first-seed 21]
Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import pydicom

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.carm import CArmView
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.kcr import render_marker_drr
from drillnav.registration.marker_pose import register_markers

RADIOGRAPH = Path(__file__).resolve().parents[2] / "shared" / "data" / "xray" / "chest-pa-RG1_UNCI.dcm"
DEFAULT = {"binning": 1, "quanta": 6000.0, "scatter": 0.2, "blur_px": 0.7, "anatomy": 5.0}
SETTINGS = {
    "default": {},
    "binned 2x2 (0.61 mm pixels)": {"binning": 2},
    "binned 3x3 (0.91 mm pixels)": {"binning": 3},
    "no detector blur": {"blur_px": 0.0},
    "blur 1.5 px": {"blur_px": 1.5},
    "blur 2.5 px": {"blur_px": 2.5},
    "300 quanta": {"quanta": 300.0},
    "1,000 quanta": {"quanta": 1000.0},
    "30,000 quanta": {"quanta": 30000.0},
    "thin anatomy (to 1.5)": {"anatomy": 1.0},
    "dense anatomy (to 9.5)": {"anatomy": 9.0},
    "100 % scatter, 1,000 quanta": {"scatter": 1.0, "quanta": 1000.0},
}


def shot(radiograph: np.ndarray, scene, view: CArmView, rng: np.random.Generator, *, quanta: float, scatter: float, blur_px: float, anatomy: float) -> np.ndarray:
    """Log attenuation (rows, columns): a patch of the radiograph as anatomy, the markers' DRR, scatter, quanta, blur."""
    r0, c0 = rng.integers(0, radiograph.shape[0] - 900), rng.integers(0, radiograph.shape[1] - 900)
    line = cv2.resize(radiograph[r0 : r0 + 900, c0 : c0 + 900], (view.columns, view.rows)) * anatomy + 0.5
    for marker_id, pose in scene.carm_from_marker.items():
        line = line + render_marker_drr(scene.manufactured[marker_id], pose, view, (0, 0, view.columns, view.rows))
    primary = quanta * np.exp(-line)
    counts = rng.poisson(primary + scatter * cv2.GaussianBlur(primary, (0, 0), 40.0 * view.columns / 976)).astype(np.float32)
    if blur_px > 0:
        counts = cv2.GaussianBlur(counts, (0, 0), blur_px)
    return (-np.log(np.maximum(counts, 1.0) / quanta)).astype(np.float32)


def run_setting(radiograph: np.ndarray, setting: dict, seeds: range) -> dict:
    p = {**DEFAULT, **setting}
    in_field = identified = false_ids = 0
    errors: list[float] = []
    for seed in seeds:
        for pair in ("inlet,outlet", "ap,lateral"):
            scene = make_scene(seed=seed, views=pair, render=False)
            rng = np.random.default_rng(seed)
            views = [scene.views[n].binned(p["binning"]) for n in scene.views]
            dets = []
            for view in views:
                image = shot(radiograph, scene, view, rng, quanta=p["quanta"], scatter=p["scatter"], blur_px=p["blur_px"], anatomy=p["anatomy"])
                det = detect_in_view(image, view, scene.marker_set)
                dets.append(det)
                ids, truth = {m.marker_id for m in det.markers}, set(scene.carm_from_marker)
                in_field, identified, false_ids = in_field + len(truth), identified + len(ids & truth), false_ids + len(ids - truth)
            for pose in register_markers(dets, views, scene.marker_set):
                if pose.converged and pose.marker_id in scene.carm_from_marker:
                    errors.append(float(np.linalg.norm(pose.position_carm_mm - scene.carm_from_marker[pose.marker_id][:3, 3])))
    e = np.asarray(errors) if errors else np.asarray([np.nan])
    return {"marker_views": in_field, "identified": identified, "false_ids": false_ids, "posed": len(errors),
            "pose_error_median_mm": round(float(np.median(e)), 3), "pose_error_max_mm": round(float(np.max(e)), 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=21)
    args = ap.parse_args()
    if not RADIOGRAPH.is_file():
        raise SystemExit(f"the shared radiograph is not on this machine: {RADIOGRAPH}")
    raw = pydicom.dcmread(str(RADIOGRAPH)).pixel_array.astype(np.float32)
    radiograph = raw / raw.max()  # MONOCHROME1: bright where the body attenuates
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    t0 = time.time()
    results = {}
    for name, setting in SETTINGS.items():
        r = results[name] = run_setting(radiograph, setting, seeds)
        ratio = r["identified"] / max(results["default"]["identified"], 1)
        r["identified_vs_default"] = round(ratio, 2)
        print(f"{name:30s} identified {r['identified']:3d} / {r['marker_views']} ({ratio:.2f} x default), false ids {r['false_ids']}, "
              f"posed {r['posed']}, pose error median {r['pose_error_median_mm']:.3f} mm, max {r['pose_error_max_mm']:.2f} mm", flush=True)
    print(f"seeds {seeds.start}-{seeds.stop - 1}, {time.time() - t0:.0f} s")
    print(json.dumps({"benchmark": "detector_sweep", "first_seed": seeds.start, "seeds": args.seeds, "settings": results}))


if __name__ == "__main__":
    main()
