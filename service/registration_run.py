"""The work of ``drillnav register`` (its parser is ``cli_register``, which imports this only when the command runs)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from drillnav.drivers.ct_volume import read_ct
from drillnav.drivers.fluoro_dicom import read_fluoro
from drillnav.drivers.image_files import read_image
from drillnav.registration.errors import MarkersNotFound
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.overlay import annotate, draw_axis, draw_detections, mask_markers, to_display
from drillnav.registration.pipeline import LiveCalibration, track_frame
from drillnav.schemas.calibration import read_camera_calibration, read_drill_calibration, read_drill_uncertainty
from drillnav.schemas.geometry_json import axis_to_json, transform_to_json
from drillnav.schemas.markers import read_marker_set

from .fluoro_polarity import settle_polarity
from .outputs import check_output_dir, check_output_path

__all__ = ["run_registration", "handle"]


def run_registration(args: argparse.Namespace) -> dict:
    if not args.ct and (args.plan or args.ct_views or args.ct_at):
        raise ValueError("--plan, --ct-views and --ct-at need --ct")
    timings: dict[str, float] = {}
    t = time.perf_counter()
    marker_set = read_marker_set(args.markers)
    camera = read_camera_calibration(args.camera)
    axis_drill = read_drill_calibration(args.drill)
    frame = read_image(args.video)
    images = [img for f in args.fluoro for img in read_fluoro(f)]
    timings["read_s"] = time.perf_counter() - t

    calibration = LiveCalibration.build(camera=camera, axis_drill=axis_drill, marker_set=marker_set, axis_uncertainty=read_drill_uncertainty(args.drill))
    # The frame is tracked below by the node's own pipeline. A frame in which ArUco finds no tag is not refused here: a
    # tag whose code reads only in part may still be named among the markers fluoroscopy poses (tag_hypotheses).
    t = time.perf_counter()
    tags_found = bool(calibration.locator.locate(frame).markers)
    timings["video_markers_s"] = time.perf_counter() - t

    t = time.perf_counter()
    # An image whose file does not say which way its values run is taken in the reading that shows the markers.
    settled = [settle_polarity(img, marker_set) for img in images]
    images, detections = [s.image for s in settled], [s.detections for s in settled]
    timings["fluoro_features_s"] = time.perf_counter() - t
    # One is enough: the camera's markers claim the others' BBs (video_claims); a ring matched only loosely (a candidate,
    # or a loose match to one marker alone) may still be borne out by the camera's constellation, so it counts here too.
    named = [{m.marker_id for m in det.markers} | {m.marker_id for r in det.rejected for m in ((r.candidate,) if r.candidate else ()) + r.loose}
             for det in detections]
    for img, det, ids in zip(images, detections, named):
        if not ids and len(images) == 1:
            raise MarkersNotFound(f"{Path(img.source_file).name}: no marker identified in the single view; at least 1 is needed" + "".join(f"; {r.reason}" for r in det.rejected))
    seen = set().union(*named)
    if not seen & set(marker_set.ids):
        raise MarkersNotFound(f"none of the marker set's ids {sorted(marker_set.ids)} is identified in the fluoroscopy views")

    t = time.perf_counter()
    poses = register_markers(detections, [img.view for img in images], marker_set)
    if args.refine_gi:
        from dataclasses import replace

        from drillnav.registration.kcr import refine_marker_pose

        refined = []
        for p in poses:
            seen = [(img.view, img.pixels_log) for img, det in zip(images, detections) if p.marker_id in det.by_id()]
            if not seen:  # posed from a ring no view identified it by (a candidate, a loose match): nothing to refine on
                refined.append(p)
                continue
            r = refine_marker_pose(marker_set.by_id(p.marker_id), p.carm_from_marker, [v for v, _ in seen], [i for _, i in seen])
            refined.append(replace(p, carm_from_marker=r.carm_from_marker, converged=p.converged and r.converged))
        poses = tuple(refined)
    timings["marker_registration_s"] = time.perf_counter() - t

    t = time.perf_counter()
    try:
        fa = track_frame(frame, calibration=calibration, poses=poses, marker_set=marker_set)  # the node's pipeline, one home
    except MarkersNotFound as exc:
        if tags_found:
            raise
        raise MarkersNotFound(f"{args.video}: {exc}") from None
    timings["video_to_fluoro_s"] = time.perf_counter() - t
    video, reg, pe, axis_c, axis_out = fa.video, fa.registration, fa.predicted_error, fa.axis_full_carm, fa.axis_carm

    result = {
        "carm_from_drill": transform_to_json(reg.carm_from_drill),
        "drill_axis_carm": axis_to_json(axis_out),
        "views": [{"file": img.source_file, "frame": img.frame_index, "geometry": img.geometry_source, "line_px": [float(v) for v in axis_c.project(img.view.projection_matrix)],
                   "markers_identified": sorted(m.marker_id for m in det.markers), "rejected": [r.reason for r in det.rejected],
                   "detector_distortion_px": _distortion_of(reg, img.view), "polarity": st.note or "stated by the file"}
                  for img, det, st in zip(images, detections, settled)],
        "markers": [{"id": p.marker_id, "position_carm_mm": [float(v) for v in p.position_carm_mm], "fre_mm": reg.fre_mm.get(p.marker_id),
                     "residual_px": p.residual_px, "views": p.n_views, "converged": p.converged, "needs_camera": p.needs_camera,
                     "loose": p.loose, "rejected": p.marker_id in reg.rejected_ids}
                    # a loose match (one marker alone, RejectedRing.loose) is listed only where the camera bore it out
                    for p in poses if not p.loose or p.marker_id in reg.used_ids],
        "predicted_error": {"position_mm": pe.position_mm, "angle_deg": pe.angle_deg, "cone_half_angle_deg": pe.cone_half_angle_deg, "at": "axis point nearest the markers' centroid"},
        "video": {"markers": [m.marker_id for m in video.markers], "ignored_ids": list(video.ignored_ids), "unplaced_ids": list(video.unplaced_ids), "misread_ids": list(video.misread_ids), "corner_rms_px": reg.corner_rms_px},
        "timings_s": timings,
    }
    if args.ct:
        result["ct"] = _ct_mode(args, images, detections, axis_out, pe.cone_half_angle_deg, timings)
    if args.overlays:
        t = time.perf_counter()
        out_dir = check_output_dir(args.overlays)
        for img, det in zip(images, detections):
            base = mask_markers(img.pixels_log, det) if args.mask_markers else img.pixels_log
            coef = _distortion_of(reg, img.view)
            bgr = draw_axis(draw_detections(to_display(base), det), img.view, axis_c, cone_half_angle_deg=pe.cone_half_angle_deg, position_error_mm=pe.position_mm,
                            distortion_px=None if coef is None else np.asarray(coef))
            bgr = annotate(bgr, view_name=img.view_name, predicted_error=(pe.position_mm, pe.angle_deg))
            cv2.imwrite(str(out_dir / f"{Path(img.source_file).stem}-{img.frame_index}.png"), bgr)
        timings["overlays_s"] = time.perf_counter() - t
    return result


def _distortion_of(reg, view) -> list[float] | None:
    """The view's intensifier distortion as the registration estimated it ([pincushion, S] at the field's corner, px); None for a flat panel."""
    return next(([float(c[0]), float(c[1])] for v, c in reg.detector_distortion_px if v is view), None)


def _ct_mode(args: argparse.Namespace, images, detections, axis_carm, cone_half_angle_deg: float, timings: dict[str, float]) -> dict:
    from .ct_mode import axis_in_ct_report, load_plan, register_ct_to_fluoro

    t = time.perf_counter()
    plan = load_plan(args.plan) if args.plan else None
    views_dir = check_output_dir(args.ct_views) if args.ct_views else None
    ct = read_ct(args.ct)
    timings["ct_read_s"] = time.perf_counter() - t
    at = None
    if args.ct_at:
        try:
            at = np.array([float(v) for v in args.ct_at.split(",")])
            assert at.shape == (3,)
        except (ValueError, AssertionError):
            raise ValueError(f"--ct-at wants X,Y,Z in CT mm, got '{args.ct_at}'") from None
    elif plan:
        at = plan[0].trajectory.entry_mm
    t = time.perf_counter()
    reg = register_ct_to_fluoro(ct, images, detections, at_isocentre_mm=at)
    timings["ct_registration_s"] = time.perf_counter() - t
    report = axis_in_ct_report(ct, reg, axis_carm, cone_half_angle_deg=cone_half_angle_deg, plan=plan, views_dir=views_dir)
    report["ct"] = ct.description
    timings["ct_report_s"] = report.pop("report_s")
    return report


def handle(args: argparse.Namespace) -> int:
    out = check_output_path(args.out, suffixes=(".json",))
    result = run_registration(args)
    out.write_text(json.dumps(result, indent=1))
    a = result["drill_axis_carm"]
    if "ct" in result:
        c = result["ct"]
        flags = "; ".join(f"{r['trajectory']}: {'BREACH' if r['breach'] else 'clear'} (min clearance {r['min_clearance_mm'] if r['min_clearance_mm'] is None else round(r['min_clearance_mm'], 1)} mm)"
                          for r in c["conformance"] if r["evaluated"])
        print(f"CT registered: GC {c['registration']['similarity_gc']:.3f}, {'converged' if c['registration']['converged'] else 'NOT converged'} in {c['registration']['runtime_s']:.1f} s" + (f"; {flags}" if flags else ""))
    print(f"registered with markers {[m['id'] for m in result['markers'] if not m['rejected']]}; axis point {np.round(a['point_mm'], 1).tolist()} mm, "
          f"direction {np.round(a['direction'], 3).tolist()}; predicted error {result['predicted_error']['position_mm']:.2f} mm / {result['predicted_error']['angle_deg']:.2f} deg -> {out}")
    return 0
