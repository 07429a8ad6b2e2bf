"""Markers identified in fluoroscopy on the twin as hard as an operating room (issue 17).

With surgeon-placed markers, low dose, surgical hardware, collimation and image-intensifier distortion, a
clamp's jaw or a K-wire crossing a ring cuts its wire into arcs; each arc was fitted and identified on its
own, from the same BBs, and the detector then dropped the marker as "found twice" (seed 3000's AP view of
the accuracy study, benchmarks/accuracy.py, pair ap+lateral: marker 12). A blob smaller than any BB inside a
ring (metal's end or corner) made every BB look large, so no central BB was found (seed 3001's AP view:
marker 39). Both are identified now, and every identity stays at its true place. A ring partly hidden can match
another marker's design, which a ring in plain view shows too; the one that fits the design clearly better keeps it
(seeds 10400 and 10900, markers flat, outlet views).
"""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from twin_images import operating_room_scene  # noqa: E402  (tests/: the accuracy study's scenes)

from drillnav.drivers.sim.degradations import Degradations
from drillnav.drivers.sim.scene import make_scene, render_fluoro
from drillnav.registration.fluoro_markers import DUPLICATE_MARGIN_MM, DetectedBB, DetectedMarker, _merge_split_rings, detect_in_view, detect_markers
from drillnav.registration.markers import default_marker_set
from drillnav.registration.transforms import apply

HARD_NO_CT = Degradations.parse("surgeon_markers,low_dose,hardware,collimator,ii_distortion")


@pytest.fixture(scope="module", params=[(3000, 12), (3001, 39)], ids=["cut-by-metal", "small-blob-inside"])
def hard_ap(request):
    seed, marker_id = request.param
    scene = make_scene(seed=seed, views="ap,lateral", render=False, degradations=HARD_NO_CT)
    # The study's generator for this seed and pair (k = 1: ap+lateral), so the image is the study's.
    image = render_fluoro(scene, "ap", np.random.default_rng([seed, 1, 1]))
    return scene, detect_markers(image, scene.marker_set), marker_id


def test_the_marker_formerly_lost_is_identified(hard_ap):
    scene, det, marker_id = hard_ap
    assert marker_id in scene.carm_from_marker
    assert marker_id in det.by_id(), [(r.reason, r.center_px.round()) for r in det.rejected]
    assert not any("found twice" in r.reason for r in det.rejected)


def test_no_wrong_identity_on_the_hard_view(hard_ap):
    scene, det, _ = hard_ap
    view = scene.views["ap"]
    assert len(det.markers) >= 3
    for m in det.markers:
        # The intensifier's distortion moves points by up to 8 px; a wrong identity is a ring ~60 mm away.
        _assert_at_its_true_place(scene, view, m, ring_px=20.0, bb_px=10.0)


def _assert_at_its_true_place(scene, view, m: DetectedMarker, *, ring_px: float, bb_px: float) -> None:
    """The identified marker's ring centre and matched BBs lie where the twin put that marker."""
    truth = view.project(apply(scene.carm_from_marker[m.marker_id], np.zeros((1, 3))))[0]
    assert np.hypot(*(np.asarray(m.ring_ellipse[0]) - truth)) < ring_px, m.marker_id
    bbs = view.project(apply(scene.carm_from_marker[m.marker_id], default_marker_set().by_id(m.marker_id).bb_centers_mm))
    ok = m.bb_index >= 0
    found = np.array([b.center_px for b in m.bbs])[ok]
    assert np.all(np.linalg.norm(found - bbs[m.bb_index[ok]], axis=1) < bb_px), m.marker_id


def _marker(marker_id: int, centres, cost: float) -> DetectedMarker:
    bbs = tuple(DetectedBB(center_px=np.asarray(c, float), diameter_px=8.0, large=False) for c in centres)
    return DetectedMarker(marker_id=marker_id, bbs=bbs, bb_index=np.arange(len(bbs)), ring_ellipse=((0.0, 0.0), (100.0, 90.0), 0.0),
                          mirrored=False, identification_cost_mm=cost)


def test_pieces_sharing_bbs_are_kept_once_and_disjoint_rings_refused():
    shared = [(10, 10), (20, 10), (30, 15), (12, 40)]
    kept, rejected = _merge_split_rings([_marker(7, shared, 0.4), _marker(7, shared[:3], 0.3), _marker(8, shared, 0.2)])
    assert sorted(m.marker_id for m in kept) == [7, 8] and not rejected
    assert next(m for m in kept if m.marker_id == 7).identification_cost_mm == 0.3
    far = [(500 + x, 500 + y) for x, y in shared]
    kept, rejected = _merge_split_rings([_marker(7, shared, 0.4), _marker(7, far, 0.3)])
    assert kept == [] and len(rejected) == 2 and all("found twice" in r.reason for r in rejected)


def test_of_two_rings_claiming_one_id_the_one_fitting_it_clearly_better_is_kept():
    shared = [(10, 10), (20, 10), (30, 15), (12, 40)]
    far = [(500 + x, 500 + y) for x, y in shared]
    kept, rejected = _merge_split_rings([_marker(7, far, 0.8), _marker(7, shared, 0.2)])
    assert [m.identification_cost_mm for m in kept] == [0.2]
    assert len(rejected) == 1 and "fits it better (0.20 against 0.80 mm)" in rejected[0].reason
    just = 0.2 + DUPLICATE_MARGIN_MM - 0.01
    kept, rejected = _merge_split_rings([_marker(7, far, just), _marker(7, shared, 0.2)])
    assert kept == [] and len(rejected) == 2


@pytest.mark.parametrize("seed, true_id, other_id", [(10400, 6, 22), (10900, 6, 42)])
def test_a_ring_misread_as_a_marker_another_ring_shows_leaves_the_true_one(seed, true_id, other_id):
    """The accuracy study's outlet view with the markers flat on the skin (``--marker-tilt 0,10``): marker
    ``other_id``'s ring, partly hidden, matches marker ``true_id``'s design at 0.81-0.86 mm, and the true ring of
    ``true_id`` matches it at 0.05-0.23 mm. Both were rejected as one id found twice; the true one is kept now, at its
    true place, and the other named as beaten."""
    scene, k = operating_room_scene(seed, "inlet+outlet", marker_tilt_deg=(0.0, 10.0))
    rng = np.random.default_rng([seed, k, 1])
    images = {n: render_fluoro(scene, n, rng) for n in scene.views}  # in the study's order: the rng is shared
    view = scene.views["outlet"]
    det = detect_in_view(images["outlet"], view, scene.marker_set)
    assert true_id in det.by_id(), [r.reason for r in det.rejected]
    _assert_at_its_true_place(scene, view, det.by_id()[true_id], ring_px=20.0, bb_px=10.0)
    beaten = [r for r in det.rejected if r.reason.startswith(f"marker id {true_id} found twice; the ring at")]
    assert len(beaten) == 1
    other = view.project(apply(scene.carm_from_marker[other_id], np.zeros((1, 3))))[0]
    assert np.hypot(*(beaten[0].center_px - other)) < 30.0


@pytest.mark.parametrize("seed", [3000, 3001])
def test_a_marker_whose_central_bb_is_hidden_is_identified_from_its_ring_centre(seed):
    """Dense bone, a K-wire or the dose can hide a marker's central BB (with the real CT as the patient, the
    study's seeds 6101 and 6102 each lost one marker that way in the AP view). The ring's centre stands in for it: every
    marker of the view whose central BB is painted over with the background around it is still identified, at its
    true place, with the central BB missing from its matched BBs."""
    scene = make_scene(seed=seed, views="ap,lateral", render=False)
    view = scene.views["ap"]
    image = render_fluoro(scene, "ap", np.random.default_rng([seed, 1, 1]))
    before = detect_markers(image, scene.marker_set)
    assert len(before.markers) >= 3
    hidden = image.copy()
    rows, cols = np.mgrid[: image.shape[0], : image.shape[1]]
    for m in before.markers:
        centre = view.project(apply(scene.carm_from_marker[m.marker_id], np.zeros((1, 3))))[0]
        r = np.hypot(cols - centre[0], rows - centre[1])
        ring = (r > 9.0) & (r < 13.0)
        hidden[r <= 7.0] = np.median(image[ring])  # the 2 mm central BB is ~4 px across here: painted with margin
    after = detect_markers(hidden, scene.marker_set)
    assert {m.marker_id for m in after.markers} == {m.marker_id for m in before.markers}, [r.reason for r in after.rejected]
    for m in after.markers:
        assert 0 not in m.bb_index.tolist(), m.marker_id  # no blob taken for the hidden central BB
        _assert_at_its_true_place(scene, view, m, ring_px=5.0, bb_px=3.0)
