"""schemas.continuity: gaps, late and repeated axes, restarts and registration changes in an axis stream."""

import pytest

from drillnav.schemas.continuity import AxisContinuity, ContinuityEvent as E

T0 = 1_795_563_858_000_000_000
FRAME_NS = 33_333_333


def axis(seq: int, reg: int = 1, *, stamp: int | None = None, ct: int | None = None, stamped: bool = True) -> dict:
    a = {"sequence": seq, "registration_id": reg, "point_mm": [0.0, 0.0, 0.0], "direction": [0.0, 0.0, 1.0]}
    if stamped:
        a["stamp_ns"] = T0 + seq * FRAME_NS if stamp is None else stamp
    if ct is not None:
        a["ct_registration_id"] = ct
    return a


def test_an_unbroken_stream_reports_nothing_and_a_late_joiner_is_no_gap():
    c = AxisContinuity()
    reports = [c.feed(axis(s)) for s in range(1000, 1010)]  # joined a running stream at 1000
    assert all(r.events == () and r.current for r in reports)
    assert c.totals.received == 10 and c.totals.missed == 0
    assert reports[0].describe() == ""


def test_gap_then_the_missing_axes_arrive_late():
    c = AxisContinuity()
    for s in range(5):
        c.feed(axis(s))
    r = c.feed(axis(9))
    assert r.events == (E.GAP,) and r.missed == (5, 8) and r.missed_count == 4 and r.current
    assert r.describe() == "4 axes missed (5-8)"
    assert c.totals.missed == 4
    late = c.feed(axis(6))
    assert late.events == (E.REORDERED,) and not late.current  # older than the axis on screen: not to be drawn
    assert late.describe() == "axis 6 arrived late"
    assert c.totals.missed == 3 and c.totals.reordered == 1
    again = c.feed(axis(6))
    assert again.events == (E.DUPLICATE,) and not again.current
    assert c.feed(axis(10)).events == ()
    one = c.feed(axis(12))
    assert one.missed == (11, 11) and one.describe() == "1 axis missed (11)"


def test_restart_back_to_zero_with_and_without_stamps():
    c = AxisContinuity()
    for s in range(50):
        c.feed(axis(s))
    later = T0 + 10**12
    r = c.feed(axis(0, stamp=later))
    assert r.events == (E.RESTART,) and r.current and c.totals.restarts == 1
    for s in range(1, 40):
        assert c.feed(axis(s, stamp=later + s * FRAME_NS)).events == ()
    # a restart whose first axes were lost: the sequence is lower than the newest, the stamp newer
    r = c.feed(axis(3, stamp=later + 10**11))
    assert r.events == (E.RESTART, E.GAP) and r.missed == (0, 2)
    # without stamps, only a return to 0 says restart; a repeated 0 is a duplicate
    u = AxisContinuity()
    for s in range(5):
        u.feed(axis(s, stamped=False))
    assert u.feed(axis(0, stamped=False)).events == (E.RESTART,)
    assert u.feed(axis(0, stamped=False)).events == (E.DUPLICATE,)
    assert u.feed(axis(2, stamped=False)).events == (E.GAP,)


def test_registration_changes_are_reported_once_and_late_axes_of_the_old_one_do_not_flip_it():
    c = AxisContinuity()
    c.feed(axis(0, reg=1))
    c.feed(axis(1, reg=1))
    r = c.feed(axis(3, reg=2))
    assert r.events == (E.GAP, E.REGISTRATION_CHANGED) and r.previous_registration == (1, None) and r.registration == (2, None)
    assert "registration changed from 1 to 2" in r.describe()
    late = c.feed(axis(2, reg=1))  # the missed axis of registration 1 arrives after the first of 2
    assert late.events == (E.REORDERED,) and not late.current
    assert c.feed(axis(4, reg=2)).events == ()
    assert c.totals.registration_changes == 1
    # the video-CT stream: a new CT registration is a change too
    r = c.feed(axis(5, reg=2, ct=7))
    assert r.events == (E.REGISTRATION_CHANGED,) and r.describe() == "registration changed from 2 to 2 (CT 7)"


def test_a_huge_gap_remembers_only_the_window():
    c = AxisContinuity(window=8)
    c.feed(axis(0))
    r = c.feed(axis(1_000_000))
    assert r.missed_count == 999_999 and c.totals.missed == 999_999
    assert c.feed(axis(999_995)).events == (E.REORDERED,)
    assert c.feed(axis(10)).events == (E.DUPLICATE,)  # beyond the window: cannot tell, not counted as filled
    assert len(c._missing) <= 8


@pytest.mark.parametrize("bad, message", [
    ({"registration_id": 1}, "'sequence' must be an integer, got None"),
    ({"sequence": "3", "registration_id": 1}, "'sequence' must be an integer, got '3'"),
    ({"sequence": 3.0, "registration_id": 1}, "'sequence' must be an integer, got 3.0"),
    ({"sequence": True, "registration_id": 1}, "'sequence' must be an integer, got True"),
    ({"sequence": -1, "registration_id": 1}, "'sequence' must not be negative"),
    ({"sequence": 1}, "'registration_id' must be an integer, got None"),
    ([1, 2], "an axis message is a JSON object"),
])
def test_bad_messages_are_refused_naming_the_field(bad, message):
    c = AxisContinuity()
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        c.feed(bad)
    assert c.totals.received == 0
    with pytest.raises(ValueError, match="window must be at least 1"):
        AxisContinuity(window=0)
