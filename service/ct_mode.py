"""Video-CT mode: register the CT to the fluoroscopy views, carry the drill axis into CT, judge it against the plan.

``L_V = ct_from_carm @ carm_from_drill @ L_D``. Wiring only: the math is in
registration/ (ct_registration, conformance, ct_views).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drillnav.drivers.ct_volume import read_ct
from drillnav.registration.conformance import Conformance, SurfaceDistance, conformance_along
from drillnav.registration.ct_registration import CtRegistration, FluoroShot, register_ct
from drillnav.registration.ct_views import PlannedTrajectory, compose_views, render_ct_views
from drillnav.registration.errors import DrillnavError
from drillnav.registration.fluoro_masks import marker_mask, metal_mask
from drillnav.registration.line import Line3D
from drillnav.registration.transforms import invert, make_transform
from drillnav.registration.volume import Volume
from drillnav.schemas.geometry_json import axis_to_json, transform_to_json
from drillnav.schemas.scene_files import read_plan

__all__ = ["PlanEntry", "load_plan", "initial_carm_from_ct", "register_ct_to_fluoro", "axis_in_ct_report", "acceptance_surface", "shots_for_ct", "plan_entries", "angle_and_offset", "CtModeError", "Judgement", "judge_conformance"]


MAX_ANGLE_TO_JUDGE_DEG = 45.0


class CtModeError(DrillnavError):
    """The CT, plan or their combination cannot be used (names the file and the problem)."""


@dataclass(frozen=True, kw_only=True)
class PlanEntry:
    trajectory: PlannedTrajectory
    acceptance: dict[str, Any]


def load_plan(path: str | Path) -> list[PlanEntry]:
    return plan_entries(read_plan(path), base=Path(path).parent)


def plan_entries(doc: dict[str, Any], *, base: Path) -> list[PlanEntry]:
    """A validated plan document as entries; label volume paths resolved against ``base``; bone at 200 HU by default."""
    out = []
    for t in doc["trajectories"]:
        acc = dict(t.get("acceptance", {"type": "bone", "threshold_hu": 200.0}))
        if acc["type"] == "label":
            acc["path"] = str((base / acc["path"]).resolve())
        out.append(PlanEntry(trajectory=PlannedTrajectory(name=t["name"], entry_mm=np.asarray(t["entry_mm"], float), target_mm=np.asarray(t["target_mm"], float),
                                                          radius_mm=float(t["corridor"]["radius_mm"])), acceptance=acc))
    return out


def initial_carm_from_ct(ct: Volume, *, at_isocentre_mm: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """C follows the supine patient (docs/geometry.md), so only a translation: ``at_isocentre_mm`` (CT point the
    C-arm is centred on: the planned entry, else the CT's centre) goes to the isocentre."""
    p = ct.centre_mm() if at_isocentre_mm is None else np.asarray(at_isocentre_mm, dtype=np.float64)
    return make_transform(np.eye(3), -p)


def shots_for_ct(views_images_detections) -> list[FluoroShot]:
    """``(view, image_log, detections | None)`` triples as shots with markers (detected rings and BBs) and other metal masked."""
    shots = []
    for view, image_log, det in views_images_detections:
        exclude = metal_mask(image_log)
        if det is not None:
            exclude |= marker_mask(image_log.shape, det)
        shots.append(FluoroShot(view=view, image_log=image_log, exclude=exclude))
    return shots


def register_ct_to_fluoro(ct: Volume, images, detections, *, at_isocentre_mm=None, search_mm: float = 120.0, seed: int = 0) -> CtRegistration:
    """Masks markers and other metal out of each view, then registers from the initial guess."""
    shots = shots_for_ct([(img.view, img.pixels_log, det) for img, det in zip(images, detections)])
    return register_ct(ct, shots, initial_carm_from_ct(ct, at_isocentre_mm=at_isocentre_mm), search_mm=search_mm, seed=seed)


def acceptance_surface(ct: Volume, entry: PlanEntry, cache: dict) -> SurfaceDistance:
    """The signed distance to ``entry``'s acceptance volume (bone threshold or labels), cached by its definition."""
    acc = entry.acceptance
    pts = np.vstack([entry.trajectory.entry_mm, entry.trajectory.target_mm])
    # The map is cropped about this trajectory, so the trajectory is part of the key, not the definition alone.
    key = (acc["type"], acc.get("threshold_hu"), acc.get("path"), tuple(acc.get("labels", ())), tuple(pts.ravel().tolist()))
    if key not in cache:
        if acc["type"] == "bone":
            cache[key] = SurfaceDistance.bone(ct, threshold_hu=float(acc.get("threshold_hu", 200.0)), around_mm=pts)
        else:
            labels = read_ct(acc["path"])
            mask = np.isin(np.asarray(labels.data), acc["labels"])
            if not mask.any():
                raise CtModeError(f"{acc['path']}: none of the labels {acc['labels']} is present")
            # The label volume keeps its own grid: distances are taken in patient mm, so it need not match the CT's.
            cache[key] = SurfaceDistance.from_mask(mask, labels.patient_from_voxel, around_mm=pts)
    return cache[key]


def angle_and_offset(axis_ct: Line3D, trajectory: PlannedTrajectory) -> tuple[float, float]:
    """Angle (deg) between the axis and the planned direction, and the axis's distance (mm) from the planned entry."""
    planned = (trajectory.target_mm - trajectory.entry_mm) / np.linalg.norm(trajectory.target_mm - trajectory.entry_mm)
    angle = float(np.degrees(np.arccos(np.clip(axis_ct.direction @ planned, -1.0, 1.0))))
    return angle, float(axis_ct.distance_to_point(trajectory.entry_mm))


@dataclass(frozen=True, kw_only=True)
class Judgement:
    """The axis against one planned trajectory: judged (``result``) when within ``MAX_ANGLE_TO_JUDGE_DEG`` of it, else why not."""

    entry: PlanEntry
    axis_to_planned_entry_mm: float
    angle_to_plan_deg: float
    result: Conformance | None
    reason: str | None = None

    @property
    def trajectory(self) -> str:
        return self.entry.trajectory.name

    @property
    def evaluated(self) -> bool:
        return self.result is not None

    @property
    def breach(self) -> bool:
        return bool(self.result is not None and self.result.breach)

    @property
    def min_clearance_mm(self) -> float | None:
        if self.result is None or not np.isfinite(self.result.min_distance_mm):
            return None
        return float(self.result.min_distance_mm)

    @property
    def kwire_radius_mm(self) -> float:
        return float(self.result.kwire_radius_mm) if self.result is not None else float("nan")

    def min_clearance_where(self, axis_ct: Line3D) -> tuple[float, tuple[float, float, float]] | None:
        """Where the clearance is smallest: mm along ``axis_ct`` from its entry into bone, and the point in V; None if not judged."""
        c = self.result
        if c is None or c.entry_mm is None:
            return None
        judged = np.flatnonzero(c.judged)
        if not judged.size:
            return None
        i = int(judged[np.argmin(c.distance_mm[judged])])
        point = c.entry_mm + c.along_mm[i] * axis_ct.direction
        return float(c.along_mm[i]), (float(point[0]), float(point[1]), float(point[2]))


def judge_conformance(ct: Volume, axis_ct: Line3D, plan: list[PlanEntry], cache: dict, *, nearest_only: bool = False) -> list[Judgement]:
    """The one conformance judgement (the CLI and the live CT tracker both call it).

    Each trajectory within ``MAX_ANGLE_TO_JUDGE_DEG`` of the axis is judged
    along its acceptance surface; one further off is listed with the reason.
    ``nearest_only``: only the judged trajectory nearest the axis (by distance
    from its planned entry), or nothing (the live tracker, at camera rate).
    """
    rows = []
    for entry in plan:
        angle, offset = angle_and_offset(axis_ct, entry.trajectory)
        rows.append((entry, angle, offset))
    if nearest_only:
        judged = [r for r in rows if r[1] <= MAX_ANGLE_TO_JUDGE_DEG]
        rows = [min(judged, key=lambda r: r[2])] if judged else []
    out = []
    for entry, angle, offset in rows:
        t = entry.trajectory
        if angle > MAX_ANGLE_TO_JUDGE_DEG:
            out.append(Judgement(entry=entry, axis_to_planned_entry_mm=offset, angle_to_plan_deg=angle, result=None,
                                 reason=f"the axis is {angle:.0f} deg off this trajectory (judged within {MAX_ANGLE_TO_JUDGE_DEG:.0f} deg)"))
        else:
            c = conformance_along(axis_ct, acceptance_surface(ct, entry, cache), planned_entry_mm=t.entry_mm, planned_target_mm=t.target_mm)
            out.append(Judgement(entry=entry, axis_to_planned_entry_mm=offset, angle_to_plan_deg=angle, result=c))
    return out


def axis_in_ct_report(
    ct: Volume,
    reg: CtRegistration,
    axis_carm: Line3D,
    *,
    cone_half_angle_deg: float,
    plan: list[PlanEntry] | None,
    views_dir: Path | None,
) -> dict[str, Any]:
    """The axis in CT, conformance against each planned trajectory, and the slice images (when ``views_dir``)."""
    t0 = time.perf_counter()
    ct_from_carm = invert(reg.carm_from_ct)
    axis_ct = axis_carm.transformed(ct_from_carm)
    report: dict[str, Any] = {
        "carm_from_ct": transform_to_json(reg.carm_from_ct),
        "registration": {"similarity_gc": reg.similarity, "initial_similarity_gc": reg.initial_similarity, "residual": reg.residual,
                         "converged": reg.converged, "evaluations": reg.evaluations, "runtime_s": reg.runtime_s,
                         "levels": [{"similarity_gc": lv.similarity, "evaluations": lv.evaluations, "stop": lv.stop, "seconds": lv.seconds,
                                     "detector_bin": lv.level.detector_bin, "volume_factor": lv.level.volume_factor} for lv in reg.levels]},
        "drill_axis_ct": axis_to_json(axis_ct),
        "conformance": [],
    }
    centre = axis_ct.point_mm
    for j in judge_conformance(ct, axis_ct, plan or [], {}):
        row: dict[str, Any] = {"trajectory": j.trajectory, "axis_to_planned_entry_mm": j.axis_to_planned_entry_mm, "angle_to_plan_deg": j.angle_to_plan_deg}
        if not j.evaluated:
            row.update(evaluated=False, reason=j.reason)
        else:
            c = j.result
            row.update(evaluated=True, breach=j.breach, min_clearance_mm=j.min_clearance_mm,
                       kwire_radius_mm=c.kwire_radius_mm, entry_ct_mm=None if c.entry_mm is None else [float(v) for v in c.entry_mm],
                       breach_at_mm=[float(v) for v in c.breach_along_mm[:50]],
                       along_mm=[round(float(v), 2) for v in c.along_mm[::2]], clearance_mm=[round(float(v), 2) for v in c.distance_mm[::2]])
        report["conformance"].append(row)
    if report["conformance"]:
        nearest = min(report["conformance"], key=lambda r: (not r["evaluated"], r["axis_to_planned_entry_mm"]))
        report["nearest_trajectory"] = nearest["trajectory"]
        centre = axis_ct.closest_point(next(e.trajectory.entry_mm for e in plan if e.trajectory.name == nearest["trajectory"]))
    if views_dir is not None:
        import cv2

        views = render_ct_views(ct, axis_ct=axis_ct, centre_mm=centre, cone_half_angle_deg=cone_half_angle_deg, plan=[e.trajectory for e in plan or []])
        files = {}
        for name, img in views.items():
            f = views_dir / f"ct-{name}.png"
            cv2.imwrite(str(f), img)
            files[name] = str(f)
        mosaic = views_dir / "ct-views.png"
        judged = [r for r in report["conformance"] if r.get("evaluated") and r["trajectory"] == report.get("nearest_trajectory")]
        cv2.imwrite(str(mosaic), compose_views(views, caption=f"CT registration GC {reg.similarity:.3f}", verdict=judged[0] if judged else None))
        files["mosaic"] = str(mosaic)
        report["views"] = files
    report["report_s"] = time.perf_counter() - t0
    return report
