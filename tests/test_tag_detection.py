"""The drill camera's detector on operating-room frames from the twin (issue 17): tags found, no false ids.

Figures measured with ``benchmarks/tag_detection.py`` (seed 3000, 4 drill poses, 20 visible tags):
``tag_glare`` frames: 16 tags found with ArUco's default errorCorrectionRate 0.6, 17 with 1.0 (the glare spot
flips black cells); clean frames: 20 of 20 both ways. Corner RMS against the twin's true projection, with
cv2.cornerSubPix alone / with the edge-line refinement: clean 0.20 / 0.12 px, motion blur 1.27 / 0.52 px.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from tag_detection import false_ids_without_tags, measure  # noqa: E402


def test_glare_frames_give_up_more_tags_without_false_ids():
    res = measure(seeds=1, poses=4, first_seed=3000, conditions=["none", "tag_glare"])
    clean, glare = res["none"], res["tag_glare"]
    assert clean["visible"] == 20 and clean["found"] == 20, clean
    assert glare["visible"] == 20
    assert glare["found"] >= 17, f"only {glare['found']} of 20 glare-struck tags found (16 before the fix)"
    assert clean["false_ids"] == 0 and glare["false_ids"] == 0
    # Corners of found tags against the twin's true projection (0.12 px measured, 0.19-0.20 with cornerSubPix alone).
    assert glare["corner_rms_px"] < 0.16 and clean["corner_rms_px"] < 0.16, (clean, glare)


def test_corners_stay_put_under_motion_blur():
    blurred = measure(seeds=1, poses=4, first_seed=3000, conditions=["motion_blur"])["motion_blur"]
    assert blurred["found"] == blurred["visible"] == 20
    # 0.52 px measured with the edge-line fit; cornerSubPix alone gave 1.27 px (rounded corners pull it inwards).
    assert blurred["corner_rms_px"] < 0.8, blurred


def test_no_ids_on_a_tag_free_frame_with_every_camera_degradation():
    assert false_ids_without_tags(seeds=1, first_seed=3000) == 0
