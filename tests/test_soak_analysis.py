"""The soak's judgement of an axis stream: gaps inside unplug windows set apart, garbage bursts judged on the second
after them (benchmarks/soak.py; the soak itself runs for 30 minutes, outside the suite)."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from soak import GARBAGE_WINDOW_S, garbage_gaps_s, gaps_s, longest_outside, rss_growth_pct  # noqa: E402


def stream(*, period_s: float, until_s: float, holes: list[tuple[float, float]]) -> list[float]:
    """Arrival times every ``period_s`` up to ``until_s``, none inside each (start, end) of ``holes``."""
    n = int(until_s / period_s)
    return [k * period_s for k in range(n) if not any(a < k * period_s < b for a, b in holes)]


def test_an_unplug_window_is_set_apart_and_a_stall_outside_it_is_not():
    arrivals = stream(period_s=0.05, until_s=60.0, holes=[(10.0, 14.0), (30.0, 30.4)])  # an unplug, then a 0.4 s stall
    gaps = gaps_s(arrivals)
    longest, at = longest_outside(gaps, windows=[(10.02, 14.5)])  # lost event just after the last axis; first axis after
    assert longest == pytest.approx(0.4, abs=0.06) and at == pytest.approx(30.0, abs=0.06)
    longest, _ = longest_outside(gaps, windows=[])
    assert longest == pytest.approx(4.0, abs=0.06)  # the unplug itself, when nothing sets it apart


def test_a_garbage_burst_is_judged_on_the_second_after_it_unless_it_met_an_unplug():
    arrivals = stream(period_s=0.033, until_s=60.0, holes=[(20.1, 20.35), (40.0, 43.0)])
    gaps = gaps_s(arrivals)
    each = garbage_gaps_s(gaps, garbage_at=[5.0, 20.0, 41.0], windows=[(40.0, 43.0)])
    assert each[0] == pytest.approx(0.033, abs=0.01)  # nothing happened
    assert each[1] == pytest.approx(0.25, abs=0.04)   # a 250 ms gap within GARBAGE_WINDOW_S of the burst
    assert each[2] is None                            # during the unplug: no axis to judge
    late = garbage_gaps_s(gaps, garbage_at=[20.1 - GARBAGE_WINDOW_S - 0.2], windows=[])
    assert late[0] < 0.1  # a gap that starts after the burst's window is not the burst's


def test_rss_growth_follows_a_trend_not_a_swing():
    swing = [500.0, 620.0, 480.0, 640.0] * 10  # +-15 % within a minute, no trend
    assert abs(rss_growth_pct(swing)) < 5.0
    leak = [s + 3.0 * k for k, s in enumerate(swing)]  # 3 MB per sample on top of the swing
    assert rss_growth_pct(leak) > 15.0
