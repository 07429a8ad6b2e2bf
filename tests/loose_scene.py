"""A view whose markers the detector leaves to the camera: the twin's inlet view (seed 42, three markers, all identified by
the detector) taken back to what a low-dose view behind dense bone leaves. No marker identified; one ring whose BBs
matched its own marker only loosely (and another marker, wrongly); the other markers' BBs among the view's blobs."""

from dataclasses import replace
from functools import lru_cache

import numpy as np

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.fluoro_markers import FluoroDetections, RejectedRing, detect_markers

SEED, VIEW = 42, "inlet"


@lru_cache(maxsize=1)
def loose_shot():
    """(scene, detections left with one loose ring, the ring's marker id, the other ids, camera image, true carm_from_drill)."""
    scene = make_scene(seed=SEED, n_markers=3, views=VIEW)
    det = detect_markers(scene.fluoro_log[VIEW], scene.marker_set)
    assert sorted(m.marker_id for m in det.markers) == sorted(scene.carm_from_marker), "the scene must show its three markers"
    rng = np.random.default_rng(SEED)
    carm_from_drill = scene.drill_pose_towards(rng, offset_mm=5.0, tilt_deg=5.0)
    image = scene.render_camera(rng, carm_from_drill=carm_from_drill)
    ring_id, *others = sorted(scene.carm_from_marker)
    found = det.by_id()[ring_id]
    # The ring's BBs matched to its own marker at a loose cost, and to another marker (the same BBs, a wrong design).
    loose = (replace(found, identification_cost_mm=1.6), replace(found, marker_id=others[0], identification_cost_mm=1.7))
    ring = RejectedRing(reason=f"no marker matches the observed {len(found.bbs)} BBs", center_px=np.asarray(found.ring_ellipse[0]), loose=loose)
    bare = FluoroDetections(markers=(), rejected=(ring,), blobs=det.blobs)
    return scene, bare, ring_id, tuple(others), image, carm_from_drill
