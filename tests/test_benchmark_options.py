"""The benchmarks' command lines: a setting they cannot use is refused by name before any scene is made."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


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
