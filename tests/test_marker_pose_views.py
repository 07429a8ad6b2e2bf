"""A marker identified in two views whose BBs were matched wrongly in one keeps the pose of the view that agrees."""

from __future__ import annotations

import numpy as np

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.fluoro_markers import DetectedBB, DetectedMarker, FluoroDetections
from drillnav.registration.marker_pose import register_markers
from drillnav.registration.transforms import apply


def _detections(scene, view_name: str, rng, *, spoil: int | None = None) -> FluoroDetections:
    """Each placed marker's BBs projected into the view with 0.2 px noise; ``spoil``: that marker's BBs matched wrongly
    (two design indices swapped, as clutter inside a ring or a mirrored assignment does)."""
    view = scene.views[view_name]
    markers = []
    for marker_id, pose in scene.carm_from_marker.items():
        design = scene.marker_set.by_id(marker_id)
        px = view.project(apply(pose, design.bb_centers_mm)) + rng.normal(scale=0.2, size=(len(design.bb_centers_mm), 2))
        index = np.arange(len(px))
        if marker_id == spoil:
            index[[1, 3]] = index[[3, 1]]
        bbs = tuple(DetectedBB(center_px=c, diameter_px=8.0, large=False) for c in px)
        markers.append(DetectedMarker(marker_id=marker_id, bbs=bbs, bb_index=index, ring_ellipse=((0.0, 0.0), (1.0, 1.0), 0.0), mirrored=False,
                                      identification_cost_mm=0.1))
    return FluoroDetections(markers=tuple(markers), rejected=(), blobs=tuple(b for m in markers for b in m.bbs))


def test_a_view_with_wrongly_matched_bbs_does_not_leave_the_marker_without_a_pose():
    scene = make_scene(seed=23, views="inlet,outlet", render=False)
    rng = np.random.default_rng(5)
    spoiled = sorted(scene.carm_from_marker)[0]
    dets = [_detections(scene, "inlet", rng), _detections(scene, "outlet", rng, spoil=spoiled)]
    poses = {p.marker_id: p for p in register_markers(dets, [scene.views["inlet"], scene.views["outlet"]], scene.marker_set)}
    assert all(p.converged for p in poses.values()), {i: (p.converged, round(p.residual_px, 2)) for i, p in poses.items()}
    p = poses[spoiled]
    # Posed from the inlet view alone: its own BBs, a single view's depth error along the beam at most.
    assert p.n_views == 1 and p.residual_px < 0.6
    assert np.linalg.norm(p.position_carm_mm - scene.carm_from_marker[spoiled][:3, 3]) < 1.5
    # The others keep both views.
    assert all(q.n_views == 2 for i, q in poses.items() if i != spoiled)
