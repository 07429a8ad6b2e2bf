"""A tag cut by the frame's edge, whose code names it dictionary-wide, of a marker fluoroscopy identified but did not pose.

On the operating-room twin (seed 28402, AP+lateral, the study's first drill pose: every degradation, the real CT) the
camera read no whole tag: tags 19 and 20 were cut by the frame's top edge, tag 46 glared and gloved. Fluoroscopy posed
markers 15, 45 and 46; marker 20 was identified in the lateral view alone and its fit there did not converge. Tag 46,
named among the posed markers on its outline, stood alone (its code read only in part), so the frame was refused.
Tag 20's cells, in the frame, identify it dictionary-wide; named as well (``pipeline._registration_with_named_tags``),
the joint solve places marker 20 from the camera and its lateral BBs, and the frame registers on markers 20 and 46.
"""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from twin_images import axis_error_at_entry, study_shot  # noqa: E402  (tests/: the study's shot of a seed, pair and drill pose)

from drillnav.registration.errors import MarkersNotFound  # noqa: E402
from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro  # noqa: E402

SEED, PAIR, POSE = 28402, "ap+lateral", 0


def test_a_tag_named_by_its_code_brings_in_a_marker_fluoroscopy_did_not_pose():
    import accuracy

    scene, poses, carm_from_drill, video, image = study_shot(SEED, PAIR, POSE)

    unposed = next(p for p in poses if p.marker_id == 20)
    assert not unposed.converged and len({id(o[0]) for o in unposed.observations}) == 1
    assert {p.marker_id for p in poses if p.converged} == {15, 45, 46}
    assert not video.markers
    with pytest.raises(MarkersNotFound):
        register_video_to_fluoro(video, poses, scene.marker_set, scene.calibrated_camera, joint=True)

    found, reg = accuracy._register(scene, image, video, poses, joint=True)
    assert set(reg.used_ids) == {20, 46}, reg.used_ids
    tag = next(m for m in found.markers if m.marker_id == 20)
    assert tag.named_among_posed and tag.identified_by_code
    assert float(tag.corners_px.min()) < 0.0  # a corner beyond the frame's edge
    off_mm, off_deg = axis_error_at_entry(scene, carm_from_drill, reg)
    pe = predicted_axis_error(found, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=scene.corridor_entry_carm_mm)
    assert off_mm < 1.5 and off_mm <= pe.position90_mm, (off_mm, pe.position90_mm)
    assert off_deg < 1.0 and pe.reliable
