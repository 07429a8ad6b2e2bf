"""A tag the camera missed, of a marker whose fit over two views did not converge, looked for where the open mirror puts it.

On the operating-room twin (seed 27002, inlet+outlet, the study's first drill pose: every degradation, the real CT)
the camera read only marker 3's tag; fluoroscopy posed marker 3 in the outlet view alone, its mirror open, and the
registration on it was 47 deg off, the mirror within 1 deg. Marker 7 was identified in both views but its fit over them
did not converge (1.9 px), so its gloved tag was looked for only where the registration put it: out of the frame.
The axis came out 107 mm and 47 deg off (flagged, under a 135 mm bound). The recovery now looks for such tags where
either solution puts them, as it does for the converged markers' tags (``pipeline._recover_predicted``).
"""

import sys
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from twin_images import axis_error_at_entry, study_shot  # noqa: E402  (tests/: the study's shot of a seed, pair and drill pose)

from drillnav.registration.video_fluoro import predicted_axis_error, register_video_to_fluoro  # noqa: E402

SEED, PAIR, POSE = 27002, "inlet+outlet", 0


def test_an_unconverged_markers_tag_is_recovered_where_the_mirror_puts_it():
    import accuracy

    scene, poses, carm_from_drill, video, image = study_shot(SEED, PAIR, POSE)

    def off_mm(reg) -> float:
        return axis_error_at_entry(scene, carm_from_drill, reg)[0]

    unconverged = next(p for p in poses if p.marker_id == 7)
    assert not unconverged.converged and len({id(o[0]) for o in unconverged.observations}) == 2
    first = register_video_to_fluoro(video, poses, scene.marker_set, scene.calibrated_camera, joint=True)
    assert first.used_ids == (3,) and first.mirror_carm_from_drill is not None
    assert off_mm(first) > 50.0

    found, reg = accuracy._register(scene, image, video, poses, joint=True)
    assert next(m for m in found.markers if m.marker_id == 7).recovered
    assert set(reg.used_ids) == {3, 7}, reg.used_ids
    pe = predicted_axis_error(found, poses, reg, scene.calibrated_axis_drill, working_point_carm_mm=scene.corridor_entry_carm_mm)
    assert off_mm(reg) < 2.5 and off_mm(reg) <= pe.position90_mm, (off_mm(reg), pe.position90_mm)
    assert pe.reliable
