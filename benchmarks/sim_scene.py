"""Time to write a 5-marker, 2-view twin scene folder (issue bar: under 10 s on 2 cores), and the real CT's DRR
as the twin's anatomy: one view with a ray through every 2nd pixel (the twin's default) against every pixel.

Run: .venv/bin/python benchmarks/sim_scene.py
"""

import dataclasses
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

from drillnav.service.cli import main as cli


def main() -> None:
    times = []
    for seed in range(3):
        with tempfile.TemporaryDirectory() as d:
            t = time.perf_counter()
            assert cli(["sim", "scene", "--seed", str(seed), "--markers", "5", "--views", "inlet,outlet", "--out", d]) == 0
            times.append(time.perf_counter() - t)
    figures = [figure("sim scene 5 markers 2 views (median of 3)", sorted(times)[1], "s", 10.0)]
    figures += shot_render()
    figures += ct_anatomy_render()
    report("sim_scene", figures, note="reference: the issue's bar for the scene; every pixel's ray for the CT anatomy's DRR")


def shot_render() -> list[dict]:
    """One fluoroscopy shot of the twin (median of 5, K-wire in): the clean pelvis, and every degradation but the
    CT anatomy (low dose, hardware, collimator, image-intensifier distortion, surgeon-placed markers)."""
    import numpy as np

    from drillnav.drivers.sim.degradations import Degradations
    from drillnav.drivers.sim.scene import make_scene, render_fluoro

    out = []
    for label, degradations in (("clean", Degradations()), ("every degradation but the CT", dataclasses.replace(Degradations.parse("all"), ct_anatomy=False))):
        scene = make_scene(seed=2, views="ap,lateral", render=False, degradations=degradations)
        rng = np.random.default_rng(0)
        runs = []
        for k in range(5):
            t = time.perf_counter()
            render_fluoro(scene, ("ap", "lateral")[k % 2], rng, carm_from_drill=scene.carm_from_drill)
            runs.append(time.perf_counter() - t)
        out.append(figure(f"fluoroscopy shot, {label} (median of 5)", sorted(runs)[2], "s"))
    return out


def ct_anatomy_render() -> list[dict]:
    """The real chest CT's DRR for one view (median of 3): every 2nd pixel's ray (bilinear between) vs every pixel's."""
    import numpy as np

    from accuracy import CT, load_patient
    from drillnav.drivers.sim import ct_anatomy
    from drillnav.drivers.sim.scene import make_scene

    if not CT.exists():
        print(f"(no real CT at {CT}: the CT anatomy's DRR is not timed)")
        return []
    patient = load_patient(CT)
    scene = make_scene(seed=2, views="ap,lateral", render=False, voxel_anatomy=patient)
    view = scene.views["ap"]
    out = {}
    default = ct_anatomy.RENDER_STRIDE
    for stride in (1, default):
        ct_anatomy.RENDER_STRIDE = stride
        try:
            runs = []
            for _ in range(3):
                t = time.perf_counter()
                out[stride] = ct_anatomy.render_line_integrals(patient.truth_mu, view, scene.carm_from_ct)
                runs.append(time.perf_counter() - t)
        finally:
            ct_anatomy.RENDER_STRIDE = default
        out[f"t{stride}"] = sorted(runs)[1]
    diff = np.abs(out[default] - out[1])
    return [figure("real CT DRR per view, every pixel's ray", out["t1"], "s"),
            figure(f"real CT DRR per view, every {default}nd pixel's ray", out[f"t{default}"], "s", out["t1"]),
            figure("  its difference from every ray, RMS", float(np.sqrt(np.mean(diff**2))), "log"),
            figure("  its difference from every ray, p99", float(np.percentile(diff, 99)), "log")]


if __name__ == "__main__":
    main()
