"""The marker set: geometry constraints, code uniqueness under rotation and mirror, identification."""

import numpy as np
import pytest

from drillnav.registration import markers as mk

MS = mk.default_marker_set()


def test_48_markers_with_the_papers_dimensions():
    assert MS.ids == tuple(range(48))
    for m in MS.markers:
        assert m.aruco_id == m.marker_id and m.aruco_dictionary == "DICT_6X6_250"
        assert m.tag_size_mm == 30.0 and np.allclose(m.tag_center_mm, [0, 0, 2.0])
        assert m.ring_radius_mm * 2 == 48.0 and m.ring_wire_diameter_mm == 0.8
        assert m.bbs[0].diameter_mm == 2.0 and np.allclose(m.bbs[0].center_mm, 0)
        assert {b.diameter_mm for b in m.bbs[1:]} <= {2.0, 3.5}


def test_every_bb_collinear_with_two_others_and_clear_of_ring():
    for m in MS.markers:
        c = m.bb_centers_mm[:, :2]
        for i in range(1, len(c)):
            partners = 0
            for j in range(len(c)):
                if j != i:
                    cross = c[i, 0] * c[j, 1] - c[i, 1] * c[j, 0]  # collinear with the centre
                    partners += abs(cross) < 1e-9
            assert partners >= 2, f"marker {m.marker_id} BB {i} is on a line with fewer than 3 BBs"
        assert np.linalg.norm(c, axis=1).max() + 3.5 / 2 <= m.ring_radius_mm - 4.0


def test_codes_unique_under_rotation_and_mirror():
    codes = [np.array(m.code) for m in MS.markers]
    worst = min(mk.code_distance(a, b) for i, a in enumerate(codes) for b in codes[i + 1:])
    assert worst >= mk.MIN_CODE_DISTANCE
    for a in codes:  # no marker looks like itself turned or flipped: orientation is unambiguous
        assert mk._self_distance(a) >= mk.MIN_CODE_DISTANCE


@pytest.mark.parametrize("marker_id", [0, 13, 29, 47])
@pytest.mark.parametrize("mirrored", [False, True])
def test_identify_rotated_noisy_with_a_missing_bb(marker_id, mirrored):
    rng = np.random.default_rng(marker_id)
    m = MS.by_id(marker_id)
    a = rng.uniform(0, 2 * np.pi)
    xy = m.bb_centers_mm[:, :2] * ([1, -1] if mirrored else [1, 1])
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    obs = xy @ rot.T + rng.normal(scale=0.4, size=xy.shape)
    keep = np.ones(len(obs), bool)
    keep[-1] = False
    got = mk.identify(obs[keep], m.bb_diameters_mm[keep], MS)
    assert got.marker_id == marker_id and got.mirrored == mirrored
    assert np.all(got.bb_index[: keep.sum()] == np.arange(keep.sum()))


@pytest.mark.parametrize(("marker_id", "minor_error"), [(3, 1.25), (36, 1.25), (18, 0.8)])
def test_a_flat_ring_is_identified_when_measured_as_the_image_shows_it(marker_id, minor_error):
    # A marker 81 deg to the beam: its pattern is squeezed to cos(81 deg) = 0.16 across. Rectified through an ellipse
    # whose minor axis is 25 % too long (or 20 % too short: a thick wire on a thin ellipse) the BBs land off their
    # design across it, and the image's noise (0.15 mm per axis at the marker) is stretched sixfold: no marker, or
    # two, match. Measured as the image shows them (identify's ``metric``), the marker is found.
    rng = np.random.default_rng(marker_id)
    m = MS.by_id(marker_id)
    a, squeeze = rng.uniform(0, 2 * np.pi), np.cos(np.radians(81.0))
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    image = (m.bb_centers_mm[:, :2] @ rot.T) * [1.0, squeeze] + rng.normal(scale=0.15, size=(len(m.bbs), 2))
    fitted = squeeze * minor_error
    rectified = image / [1.0, fitted]
    with pytest.raises(mk.MarkerNotIdentified):
        mk.identify(rectified, m.bb_diameters_mm, MS)
    got = mk.identify(rectified, m.bb_diameters_mm, MS, metric=(1.0, fitted))
    assert got.marker_id == marker_id and not got.mirrored
    assert np.array_equal(got.bb_index, np.arange(len(m.bbs)))


def test_identify_refuses_garbage():
    rng = np.random.default_rng(3)
    with pytest.raises(mk.MarkerNotIdentified):
        mk.identify(rng.uniform(-20, 20, size=(7, 2)), np.full(7, 2.0), MS)
    with pytest.raises(mk.MarkerNotIdentified, match="at least 3"):
        mk.identify(np.zeros((2, 2)), np.full(2, 2.0), MS)


def test_unknown_id_names_the_range():
    with pytest.raises(mk.UnknownMarker, match="0-47"):
        MS.by_id(99)


def test_manufacturing_error_moves_bbs():
    m = MS.by_id(1)
    made = m.with_bb_errors(np.random.default_rng(0), 0.1)
    d = np.linalg.norm(made.bb_centers_mm - m.bb_centers_mm, axis=1)
    assert 0 < d.mean() < 0.5
