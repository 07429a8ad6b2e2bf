"""One intensifier view: the constellation's mirror image may not fit better than the truth by bending the image
into a barrel (``joint_solve.BARREL_SHARE``).

An image intensifier's input screen is curved and its output flat: its radial distortion is pincushion (outward at
the edge), never barrel. Twin seed 23702, markers stuck flat (``accuracy.py --marker-tilt 0,10``), the random
pair's first view alone, the first drill pose: two markers nearly in one plane, so in one view the pair has the
planar ambiguity of a single marker. Held by a prior symmetric about zero, the mirror image's solve took a barrel
distortion (-7.7 px at the field's corner; the truth's solve +12.2, the twin's intensifier +8) and fitted better
than the truth (chi-square 10.7 against 40.7): the axis came out 76.7 mm / 36.6 deg off under a 6.1 mm / 3.0 deg
bound (flagged, the bound over its limit, but a bound that did not reach the error).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from twin_images import one_view_registration  # noqa: E402  (tests/: the study's registration of one view)


def test_the_mirror_image_of_a_flat_pair_takes_no_barrel_distortion():
    scene, view, reg, pe, off_mm, off_deg = one_view_registration(23702, "random", 0, marker_tilt_deg=(0.0, 10.0))
    assert scene.views[view].distortion_sigma_px > 0  # an intensifier's view: its distortion is estimated
    # 76.7 mm under a 6.1 mm bound with the symmetric prior.
    assert off_mm <= pe.position90_mm and off_deg <= pe.angle90_deg, (off_mm, off_deg, pe)
    assert off_mm < 5.0, off_mm
    for _, coefficients in reg.detector_distortion_px:
        assert coefficients[0] > -2.0, reg.detector_distortion_px  # no barrel beyond the prior's 1 px sigma
