"""The CLI's overlays and CT mosaic: the full trajectory across the image, cone, legend, title and verdict."""

from __future__ import annotations

import numpy as np
import pytest

from drillnav.registration.carm import CArmView, intensifier_shift_px
from drillnav.registration.ct_views import PlannedTrajectory, compose_views, render_ct_views
from drillnav.registration.line import Line3D
from drillnav.registration.overlay import ALARM_BGR, AXIS_BGR, OK_BGR, annotate, axis_curve_px, draw_axis, line_across_image
from drillnav.registration.volume import Volume
from drillnav.service.display_hub import ct_for_display

VIEW = CArmView.from_positioner(primary_deg=20, secondary_deg=-10, source_to_detector_mm=1164.0, source_to_isocenter_mm=624.0,
                                pixel_spacing_mm=(0.304, 0.304), rows=976, columns=976)


def _distance(points, a, b):
    d = (b - a) / np.linalg.norm(b - a)
    r = np.atleast_2d(points) - a
    return np.abs(r[:, 0] * d[1] - r[:, 1] * d[0])


@pytest.mark.parametrize("direction", [(0.3, 0.2, 0.93), (1.0, 0.05, 0.0), (0.0, 0.0, 1.0), (-0.5, 0.7, -0.2)])
def test_axis_runs_across_the_whole_image_on_its_projection(direction):
    axis = Line3D(point_mm=np.array([3.0, -5.0, 8.0]), direction=np.array(direction))
    a, b = VIEW.project(np.vstack([axis.point_mm, axis.point_mm + 100 * axis.direction]))
    seg = line_across_image(VIEW, axis)
    assert seg is not None
    p, q = seg
    assert _distance(np.vstack(seg), a, b).max() < 1e-6
    for x, y in seg:  # both ends on the border
        assert min(abs(x + 0.5), abs(x - 975.5), abs(y + 0.5), abs(y - 975.5)) < 1e-6
    assert (q - p) @ (b - a) > 0  # ordered the way the drill advances
    img = draw_axis(np.full((976, 976, 3), 60, np.uint8), VIEW, axis, cone_half_angle_deg=1.0, position_error_mm=1.0)
    ys, xs = np.nonzero(np.all(np.abs(img.astype(int) - AXIS_BGR) < 12, axis=2))
    pts = np.stack([xs, ys], axis=1).astype(float)
    assert _distance(pts, a, b).max() < 13.0  # the line (4 px wide); only the arrowhead reaches further
    c = pts.mean(axis=0)
    u = np.linalg.svd(pts - c)[2][0]
    assert _distance(np.vstack([c - 500 * u, c + 500 * u]), a, b).max() < 1.0  # the drawn line's fit lies on the projection
    span = np.ptp(np.stack([xs, ys], axis=1) @ ((q - p) / np.linalg.norm(q - p)))
    assert span > 0.9 * np.linalg.norm(q - p), f"drawn {span:.0f} px of {np.linalg.norm(q - p):.0f}"


def test_an_intensifier_view_draws_the_axis_bent_as_its_image_shows_it():
    """With a view's estimated distortion the drawn axis follows the distorted image of the line (within 2 px
    along all of it, ends on the border), not the ideal projection it leaves by the distortion's size near the border."""
    axis = Line3D(point_mm=np.array([40.0, -35.0, 8.0]), direction=np.array([0.6, 0.3, 0.74]))  # off the centre: bent most
    k = np.array([14.0, -8.0])  # pincushion, S at the field's corner, px: an uncorrected intensifier
    curve = axis_curve_px(VIEW, axis, k)
    ideal = np.vstack(line_across_image(VIEW, axis))
    assert curve.shape[0] > 20
    for x, y in curve[[0, -1]]:  # both ends on the border
        assert min(abs(x + 0.5), abs(x - 975.5), abs(y + 0.5), abs(y - 975.5)) < 1e-6
    assert (curve[-1] - curve[0]) @ (ideal[1] - ideal[0]) > 0  # ordered the way the drill advances
    # Every curve point is the distortion of a point of the ideal line.
    t = np.linspace(-0.2, 1.2, 4001)[:, None]
    line = ideal[0] + t * (ideal[1] - ideal[0])
    bent_line = line + intensifier_shift_px(line, VIEW.center_px, VIEW.corner_radius_px, k)
    assert np.min(np.linalg.norm(curve[:, None] - bent_line[None], axis=2), axis=1).max() < 0.5
    img = draw_axis(np.full((976, 976, 3), 60, np.uint8), VIEW, axis, cone_half_angle_deg=1.0, position_error_mm=1.0, distortion_px=k)
    ys, xs = np.nonzero(np.all(np.abs(img.astype(int) - AXIS_BGR) < 12, axis=2))
    pts = np.stack([xs, ys], axis=1).astype(float)
    to_bent = np.min(np.linalg.norm(pts[:, None] - bent_line[None, ::4], axis=2), axis=1)
    body = pts[np.linalg.norm(pts - curve[-1], axis=1) > 50]  # leaving out the arrowhead (16-40 px from the end, 12 px either side)
    assert np.min(np.linalg.norm(body[:, None] - bent_line[None, ::4], axis=2), axis=1).max() < 4.0  # the line is 4 px wide
    # Where the bent line is over 6 px from the ideal one, the drawing follows the bent line.
    far = bent_line[::4][_distance(bent_line[::4], *ideal) > 6.0]
    assert len(far) > 20
    there = body[np.min(np.linalg.norm(body[:, None] - far[None], axis=2), axis=1) < 3.0]
    off_bent = np.min(np.linalg.norm(there[:, None] - bent_line[None, ::4], axis=2), axis=1).mean()
    off_ideal = _distance(there, *ideal).mean()
    assert off_bent < 2.0 and off_ideal > 4.0, f"drawn {off_bent:.1f} px from the bent line, {off_ideal:.1f} px from the ideal one"
    assert to_bent.size > 0.9 * 4 * np.linalg.norm(curve[-1] - curve[0])  # drawn across the whole image


def test_axis_missing_the_image_draws_no_line():
    axis = Line3D(point_mm=np.array([0.0, 0.0, 400.0]), direction=np.array([1.0, 0.0, 0.0]))  # far above the field
    assert line_across_image(VIEW, axis) is None


def test_stale_axis_is_grey_and_title_and_legend_are_drawn():
    axis = Line3D(point_mm=np.zeros(3), direction=np.array([0.3, 0.2, 0.93]))
    img = draw_axis(np.full((976, 976, 3), 60, np.uint8), VIEW, axis, cone_half_angle_deg=1.0, stale=True)
    assert not np.any(np.all(np.abs(img.astype(int) - AXIS_BGR) < 12, axis=2))
    out = annotate(img, view_name="p+20s-10", stamp_ns=1_795_000_000_000_000_000, predicted_error=(1.2, 0.8))
    assert out.shape[0] > img.shape[0] and out.shape[1] == img.shape[1]
    strip = out[: out.shape[0] - img.shape[0]]
    assert (strip > 200).any()  # the title is written
    assert np.all(np.abs(out[-130:, :250].astype(int) - AXIS_BGR) < 12, axis=2).any()  # the legend's axis swatch


def _ct() -> Volume:
    data = np.full((60, 60, 60), -1000.0, np.float32)
    data[15:45, 15:45, 15:45] = 1200.0
    return Volume(data=data, patient_from_voxel=np.array([[2.0, 0, 0, -60], [0, 2.0, 0, -60], [0, 0, 2.0, -60], [0, 0, 0, 1]]))


@pytest.mark.parametrize("breach,colour", [(True, ALARM_BGR), (False, OK_BGR)])
def test_ct_mosaic_carries_the_verdict(breach, colour):
    axis = Line3D(point_mm=np.zeros(3), direction=np.array([0.1, 0.2, 1.0]))
    plan = [PlannedTrajectory(name="T1", entry_mm=np.array([0.0, 0.0, -20.0]), target_mm=np.array([0.0, 5.0, 30.0]), radius_mm=3.0)]
    views = render_ct_views(_ct(), axis_ct=axis, centre_mm=np.zeros(3), cone_half_angle_deg=1.0, plan=plan, size_px=200)
    plain = compose_views(views)
    judged = compose_views(views, verdict={"trajectory": "T1", "breach": breach, "min_clearance_mm": 0.4 if breach else 2.5, "min_clearance_along_mm": 12.0})
    assert judged.shape[0] > plain.shape[0]
    bar = judged[: judged.shape[0] - plain.shape[0]]
    assert (np.all(bar == colour, axis=2)).mean() > 0.5  # a wide bar in the verdict's colour, text on it


def test_ct_for_display_windows_and_strides_the_volume():
    ct = _ct()
    small = ct_for_display(ct, max_voxels_per_axis=32)
    assert small.shape == (30, 30, 30)
    data = np.frombuffer(small.data, np.uint8).reshape(small.shape)
    # Voxel (i, j, k) of the small volume sits where voxel (2i, 2j, 2k) of the CT does.
    assert np.allclose(small.patient_from_voxel @ [5, 6, 7, 1], ct.patient_from_voxel @ [10, 12, 14, 1])
    assert data[15, 15, 15] == int((1200 + 500) / 1800 * 255) and data[2, 2, 2] == 0  # bone window: level 400 HU, width 1800 HU
