"""The benchmarks' command lines: a setting they cannot use is refused by name before any scene is made."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import accuracy  # noqa: E402


@pytest.mark.parametrize("tilt, why", [("50,10", "marker_tilt_deg must be 0 <= low <= high < 80"), ("5,x", "could not convert")])
def test_live_path_refuses_a_marker_tilt_it_cannot_use(tilt, why):
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "live_path.py"), "--marker-tilt", tilt],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2
    assert "--marker-tilt must be LOW,HIGH deg" in proc.stderr and repr(tilt) in proc.stderr and why in proc.stderr


@pytest.mark.parametrize("args, why", [(["--seeds", "8,x"], "--seeds must be integers separated by commas, got '8,x'"),
                                       (["--repeats", "0"], "--repeats must be at least 1, got 0")])
def test_edge_on_rows_refuses_settings_it_cannot_use(args, why):
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "edge_on_rows.py"), *args], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2
    assert why in proc.stderr, proc.stderr


@pytest.mark.parametrize("args, why", [(["--random-pairs", "40,15"], "--random-pairs must be SEP_LOW,SEP_HIGH[,SECONDARY] deg"),
                                       (["--random-pairs", "15,40,90"], "got '15,40,90'"),
                                       (["--pairs", "random,oblique"], "--pairs takes inlet+outlet, ap+lateral, random, comma-separated; got 'random,oblique'"),
                                       (["--camera-fov", "10"], "--camera-fov must be 20-150 deg, got 10.0"),
                                       (["--source-distances", "600,700"], "--source-distances must be SID,SOD mm with 300 <= SOD < SID <= 2000, got '600,700'")])
def test_accuracy_refuses_view_pairs_and_c_arms_it_cannot_draw(args, why):
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "accuracy.py"), "--quick", "--no-docs", *args],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2
    assert why in proc.stderr, proc.stderr


def _random_angles(views: str) -> list[tuple[float, float]]:
    return [tuple(float(v) for v in view.split(":")) for view in views.split(",")]


def test_close_random_pairs_keep_every_other_pair_and_the_seeds_later_draws():
    """Another random pair's ranges draw as many numbers as the study's own: the other pairs are the same, and so is
    everything the seed's generator draws after them; the pair itself lies within the ranges asked for."""
    close = accuracy.RandomPairs(separation_deg=(15.0, 40.0), secondary_max_deg=40.0)
    seps, secondaries = [], []
    for seed in range(3000, 3040):
        own_rng, close_rng = np.random.default_rng(seed), np.random.default_rng(seed)
        own, other = accuracy._pairs(own_rng), accuracy._pairs(close_rng, close)
        assert {k: v for k, v in own.items() if k != "random"} == {k: v for k, v in other.items() if k != "random"}
        assert own_rng.random() == close_rng.random()
        (a, sa), (b, sb) = _random_angles(other["random"])
        if abs(b) < 120:  # not clipped
            seps.append(abs(b - a))
        secondaries += [abs(sa), abs(sb)]
    # Rounded to whole degrees as the views are named.
    assert 14.5 <= min(seps) and max(seps) <= 40.5 and max(seps) > 30.0
    assert max(secondaries) <= 40.5 and max(secondaries) > 30.0
    assert accuracy._pairs(np.random.default_rng(3000)) == accuracy._pairs(np.random.default_rng(3000), accuracy.RandomPairs())
