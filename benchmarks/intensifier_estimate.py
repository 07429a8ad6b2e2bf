"""How well the joint solve estimates an image intensifier's distortion (issue 17).

An intensifier view without a dewarp calibration carries two distortion parameters in the joint solve: the pincushion
(radial) and S (tangential) shifts at the field's corner (:func:`~drillnav.registration.carm.intensifier_shift_px`),
with a zero-mean prior of ``intensifier_distortion_sigma_px`` (10 px on the reference's detector). This benchmark
registers the study's frames as the product does (``register_with_recovery``: the hard twin, every degradation but
the CT anatomy, whose DRRs add minutes and nothing to the distortion; inlet+outlet, AP+lateral and random view
pairs, both views; every marker of the scene) and sets each view's estimate beside the twin's own distortion
(``Degradations.ii_pincushion_px`` at the corner; ``ii_s_px`` is stated at the field's edge and grows with the cube
of the radius, so 2^1.5 times that at the corner). Reported: the median and quartiles of each parameter's estimate,
the median error, and the twin's value as the reference (ratio: estimate over truth).

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/intensifier_estimate.py [--seeds 3 --first-seed 3000 --poses 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402
from accuracy import _locator, study_scenes  # noqa: E402

from drillnav.drivers.sim.degradations import Degradations
from drillnav.registration.errors import DrillnavError
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.pipeline import register_with_recovery


def estimates(*, seeds: int, first_seed: int, poses: int) -> tuple[np.ndarray, tuple[float, float], int]:
    """((n, 2) estimated (pincushion, S) px at the field's corner per view and registration, the twin's (2,), refused)."""
    deg = dataclasses.replace(Degradations.parse("all"), ct_anatomy=False)
    truth = (deg.ii_pincushion_px, deg.ii_s_px * 2.0**1.5)
    rows, refused = [], 0
    for _, _, scene, dets, shots in study_scenes(seeds=seeds, first_seed=first_seed, poses=poses, degradations=deg, patient=None):
        names = list(scene.views)
        poses_ = register_markers([dets[n] for n in names], [scene.views[n] for n in names], scene.marker_set)
        for _, video, image in shots:
            try:
                reg = register_with_recovery(image, video, locator=_locator(scene), camera=scene.calibrated_camera, poses=poses_,
                                             marker_set=scene.marker_set, joint=True)[1]
            except DrillnavError:
                refused += 1
                continue
            rows += [np.asarray(c, dtype=np.float64) for _, c in reg.detector_distortion_px]
    return np.array(rows).reshape(-1, 2), truth, refused


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=3000)
    ap.add_argument("--poses", type=int, default=2)
    args = ap.parse_args(argv)
    got, truth, refused = estimates(seeds=args.seeds, first_seed=args.first_seed, poses=args.poses)
    if not len(got):
        raise SystemExit("no registration estimated an intensifier's distortion")
    figs = []
    for k, name in enumerate(("pincushion", "S")):
        q1, q2, q3 = np.percentile(got[:, k], [25, 50, 75])
        figs += [figure(f"{name} at the corner, median", float(q2), "px", truth[k], lower_is_better=False),
                 figure(f"{name} at the corner, lower quartile", float(q1), "px", truth[k], lower_is_better=False),
                 figure(f"{name} at the corner, upper quartile", float(q3), "px", truth[k], lower_is_better=False),
                 figure(f"{name} at the corner, median |error|", float(np.median(np.abs(got[:, k] - truth[k]))), "px")]
    print(f"{len(got)} view estimates from two-view registrations ({refused} refused)")
    report("intensifier_estimate", figs, seeds=args.seeds, first_seed=args.first_seed, poses=args.poses, views_estimated=len(got), refused=refused)


if __name__ == "__main__":
    main()
