"""Accuracy study in the twin, after the reference's experiments (Vagdargi et al. 2021, Sec. 3.1), over view pairs.

Per seed and view pair (inlet+outlet, AP+lateral, two random positioner angles), each scene is registered
with both views and with each view alone, for M = 3, 4, 5 markers (every subset of the 5 placed, as the
reference did), over several freehand drill poses; the joint solve (the product) beside the former
Horn + corner-PnP pipeline. Figures per configuration: median, IQR and 95th percentile of the drill-axis
error (position at the corridor entry, angle), outlier rate (over 10 mm or 10 deg), refusal rate with
reasons, coverage of the predicted 90 % bounds, and errors over 10 deg that were not flagged unreliable.
The twin is as hard as an operating room by default (``--degradations all``: every switch of
drivers/sim/degradations.py, the real CT as the patient); ``--per-degradation`` adds a table with one
degradation at a time (M = 5, joint solve) so each one's cost shows.
Writes docs/accuracy.md and docs/img/accuracy_violin.png; ends with one JSON line.
Reference medians (M = 5): 2 views 0.9 mm / 2.0 deg; 1 view 3.4 mm / 2.7 deg.
Run: nice .venv/bin/python benchmarks/accuracy.py [--seeds 8 --poses 2] [--degradations all|none|a,b] [--per-degradation] | --quick
"""

import argparse
import dataclasses
import itertools
import json
import pickle
import sys
import time
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402
from tag_detection import _true_corners  # noqa: E402

from drillnav.drivers.sim.anatomy import Corridor
from drillnav.drivers.sim.ct_anatomy import VoxelAnatomy
from drillnav.drivers.sim.degradations import CAMERA, Degradations
from drillnav.drivers.sim.scene import CAMERA_FOV_DEG, PAPER_CARM, TRUE_DRILL_AXIS_CAMERA, make_scene, render_fluoro
from drillnav.registration.errors import DrillnavError
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.pipeline import register_with_recovery, search_missing_tags
from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro
from drillnav.registration.video_markers import VideoDetections, VideoMarkerLocator

ROOT = Path(__file__).resolve().parents[1]
CT = ROOT.parent / "shared" / "data" / "ct" / "cxr.nii.gz"  # the real CT (../shared/data/README.md)
CT_PLAN = ROOT / "docs" / "examples" / "chest-plan.json"
REFERENCE = {(2, 5): (0.9, 2.0), (1, 5): (3.4, 2.7)}
METHODS = ("joint", "former")


@dataclass(frozen=True, kw_only=True)
class RandomPairs:
    """How the study draws its random view pair: the first view's primary angle within +-``primary_max_deg``, the
    second's ``separation_deg`` (low, high) away from it either way (clipped to +-120 deg), each view's secondary angle
    within +-``secondary_max_deg``. The defaults are the study's own; others (``--random-pairs``) try view pairs the
    study's seeds never draw, with the same random numbers, so every other pair's scene stays as it was."""

    primary_max_deg: float = 60.0
    separation_deg: tuple[float, float] = (40.0, 90.0)
    secondary_max_deg: float = 25.0


def _pairs(rng: np.random.Generator, random_pairs: RandomPairs = RandomPairs()) -> dict[str, str]:
    r = random_pairs
    a = rng.uniform(-r.primary_max_deg, r.primary_max_deg)
    b = a + rng.choice([-1, 1]) * rng.uniform(*r.separation_deg)
    return {"inlet+outlet": "inlet,outlet", "ap+lateral": "ap,lateral",
            "random": f"{a:.0f}:{rng.uniform(-r.secondary_max_deg, r.secondary_max_deg):.0f},{np.clip(b, -120, 120):.0f}:"
                      f"{rng.uniform(-r.secondary_max_deg, r.secondary_max_deg):.0f}"}


def camera_shots(scene, *, seed: int, k: int, poses: int) -> list:
    """``poses`` freehand drill poses of the study (seeded by seed and view pair k), what the camera locates in each, and
    the frame (for the tags the registration recovers): [(true carm_from_drill, VideoDetections, image)]."""
    locator = _locator(scene)
    pose_rng, camera_rng = np.random.default_rng([seed, k, 2]), np.random.default_rng([seed, k, 3])
    shots = []
    for _ in range(poses):
        pose = scene.drill_pose_towards(pose_rng, offset_mm=5.0, tilt_deg=5.0)
        image = scene.render_camera(camera_rng, carm_from_drill=pose)
        image.setflags(write=False)
        shots.append((pose, locator.locate(image), image))
    return shots


def camera_frames(scene, *, seed: int, k: int, poses: int) -> list:
    """:func:`camera_shots` without the frames: [(true carm_from_drill, VideoDetections)]."""
    return [(pose, video) for pose, video, _ in camera_shots(scene, seed=seed, k=k, poses=poses)]


def study_scenes(*, seeds: int, first_seed: int, poses: int, degradations: Degradations, patient: VoxelAnatomy | None):
    """The study's scenes as :func:`run` draws them (without its shared caches): per seed and view pair,
    (seed, pair, scene, {view name: fluoroscopy detections}, :func:`camera_shots`)."""
    for seed in range(first_seed, first_seed + seeds):
        rng = np.random.default_rng(seed)
        for k, (pair, views) in enumerate(_pairs(rng).items()):
            scene = make_scene(seed=seed, views=views, render=False, degradations=degradations,
                               voxel_anatomy=patient if degradations.ct_anatomy else None)
            image_rng = np.random.default_rng([seed, k, 1])
            dets = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in scene.views}
            yield seed, pair, scene, dets, camera_shots(scene, seed=seed, k=k, poses=poses)
        print(f"seed {seed} done", file=sys.stderr, flush=True)


def _locator(scene) -> VideoMarkerLocator:
    return VideoMarkerLocator(camera=scene.calibrated_camera, marker_ids=scene.marker_set.ids)


def _register(scene, image, video: VideoDetections, poses, *, joint: bool, recover: bool = True):
    """What the product does with a frame: register, recover the missing tags where that registration predicts them,
    register again (:func:`~drillnav.registration.pipeline.register_with_recovery`, ``track_frame``'s own step):
    (detections, registration). ``recover`` False: the detector's tags alone."""
    if not recover:
        return video, register_video_to_fluoro(video, poses, scene.marker_set, scene.calibrated_camera, joint=joint)
    return register_with_recovery(image, video, locator=_locator(scene), camera=scene.calibrated_camera, poses=poses, marker_set=scene.marker_set,
                                  joint=joint)


def load_patient(ct_path: Path) -> VoxelAnatomy:
    """The real CT as the patient, with the L1 trajectory of docs/examples/chest-plan.json."""
    from drillnav.drivers.ct_volume import read_ct

    if not ct_path.exists():
        raise SystemExit(f"the ct_anatomy degradation needs the real CT at {ct_path} (--ct PATH), or leave ct_anatomy out of --degradations")
    t = json.loads(CT_PLAN.read_text())["trajectories"][0]
    corridor = Corridor(name=t["name"], entry_mm=tuple(t["entry_mm"]), target_mm=tuple(t["target_mm"]), radius_mm=t["corridor"]["radius_mm"])
    return VoxelAnatomy.from_volume(read_ct(ct_path), corridor=corridor)


class _Shots:
    """Fluoroscopy detections and camera frames per scene, shared between degradation settings that image them alike.

    Camera switches do not change the fluoroscopy, and fluoroscopy switches do not change the camera frames,
    so a per-degradation study renders each only once per (seed, pair).
    """

    def __init__(self) -> None:
        self.fluoro: dict = {}
        self.video: dict = {}


def run(seeds: int, poses: int, first_seed: int = 3000, *, degradations: Degradations = Degradations(), patient: VoxelAnatomy | None = None,
        ms: tuple[int, ...] = (3, 4, 5), methods: tuple[str, ...] = METHODS, shots: _Shots | None = None,
        diagnose: list | None = None, recover: bool = True, measured_markers: bool = False, exact_calibration: bool = False,
        camera_size: tuple[int, int] = (1280, 720), carm: dict | None = None, random_pairs: RandomPairs = RandomPairs(),
        pairs: tuple[str, ...] | None = None, camera_fov_deg: float = CAMERA_FOV_DEG) -> dict:
    """rows[(pair, n_views, M, method)] = list of (pos_mm, ang_deg, bound90_pos_mm, bound90_ang_deg, reliable).

    ``diagnose``: a list that gets one dict per joint registration: refused (see :func:`_case`) or registered
    (its error, 90 % bounds, reliable, and the number of markers used).
    ``recover``: as the product runs, tags the camera missed are recovered where the frame's registration predicts
    them before each registration (False: the detector's tags alone, for comparison).
    ``measured_markers``: the product is handed the markers as ``drillnav markers measure`` writes them (the BBs as
    built, in the frame that best fits the design: :meth:`Scene.measured_marker_set`) instead of their design.
    ``exact_calibration``: the product is handed the drill camera's true intrinsics and the drill axis's true line
    instead of the calibration the twin draws at the uncertainty camera.json and drill.json state (what that draw adds
    to the error, for comparison; the predicted error still assumes the stated uncertainty).
    ``camera_size``: the drill camera's frame (width, height) px; ``camera_fov_deg`` its horizontal field of view.
    ``carm``: the C-arm's geometry and detector (``PAPER_CARM``'s keys; None: ``PAPER_CARM``).
    ``random_pairs``: how the random pair is drawn (:class:`RandomPairs`). ``pairs``: the pairs studied (None: every one);
    each keeps its seeds' scene and images.
    """
    rows: dict[tuple, list] = {}
    refusals: dict[tuple, Counter] = {}
    tried: Counter = Counter()
    shots = shots if shots is not None else _Shots()
    deg = degradations
    fluoro_key = tuple(n for n in deg.enabled if n not in CAMERA)
    video_key = tuple(n for n in deg.enabled if n in CAMERA or n in ("surgeon_markers", "ct_anatomy"))
    for seed in range(first_seed, first_seed + seeds):
        rng = np.random.default_rng(seed)
        for k, (pair, views) in enumerate(_pairs(rng, random_pairs).items()):
            if pairs is not None and pair not in pairs:
                continue
            scene = make_scene(seed=seed, views=views, render=False, degradations=deg, voxel_anatomy=patient if deg.ct_anatomy else None,
                               image_size=camera_size, camera_fov_deg=camera_fov_deg, carm=carm)
            if measured_markers:
                scene = replace(scene, marker_set=scene.measured_marker_set())
            if exact_calibration:
                scene = replace(scene, calibrated_camera=replace(scene.true_camera, uncertainty=scene.calibrated_camera.uncertainty),
                                calibrated_axis_drill=TRUE_DRILL_AXIS_CAMERA)
            names = list(scene.views)
            if (seed, pair, fluoro_key) not in shots.fluoro:
                image_rng = np.random.default_rng([seed, k, 1])
                shots.fluoro[(seed, pair, fluoro_key)] = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in names}
            dets = shots.fluoro[(seed, pair, fluoro_key)]
            if (seed, pair, video_key) not in shots.video:
                shots.video[(seed, pair, video_key)] = camera_shots(scene, seed=seed, k=k, poses=poses)
            frames = shots.video[(seed, pair, video_key)]
            for vs in [names] + [[n] for n in names]:
                marker_poses = register_markers([dets[n] for n in vs], [scene.views[n] for n in vs], scene.marker_set)
                for m in ms:
                    for subset in itertools.combinations(sorted(scene.carm_from_marker), m):
                        chosen = tuple(p for p in marker_poses if p.marker_id in subset)
                        for pose_index, (carm_from_drill, seen, image) in enumerate(frames):
                            # M markers placed: the camera sees only those (else it would claim the others' BBs).
                            placed = replace(seen, markers=tuple(v for v in seen.markers if v.marker_id in subset))
                            for method in methods:
                                key = (pair, len(vs), m, method)
                                tried[key] += 1
                                try:
                                    video, reg = _register(scene, image, placed, chosen, joint=method == "joint", recover=recover)
                                except DrillnavError as exc:
                                    reason = str(exc).split(" (")[0].split(";")[0]
                                    refusals.setdefault(key, Counter())[reason] += 1
                                    if diagnose is not None and method == "joint":
                                        # What the product had when it refused: the detector's tags and those the search
                                        # with no prediction found (register_with_recovery's first step).
                                        video = search_missing_tags(image, placed, locator=_locator(scene), poses=chosen) if recover else placed
                                        diagnose.append(_case(scene, carm_from_drill, video, {n: dets[n] for n in vs}, chosen, subset,
                                                              seed=seed, pair=pair, reason=str(exc)))
                                    continue
                                entry = scene.corridor_entry_carm_mm
                                axis = scene.calibrated_axis_drill.transformed(reg.carm_from_drill)
                                true_axis = TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
                                pe = predicted_axis_error(video, chosen, reg, scene.calibrated_axis_drill, working_point_carm_mm=entry)
                                pos = float(np.linalg.norm(axis.closest_point(entry) - true_axis.closest_point(entry)))
                                rows.setdefault(key, []).append((pos, axis.angle_deg(true_axis), pe.position90_mm, pe.angle90_deg, pe.reliable))
                                if diagnose is not None and method == "joint":
                                    diagnose.append({"seed": seed, "pair": pair, "views": list(vs), "M": m, "subset": subset, "pose": pose_index,
                                                     "used": len(reg.used_ids), "pos_mm": pos,
                                                     "ang_deg": axis.angle_deg(true_axis), "b90_mm": pe.position90_mm, "b90_deg": pe.angle90_deg,
                                                     "reliable": pe.reliable, **_seen(scene, carm_from_drill, video, chosen, subset)})
        print(f"[{deg.label()}] seed {seed} done", file=sys.stderr, flush=True)
    return {"rows": rows, "refusals": refusals, "tried": tried}


def tags_in_view(scene, carm_from_drill) -> set[int]:
    """Markers whose tag lies wholly inside the camera frame at this drill pose (the twin's truth, as tag_detection.py counts them)."""
    return set(_true_corners(scene, carm_from_drill))


def _seen(scene, carm_from_drill, video, chosen, subset) -> dict:
    """What each modality had of the M markers placed: tags in the camera's view (truth) and found, markers posed in fluoroscopy."""
    placed = set(subset)
    return {"camera_in_view": sorted(tags_in_view(scene, carm_from_drill) & placed),
            "camera_found": sorted({v.marker_id for v in video.markers} & placed),
            "posed": sorted(p.marker_id for p in chosen if p.observations)}


def _case(scene, carm_from_drill, video, dets: dict, chosen, subset, *, seed: int, pair: str, reason: str) -> dict:
    """One refused registration: what each modality saw of the M markers placed."""
    placed = set(subset)
    found = {v.marker_id for v in video.markers} & placed
    return {"seed": seed, "pair": pair, "views": list(dets), "M": len(placed),
            "camera_found": sorted(found), "camera_in_view": sorted(tags_in_view(scene, carm_from_drill) & placed),
            "identified": {n: sorted({m.marker_id for m in d.markers} & placed) for n, d in dets.items()},
            "rejected_rings": {n: Counter(r.reason.split(" (")[0] for r in d.rejected) for n, d in dets.items()},
            "posed": sorted(p.marker_id for p in chosen if p.observations),
            "common": sorted(found & {p.marker_id for p in chosen if p.observations}), "reason": reason.split(" (")[0]}


def print_cases(cases: list[dict]) -> None:
    """Per refused case (M = 5 only, to keep it short): camera tags found / in view, identified per view, common, reason;
    then the registrations by the number of markers they used (every M): n, median error, coverage, flagged."""
    done = [c for c in cases if "used" in c]
    print("| views | markers used | n | position median / max mm | angle median / max deg | coverage pos / ang | flagged | >10 deg unflagged |", file=sys.stderr)
    print("|---|---|---|---|---|---|---|---|", file=sys.stderr)
    for nv, used in sorted({(len(c["views"]), c["used"]) for c in done}):
        g = [c for c in done if len(c["views"]) == nv and c["used"] == used]
        pos, ang = np.array([c["pos_mm"] for c in g]), np.array([c["ang_deg"] for c in g])
        cov_p = 100.0 * np.mean([c["pos_mm"] <= c["b90_mm"] for c in g])
        cov_a = 100.0 * np.mean([c["ang_deg"] <= c["b90_deg"] for c in g])
        flagged = 100.0 * np.mean([not c["reliable"] for c in g])
        unflagged = sum(c["ang_deg"] > 10 and c["reliable"] for c in g)
        print(f"| {nv} | {used} | {len(g)} | {np.median(pos):.2f} / {pos.max():.2f} | {np.median(ang):.2f} / {ang.max():.2f} | "
              f"{cov_p:.0f} / {cov_a:.0f} % | {flagged:.0f} % | {unflagged} |", file=sys.stderr)
    for c in cases:
        if c["M"] != 5 or "used" in c:
            continue
        views = "; ".join(f"{n} {len(ids)} {ids} (rejected: {dict(c['rejected_rings'][n])})" for n, ids in c["identified"].items())
        print(f"seed {c['seed']} {c['pair']} [{','.join(c['views'])}] M=5: camera {len(c['camera_found'])}/{len(c['camera_in_view'])} "
              f"{c['camera_found']} of {c['camera_in_view']}; fluoro {views}; common {c['common']}; {c['reason']}", file=sys.stderr)


def losses(seeds: int, first_seed: int = 3000, *, degradations: Degradations, patient: VoxelAnatomy | None, poses: int = 1) -> dict:
    """Where markers are lost under ``degradations``, M = 5, before any registration: tags the camera finds of those in
    its field and those recovered from the registration's prediction (:func:`_register`), markers fluoroscopy identifies per
    view (of 5), and markers identified in >= 1 view and found (or recovered) by the camera."""
    cam_found = cam_in = cam_recovered = false_ids = 0
    per_kind: dict[str, list[int]] = {}
    common: list[int] = []
    common_detected: list[int] = []
    for seed in range(first_seed, first_seed + seeds):
        rng = np.random.default_rng(seed)
        for k, (pair, views) in enumerate(_pairs(rng).items()):
            scene = make_scene(seed=seed, views=views, render=False, degradations=degradations, voxel_anatomy=patient if degradations.ct_anatomy else None)
            image_rng = np.random.default_rng([seed, k, 1])
            dets = {n: detect_in_view(render_fluoro(scene, n, image_rng), scene.views[n], scene.marker_set) for n in scene.views}
            for n, d in dets.items():
                kind = n if pair != "random" else "random"
                per_kind.setdefault(kind, []).append(len(d.markers))
            identified = set().union(*({m.marker_id for m in d.markers} for d in dets.values()))
            marker_poses = register_markers([dets[n] for n in scene.views], list(scene.views.values()), scene.marker_set)
            for pose, video, image in camera_shots(scene, seed=seed, k=k, poses=poses):
                found = {v.marker_id for v in video.markers}
                # Recovered as the product does it with both views' marker poses and the frame's own registration.
                try:
                    recovered = [v for v in _register(scene, image, video, marker_poses, joint=True)[0].markers if v.recovered]
                except DrillnavError:  # no registration to predict from
                    recovered = []
                after = found | {v.marker_id for v in recovered}
                truth = _true_corners(scene, pose)
                cam_found += len(found)
                cam_recovered += len(recovered)
                cam_in += len(truth)
                # A recovery is false when its tag is not in view or a corner lies over 3 px from the truth.
                false_ids += sum(v.marker_id not in truth or np.linalg.norm(v.corners_px - truth[v.marker_id], axis=1).max() > 3.0 for v in recovered)
                common.append(len(after & identified))
                common_detected.append(len(found & identified))
    return {"camera_found": cam_found, "camera_recovered": cam_recovered, "camera_in_view": cam_in, "false_recoveries": int(false_ids),
            "identified": {k: float(np.mean(v)) for k, v in per_kind.items()},
            "common_mean": float(np.mean(common)), "common_lt3_pct": 100.0 * float(np.mean(np.array(common) < 3)),
            "common_detected_mean": float(np.mean(common_detected)), "common_detected_lt3_pct": 100.0 * float(np.mean(np.array(common_detected) < 3))}


def print_losses(seeds: int, first_seed: int = 3000, *, patient: VoxelAnatomy | None, settings: list[tuple[str, Degradations]]) -> None:
    """A markdown table of :func:`losses` per degradation setting."""
    kinds = ("ap", "lateral", "inlet", "outlet", "random")
    print("| setting | camera tags found / in view | + recovered (false) | " + " | ".join(kinds) + " | common (mean) detected / recovered too | common < 3 |")
    print("|---|---|---|" + "---|" * len(kinds) + "---|---|")
    for name, deg in settings:
        r = losses(seeds, first_seed, degradations=deg, patient=patient)
        ids = " | ".join(f"{r['identified'].get(k, float('nan')):.2f}" for k in kinds)
        print(f"| {name} | {r['camera_found']} / {r['camera_in_view']} | +{r['camera_recovered']} ({r['false_recoveries']}) | {ids} | {r['common_detected_mean']:.2f} / {r['common_mean']:.2f} | {r['common_detected_lt3_pct']:.0f} / {r['common_lt3_pct']:.0f} % |", flush=True)


def per_degradation(seeds: int, poses: int, *, patient: VoxelAnatomy | None, shots: _Shots, all_result: dict | None) -> list[dict]:
    """M = 5, joint solve: no degradation, each one alone, and all of them; pooled over the view pairs."""
    settings = [("none", Degradations())] + [(n, Degradations().only(n)) for n in Degradations.names() if n != "ct_anatomy" or patient is not None]
    out = []
    for name, deg in settings + ([] if all_result is not None else [("all", Degradations.parse("all"))]):
        result = run(seeds, poses, degradations=deg, patient=patient, ms=(5,), methods=("joint",), shots=shots)
        out += _pooled(name, result)
    if all_result is not None:
        out += _pooled("all", all_result)
    return out


def _pooled(name: str, result: dict) -> list[dict]:
    """One summary per number of views (M = 5, joint) over every view pair, with the worst pair's median."""
    out = []
    for nv in (2, 1):
        keys = [k for k in result["tried"] if k[1] == nv and k[2] == 5 and k[3] == "joint"]
        a = np.array([r for k in keys for r in result["rows"].get(k, [])], dtype=float).reshape(-1, 5)
        reasons = Counter()
        for k in keys:
            reasons.update(result["refusals"].get(k, {}))
        tried = sum(result["tried"][k] for k in keys)
        s = {"degradation": name, "views": nv, "n": len(a), "tried": tried, "refusal_pct": 100.0 * sum(reasons.values()) / max(tried, 1), "refusals": dict(reasons)}
        if len(a):
            worst = max((np.median(np.array(result["rows"][k])[:, 0]), k[0]) for k in keys if result["rows"].get(k))
            s |= _stats(a) | {"worst_pair": worst[1], "worst_pair_pos_median": float(worst[0])}
        out.append(s)
    return out


def _stats(a: np.ndarray) -> dict:
    """Quartiles and p95 of position and angle, outliers, coverage of the 90 % bounds, flagged, from rows (n, 5)."""
    q = np.percentile(a[:, :2], [25, 50, 75, 95], axis=0)
    return {"pos_q": q[:, 0].tolist(), "ang_q": q[:, 1].tolist(), "outlier_pct": 100.0 * float(((a[:, 0] > 10) | (a[:, 1] > 10)).mean()),
            "cover_pos_pct": 100.0 * float(np.mean(a[:, 0] <= a[:, 2])), "cover_ang_pct": 100.0 * float(np.mean(a[:, 1] <= a[:, 3])),
            "unflagged_over_10deg": int(np.sum((a[:, 1] > 10) & (a[:, 4] > 0.5))), "unreliable_pct": 100.0 * float(np.mean(a[:, 4] < 0.5))}


def _cells(s: dict) -> str:
    """The table cells from n to flagged of one summary."""
    if s["n"] == 0:
        return f"0 | - | - | - | - | - | {s['refusal_pct']:.0f} % | - | -"
    p, a = s["pos_q"], s["ang_q"]
    return (f"{s['n']} | {p[1]:.2f} [{p[0]:.2f}-{p[2]:.2f}] | {p[3]:.2f} | {a[1]:.2f} [{a[0]:.2f}-{a[2]:.2f}] | {a[3]:.2f} | "
            f"{s['outlier_pct']:.1f} % | {s['refusal_pct']:.0f} % | {s['cover_pos_pct']:.0f} / {s['cover_ang_pct']:.0f} % | {s['unreliable_pct']:.0f} %")


def summarise(result: dict) -> list[dict]:
    out = []
    for key in sorted(result["tried"]):
        pair, nv, m, method = key
        a = np.array(result["rows"].get(key, np.zeros((0, 5))), dtype=float).reshape(-1, 5)
        refused = sum(result["refusals"].get(key, Counter()).values())
        s = {"pair": pair, "views": nv, "M": m, "method": method, "n": len(a), "tried": result["tried"][key],
             "refusal_pct": 100.0 * refused / result["tried"][key], "refusals": dict(result["refusals"].get(key, {}))}
        if len(a):
            s |= _stats(a)
        out.append(s)
    return out


def write_docs(summary: list[dict], result: dict, command: str, degradations: Degradations, per_deg: list[dict] | None, minutes: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img_dir = ROOT / "docs" / "img"
    img_dir.mkdir(parents=True, exist_ok=True)
    keys = [k for k in sorted(result["rows"]) if k[2] == 5 and k[3] == "joint" and result["rows"][k]]
    violin = img_dir / "accuracy_violin.png"
    if keys:
        fig, axes = plt.subplots(1, 2, figsize=(12, 4))
        for ax, col, unit in zip(axes, (0, 1), ("position error at corridor entry (mm)", "angle error (deg)")):
            ax.violinplot([np.array(result["rows"][k])[:, col] for k in keys], showmedians=True)
            ax.set_xticks(range(1, len(keys) + 1), [f"{k[0]}\n{k[1]} view{'s' if k[1] > 1 else ''}" for k in keys], fontsize=7)
            ax.set_ylabel(unit)
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
        fig.suptitle(f"Joint solve, M = 5, degradations: {degradations.label()}")
        fig.tight_layout()
        fig.savefig(violin, dpi=90)
    else:
        violin.unlink(missing_ok=True)  # no registration to plot: an old figure would mislead
    if per_deg:
        fig, axes = plt.subplots(1, 2, figsize=(12, 5), sharey=True)
        for ax, nv in zip(axes, (2, 1)):
            rows = [s for s in per_deg if s["views"] == nv]
            y = np.arange(len(rows))
            med = [s["pos_q"][1] if s["n"] else np.nan for s in rows]
            p95 = [s["pos_q"][3] if s["n"] else np.nan for s in rows]
            ax.barh(y, med, color="tab:blue", label="median")
            ax.scatter(p95, y, color="tab:red", marker="|", s=200, label="p95")
            for yi, s, x in zip(y, rows, p95):
                if s["refusal_pct"] > 0:
                    ax.text(0.0 if np.isnan(x) else x, yi, f"  {s['refusal_pct']:.0f} % refused", va="center", fontsize=7)
            ax.axvline(REFERENCE[(nv, 5)][0], color="gray", ls="--", label="reference median")
            ax.set_yticks(y, [s["degradation"] for s in rows])
            ax.invert_yaxis()
            ax.set_xlabel("position error at the corridor entry (mm)")
            ax.set_title(f"{nv} view{'s' if nv > 1 else ''}, M = 5, joint")
            ax.grid(alpha=0.3, axis="x")
        axes[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(img_dir / "accuracy_degradations.png", dpi=90)
    lines = [
        "# Accuracy in the digital twin",
        "",
        f"Made by `nice -n 10 .venv/bin/python {command}` ({minutes:.0f} min on the shared 2-core machine; seeds from 3000, which",
        "the product's tests do not use). Twin degradations: " + (f"**{degradations.label()}** (" + ", ".join(degradations.enabled) + ")" if degradations.enabled else "**none** (the clean twin)") + ".",
        "With `ct_anatomy` the patient is the real chest/abdomen CT (`../shared/data/ct/cxr.nii.gz`) with the L1 trajectory of",
        "`docs/examples/chest-plan.json`, markers on its real skin; without it, the analytic pelvis. Each seed's patient is shot",
        "with three view pairs: inlet+outlet, AP+lateral and two random positioner angles (primary -60..60 deg, the",
        "second 40-90 deg away, secondaries -25..25 deg); each pair is registered with both views and with each view",
        "alone, with every subset of M of the 5 placed markers, at freehand drill poses. Position: distance at the",
        "planned corridor entry between the registered and the true drill axis; angle between them. Outliers: over",
        "10 mm or 10 deg. The product is handed calibrations with error (camera intrinsics and distortion, drill axis)",
        "and the marker design, while the twin images manufactured BBs, so these figures include those errors.",
        "",
        "`joint` is the product (`register_video_to_fluoro`, one joint solve of every marker pose and the drill pose over",
        "every BB and tag corner); `former` is the earlier pipeline (`joint=False`: Horn, then PnP on the corners of",
        "fluoroscopy-only marker poses). Coverage: share of registrations whose error is within the predicted 90 %",
        "bound (position, angle; the aim is 85-95 %). Flagged: share the product marks unreliable (a 90 % bound over",
        "3 mm or 3 deg).",
        "",
        "| pair | views | M | method | n | position median [IQR] mm | p95 mm | angle median [IQR] deg | p95 deg | outliers | refused | coverage pos / ang | flagged | >10 deg unflagged | reference |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in summary:
        ref = REFERENCE.get((s["views"], s["M"]))
        ref_txt = "%.1f mm / %.1f deg" % ref if ref else "-"
        lines.append(f"| {s['pair']} | {s['views']} | {s['M']} | {s['method']} | {_cells(s)} | {s.get('unflagged_over_10deg', '-')} | {ref_txt} |")
    lines += [
        "",
        "## How the product registers (what these figures measure)",
        "",
        "- **Marker poses in fluoroscopy** (`registration/marker_pose.py`): IPPE in the view with the most BBs, both",
        "  of its planar solutions (four BBs with three on one line, where IPPE has none: SQPnP's solution and its mirror",
        "  about the beam), each refined over every BB in every view; the runner-up is kept as the mirror pose",
        "  when it fits within 3x the best (a marker nearly face-on to the beam fits its mirror pose about as well, with",
        "  its normal off by about twice the tilt). A marker identified in one view claims its BBs in another view where",
        "  its ring was not identified (edge-on in a lateral view, rings overlapping) by projection after the best common",
        "  shift (posed in one view alone, sliding along that view's beam, either planar solution). A ring cut by the",
        "  field's edge keeps its arc and BBs when at least half of it is in the field. A marker showing a part of its",
        "  pattern that pairs with the design two ways nearly as well (symmetric about a line through its centre: nearly",
        "  edge-on, or BBs lost) is solved with each pairing; when both fit, every solution stays open, and only the BBs",
        "  the pairings agree on are observed until the camera settles which",
        "  ([identity and error](identity_and_error.md#a-pattern-that-pairs-with-its-design-two-ways-2-dec-2026-twenty-fourth-session)).",
        "- **The mirror choice**: the camera's tag normal, carried into C by the Horn rotation, picks each marker's side,",
        "  among all the solutions fluoroscopy left open; the claims' constellation fit anchors on each pairing in turn.",
        "- **Identity from the video** (`registration/video_claims.py`): the markers the camera sees, fitted as one rigid",
        "  group to the BBs of the markers fluoroscopy identified (one is enough), predict the others into each view, where",
        "  they claim their BBs (edge-on in a lateral view); anchors seen in one view only also slide along its beam and",
        "  try the mirror fit ([identity and error](identity_and_error.md#one-marker-in-one-view-and-a-tag-the-prediction-missed-30-nov-2026-night));",
        "  a view where fluoroscopy identifies no marker is still refused ([identity and error](identity_and_error.md)).",
        "- **One joint solve** (`registration/joint_solve.py`): every marker pose, `carm_from_drill` and the camera's",
        "  focal scale and principal point (held by priors of their calibration uncertainty) by least squares over every",
        "  BB in every view (0.35 px) and every tag corner (0.3 px); a robust pass names and rejects a marker that",
        "  stands out and drops single BBs over 5 sigma, and first leaves out a tag corner that a glove or a glare spot",
        "  displaced, keeping the marker on its other three; a marker still misfitting with two or more left is voted out",
        "  (the one without which the others fit; of two, the one that fits nothing alone), and a misfit left multiplies",
        "  the covariance by the reduced chi-square",
        "  ([identity and error](identity_and_error.md#a-marker-that-drags-the-others-and-a-misfit-the-bound-must-show-30-nov-2026-evening)).",
        "  Markers whose fluoroscopy-only pose did not converge join it. A tag whose four corners misfit a view of its",
        "  square by over 0.2 px RMS is charged sqrt(2) times that misfit as extra noise on each corner, and a recovered tag its stated 0.5 px",
        "  ([identity and error](identity_and_error.md#tags-the-frame-still-missed-rivals-the-registration-places-elsewhere-and-corners-that-are-no-square-30-nov-2026-late-night)).",
        "  Each tag's corners and each marker's BBs in a view also share a shift and a scale (stated sizes, whitened per",
        "  group); a BB whose shadow overlaps or nearly touches another's is charged its detector's pull (up to 3.5 px,",
        "  [identity and error](identity_and_error.md#bbs-pulled-by-a-neighbours-shadow-30-nov-2026-late)); a view from an",
        "  image intensifier has its pincushion and S distortion estimated under a 10 px prior",
        "  ([geometry](geometry.md#image-intensifier-distortion)).",
        "- **Edge-on rings' strokes** (`registration/edge_on_ring.py`): a marker the solve uses that shows fewer than four",
        '  BBs in a view where its ring is edge-on (its ellipse under 0.15 as wide as long: markers on the anterior skin in',
        "  a lateral view) is measured across its ring's stroke there. The image is sampled across each half of the stroke",
        "  the solve predicts, and each half's profile is slid (up to 30 px) against the marker's own predicted profile",
        '  (its wire and BBs, a dark margin either side); the shift of the best normalised correlation (each window\'s',
        "  straight-line trend taken out, the anatomy's slope; at least 0.7, no rival within 0.85 of it), refined to a",
        '  fraction of a pixel, places that half across its line. Two halves within 3 px of each other join the solve as',
        '  a row each (1 px); two 3-8 px apart (the solve\'s pose turned about the beam) give the ring\'s centre, their',
        '  middle, at a noise that counts half their disagreement; a half alone (the other outside the image or matched',
        '  poorly) is taken at 0.85 or more, at 2.5 px, where the solve uses another marker. The solve runs again, and the',
        '  strokes are measured once more at its poses; one left over 4 sigma from the solve with it is dropped',
        '  ([identity and error](identity_and_error.md#an-edge-on-rings-stroke-places-its-marker-where-its-bbs-cannot-5-dec-2026-forty-eighth-session)).',
        "- **Edge-on markers' rolls** (`registration/edge_on_roll.py`): where the solve uses two markers or more, a marker",
        "  edge-on in a view that shows it (its BBs or its stroke; same 0.15) is turned about its ring's line there: its",
        "  shadow (the marker's DRR, blurred 1 px) is rendered at turns of -10 to 10 deg in 0.5 deg steps and matched with",
        "  the image by normalised correlation, slid up to 30 px both ways. The best turn, refined by a parabola, matched at",
        "  0.45 or more and inside the search, joins the solve as one row: how far apart across the line the ring's near and",
        "  far sides lie (0.3 deg, through the ring's opening per degree). Nearly edge-on, the same turn the other way can",
        "  match about as well; a roll whose runner-up peak is within 0.8 of its best is solved at either angle, taken where",
        "  the fit is better by 9 (in reduced chi-square units), else left out. Measured at each stroke round's poses; one",
        "  left over 4 sigma from the solve with it is dropped",
        '  ([identity and error](identity_and_error.md#an-edge-on-markers-roll-about-its-own-line-from-its-whole-shadow-6-dec-2026-fifty-second-session)).',
        "- **Tags the camera missed** (a glove over a corner) are looked for where the registration predicts them, their",
        "  identity read from the visible code cells, and the registration repeated with them",
        "  ([identity and error](identity_and_error.md#tags-recovered-from-their-prediction-issue-17)); one predicted in the",
        "  frame but not found there is searched for in the whole frame",
        "  ([identity and error](identity_and_error.md#a-tag-the-prediction-misplaced-30-nov-2026-late)); one with an edge",
        "  hidden by a highlight is placed by its pose fitted to its other three edges",
        "  ([identity and error](identity_and_error.md#a-tag-with-one-edge-hidden-30-nov-2026-evening)); a registration on",
        "  one or two markers also tries each prediction shifted, out to 24 px. The tags of the set that the same",
        "  registration places elsewhere are no rivals to a recovered tag's identity, nor, when its solution is settled,",
        "  the markers it does not place (a posed marker holds the place): a tag glared past reading is named by its place",
        "  ([identity and error](identity_and_error.md#a-tag-glared-past-reading-named-by-the-place-its-posed-marker-holds-2-dec-2026-twenty-sixth-session));",
        "  its corners must be a view of its square within 1 px RMS. A registration that a named tag brought looks for the",
        "  tags still missing where it puts them, as one that gained markers does",
        "  ([identity and error](identity_and_error.md#a-slope-under-a-stroke-and-the-tags-a-named-tags-registration-puts-in-view-5-dec-2026-forty-ninth-session)).",
        "- **One or two markers in common** register (a tag's corners fix the marker's pose in D, its BBs its pose in C),",
        "  starting from the marker poses instead of Horn, with no outlier rejection below 3; refused only with no marker",
        "  in common or under 4 BBs in all ([identity and error](identity_and_error.md#one-or-two-markers-in-common)).",
        "- **The predicted error**: the solve's covariance (BB and corner noise each re-estimated from its own residuals, variance components; camera priors at their calibration size: focal 0.2 %, principal point 0.8 px, and the distortion coefficients, `DISTORTION_SIGMA` in `registration/joint_solve.py`) propagated to the axis with",
        "  the drill axis's calibration uncertainty; 90 % and 95 % bounds of the position at the working point and of the",
        "  angle; `reliable` is False when a 90 % bound is over its limit (`RELIABLE_POSITION_MM`, `RELIABLE_ANGLE_DEG`,",
        "  3 mm / 3 deg, keywords of `predicted_axis_error`).",
    ]
    covers = [c for x in summary if x["method"] == "joint" and x["n"] for c in (x["cover_pos_pct"], x["cover_ang_pct"])]
    cover_txt = f"{min(covers):.0f}-{max(covers):.0f} %" if covers else ""
    if per_deg:
        lines += [
            "",
            "## Each degradation alone (M = 5, joint solve, every view pair pooled)",
            "",
            "Same seeds, poses and view pairs as above, one degradation switched on at a time (`--per-degradation`); `none` is",
            "the clean twin and `all` the table above's setting. The worst pair is the view pair with the largest position",
            "median. See `drivers/sim/degradations.py` for what each switch does and its magnitudes.",
            "",
            "| degradation | views | n | position median [IQR] mm | p95 mm | angle median [IQR] deg | p95 deg | outliers | refused | coverage pos / ang | flagged | worst pair (median mm) | reference |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for s in per_deg:
            ref = "%.1f mm / %.1f deg" % REFERENCE[(s["views"], 5)]
            worst = f"{s['worst_pair']} ({s['worst_pair_pos_median']:.2f})" if s["n"] else "-"
            lines.append(f"| {s['degradation']} | {s['views']} | {_cells(s)} | {worst} | {ref} |")
    lines += [
        "",
        '## What these figures do not show yet',
        '',
        f"- The 90 % bounds cover {cover_txt} of the errors (aim: 85-95 %)." if covers else
        "- No registration in the main table succeeded, so it measures no coverage of the 90 % bounds (see each degradation alone).",
        f"- n is small: {len({k[0] for k in result['tried']})} view pairs x the seeds x the drill poses of the command above; a",
        "  percentile over fewer than 20 registrations is a rough figure.",
        "- Refusals for M < 5 also count subsets that include a marker outside the camera's field at that drill pose.",
    ]
    reasons = Counter()
    for s in summary:
        if s["method"] == "joint":
            reasons.update(s["refusals"])
    lines.append("\nRefusal reasons (joint, all configurations): " + ("; ".join(f"{r}: {n}" for r, n in reasons.most_common()) or "none") + ".")
    if keys:
        lines.append("\n![violins](img/accuracy_violin.png)\n")
    if per_deg:
        lines.append("\n![each degradation's cost](img/accuracy_degradations.png)\n")
    page = ROOT / "docs" / "accuracy.md"
    old = page.read_text() if page.exists() else ""
    if HAND_WRITTEN in old:
        lines.append("\n" + old[old.index(HAND_WRITTEN):].rstrip("\n"))
    page.write_text("\n".join(lines) + "\n")


# docs/accuracy.md's section written by hand from the measured tables: a re-run keeps it (and its date says which run).
HAND_WRITTEN = "## What these figures do not show: failures the hard twin exposes (written by hand)"


def with_marker_tilt(ap: argparse.ArgumentParser, degradations: Degradations, text: str | None) -> Degradations:
    """``degradations`` with the markers' tilt ``--marker-tilt`` gives (LOW,HIGH deg; None: as they are); a value the twin
    cannot use ends the command through ``ap`` with the reason."""
    if text is None:
        return degradations
    try:
        lo, hi = (float(v) for v in text.split(","))
        return dataclasses.replace(degradations, marker_tilt_deg=(lo, hi))
    except ValueError as exc:
        ap.error(f"--marker-tilt must be LOW,HIGH deg with 0 <= LOW <= HIGH < 80, got {text!r} ({exc})")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--poses", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="2 seeds, 1 pose, every degradation but ct_anatomy: a smoke run (70 s on the shared 2-core machine)")
    ap.add_argument("--no-docs", action="store_true")
    ap.add_argument("--degradations", default=None, help="all | none | comma-separated names from drivers/sim/degradations.py "
                    "(default all; with --quick all but ct_anatomy, whose DRRs take ~25 s a shot)")
    ap.add_argument("--per-degradation", action="store_true", help="also each degradation alone (M = 5, joint solve)")
    ap.add_argument("--ct", type=Path, default=CT, help="the real CT for the ct_anatomy degradation (default %(default)s)")
    ap.add_argument("--diagnose", action="store_true", help="print each refused joint registration (M = 5): tags the camera found vs in "
                    "its field, markers identified per view, markers in common, the reason; with --per-degradation, instead a table of "
                    "where markers are lost per degradation setting (no registrations)")
    ap.add_argument("--first-seed", type=int, default=3000)
    ap.add_argument("--save", type=Path, help="also pickle the raw results here (to re-plot without re-running; with --diagnose, "
                    "every joint registration and refusal by seed, pair and views, to compare two runs one by one)")
    ap.add_argument("--ms", type=int, nargs="+", default=[3, 4, 5], help="numbers of markers M to study (default 3 4 5)")
    ap.add_argument("--measured-markers", action="store_true", help="hand the product the markers as `drillnav markers measure` writes "
                    "them (BBs as built, taken as perfectly measured) instead of markers.json's design")
    ap.add_argument("--exact-calibration", action="store_true", help="hand the product the drill camera's true intrinsics and the drill "
                    "axis's true line instead of the calibration drawn at the uncertainty camera.json and drill.json state: what the "
                    "calibration adds to the error (the predicted error still assumes the stated uncertainty)")
    ap.add_argument("--no-recover", action="store_true", help="register from the detector's tags alone: no tag recovered from the "
                    "registration's prediction (the product before it; for comparison)")
    ap.add_argument("--camera-size", default="1280x720", help="the drill camera's frame, WIDTHxHEIGHT px (default %(default)s; the "
                    "horizontal field of view as --camera-fov gives it): the product at a resolution its twin does not default to")
    ap.add_argument("--detector", default=None, help="the C-arm's detector, ROWSxCOLUMNS@PIXEL_MM (default the reference's "
                    "976x976@0.304; e.g. 488x488@0.608 for 2x2 binning), its source distances unchanged")
    ap.add_argument("--camera-fov", type=float, default=CAMERA_FOV_DEG, help="the drill camera's horizontal field of view, deg (default %(default)s)")
    ap.add_argument("--source-distances", default=None, help="the C-arm's source-to-detector and source-to-isocentre distances, SID,SOD mm "
                    "(default the reference's 1164,624; the detector as --detector gives it)")
    ap.add_argument("--random-pairs", default=None, help="draw the random view pair with its views SEP_LOW-SEP_HIGH deg apart and secondary "
                    "angles within +-SECONDARY deg, as SEP_LOW,SEP_HIGH[,SECONDARY] (default 40,90,25: the study's own)")
    ap.add_argument("--pairs", default=None, help="study only these view pairs, comma-separated (inlet+outlet, ap+lateral, random; default every one)")
    ap.add_argument("--marker-tilt", default=None, help="with surgeon_markers, the markers' tilt from the AP beam, LOW,HIGH deg (default "
                    "the twin's 10,40; e.g. 0,10 for markers stuck flat on the skin, edge-on in a lateral view)")
    args = ap.parse_args()
    carm = None
    if args.detector is not None:
        try:
            size, spacing = args.detector.lower().split("@")
            rows, columns = (int(v) for v in size.split("x"))
            pixel_mm = float(spacing)
            if min(rows, columns) < 64 or not 0.01 <= pixel_mm <= 5.0:
                raise ValueError
        except ValueError:
            ap.error(f"--detector must be ROWSxCOLUMNS@PIXEL_MM (at least 64 px, 0.01-5 mm), got {args.detector!r}")
        carm = dict(PAPER_CARM, rows=rows, columns=columns, pixel_spacing_mm=(pixel_mm, pixel_mm))
    if args.source_distances is not None:
        try:
            sid, sod = (float(v) for v in args.source_distances.split(","))
            if not 300.0 <= sod < sid <= 2000.0:
                raise ValueError
        except ValueError:
            ap.error(f"--source-distances must be SID,SOD mm with 300 <= SOD < SID <= 2000, got {args.source_distances!r}")
        carm = dict(carm or PAPER_CARM, source_to_detector_mm=sid, source_to_isocenter_mm=sod)
    try:
        camera_size = tuple(int(v) for v in args.camera_size.lower().split("x"))
        if len(camera_size) != 2 or min(camera_size) < 160:
            raise ValueError
    except ValueError:
        ap.error(f"--camera-size must be WIDTHxHEIGHT px, each at least 160, got {args.camera_size!r}")
    if not 20.0 <= args.camera_fov <= 150.0:
        ap.error(f"--camera-fov must be 20-150 deg, got {args.camera_fov}")
    random_pairs = RandomPairs()
    if args.random_pairs is not None:
        try:
            values = [float(v) for v in args.random_pairs.split(",")]
            if len(values) not in (2, 3) or not 0.0 <= values[0] <= values[1] <= 180.0 or (len(values) == 3 and not 0.0 <= values[2] <= 60.0):
                raise ValueError
        except ValueError:
            ap.error(f"--random-pairs must be SEP_LOW,SEP_HIGH[,SECONDARY] deg (0 <= low <= high <= 180, secondary 0-60), got {args.random_pairs!r}")
        random_pairs = RandomPairs(separation_deg=(values[0], values[1]), **({"secondary_max_deg": values[2]} if len(values) == 3 else {}))
    known = tuple(_pairs(np.random.default_rng(0)))
    pairs = None if args.pairs is None else tuple(p.strip() for p in args.pairs.split(","))
    if pairs is not None and (not pairs or any(p not in known for p in pairs)):
        ap.error(f"--pairs takes {', '.join(known)}, comma-separated; got {args.pairs!r}")
    seeds, poses = (2, 1) if args.quick else (args.seeds, args.poses)
    if args.degradations is None:
        degradations = Degradations.parse("all")
        if args.quick:
            degradations = dataclasses.replace(degradations, ct_anatomy=False)
    else:
        degradations = Degradations.parse(args.degradations)
    degradations = with_marker_tilt(ap, degradations, args.marker_tilt)
    needs_ct = degradations.ct_anatomy or args.per_degradation
    patient = load_patient(args.ct) if needs_ct and (degradations.ct_anatomy or args.ct.exists()) else None
    t0 = time.perf_counter()
    if args.diagnose and args.per_degradation:
        settings = [("none", Degradations())] + [(n, Degradations().only(n)) for n in Degradations.names() if n != "ct_anatomy" or patient is not None]
        print_losses(seeds, args.first_seed, patient=patient, settings=settings + [(degradations.label(), degradations)])
        return
    shots = _Shots()
    cases: list | None = [] if args.diagnose else None
    result = run(seeds, poses, args.first_seed, degradations=degradations, patient=patient, shots=shots, diagnose=cases, ms=tuple(args.ms),
                 recover=not args.no_recover, measured_markers=args.measured_markers, exact_calibration=args.exact_calibration, camera_size=camera_size, carm=carm,
                 random_pairs=random_pairs, pairs=pairs, camera_fov_deg=args.camera_fov)
    if cases is not None:
        print_cases(cases)
    summary = summarise(result)
    per_deg = per_degradation(seeds, poses, patient=patient, shots=shots, all_result=result if degradations.label() == "all" else None) if args.per_degradation else None
    minutes = (time.perf_counter() - t0) / 60.0
    if args.save:
        # With --diagnose, "cases" names each joint registration (seed, pair, views, M, error, bounds) and each refusal, so
        # two runs can be compared registration by registration.
        args.save.write_bytes(pickle.dumps({"result": result, "summary": summary, "per_deg": per_deg, "minutes": minutes, "seeds": seeds, "poses": poses,
                                            "cases": cases}))
    # The docs table is the twin's own devices and view pairs.
    own_twin = (camera_size == (1280, 720) and args.camera_fov == CAMERA_FOV_DEG and carm is None and args.marker_tilt is None
                and not args.exact_calibration and random_pairs == RandomPairs() and pairs is None)
    if not args.no_docs and not args.quick and own_twin:
        command = (f"benchmarks/accuracy.py --seeds {seeds} --poses {poses} --degradations {degradations.label()}" + (" --per-degradation" if args.per_degradation else "")
                   + (" --measured-markers" if args.measured_markers else ""))
        write_docs(summary, result, command, degradations, per_deg, minutes)
    figs = []
    for s in summary:
        if s["n"] == 0 or s["M"] != 5:
            continue
        ref = REFERENCE.get((s["views"], s["M"]), (None, None))
        name = f"{s['pair']} {s['views']}v M={s['M']} {s['method']}"
        figs.append(figure(f"{name} pos median", s["pos_q"][1], "mm", ref[0]))
        figs.append(figure(f"{name} pos p95", s["pos_q"][3], "mm", None))
        figs.append(figure(f"{name} angle median", s["ang_q"][1], "deg", ref[1]))
        figs.append(figure(f"{name} cover90 pos", s["cover_pos_pct"], "%", None))
        figs.append(figure(f"{name} cover90 ang", s["cover_ang_pct"], "%", None))
        figs.append(figure(f"{name} refused", s["refusal_pct"], "%", None))
    for s in per_deg or []:
        if s["n"]:
            figs.append(figure(f"{s['degradation']} {s['views']}v M=5 joint pos median", s["pos_q"][1], "mm", REFERENCE[(s["views"], 5)][0]))
    report("accuracy", figs, seeds=seeds, poses_per_seed=poses, degradations=degradations.label(), measured_markers=args.measured_markers,
           exact_calibration=args.exact_calibration,
           camera_size=list(camera_size), camera_fov_deg=args.camera_fov, detector=args.detector or "976x976@0.304",
           source_distances_mm=[float((carm or PAPER_CARM)[k]) for k in ("source_to_detector_mm", "source_to_isocenter_mm")],
           marker_tilt_deg=list(degradations.marker_tilt_deg),
           random_pairs=dataclasses.asdict(random_pairs), pairs=list(pairs or known), summary=summary,
           per_degradation=per_deg)


if __name__ == "__main__":
    main()
