"""Time to write a 5-marker, 2-view twin scene folder (issue bar: under 10 s on 2 cores).

Run: .venv/bin/python benchmarks/sim_scene.py
"""

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

from drillnav.service.cli import main as cli


def main() -> None:
    times = []
    for seed in range(3):
        with tempfile.TemporaryDirectory() as d:
            t = time.perf_counter()
            assert cli(["sim", "scene", "--seed", str(seed), "--markers", "5", "--views", "inlet,outlet", "--out", d]) == 0
            times.append(time.perf_counter() - t)
    report("sim_scene", [figure("sim scene 5 markers 2 views (median of 3)", sorted(times)[1], "s", 10.0)], note="reference is the issue's bar, not the paper")


if __name__ == "__main__":
    main()
