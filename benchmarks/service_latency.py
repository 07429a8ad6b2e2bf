"""The daemon on the twin: frame-capture-stamp to published-axis latency, drops, CPU, memory, recorder throughput.

Reference: 96.2 ms per frame (10 frames/s) for the video loop (Vagdargi et al. 2021, Table 4);
issue bar: p99 <= 40 ms at 30 frames/s with no dropped frames.
Run: .venv/bin/python benchmarks/service_latency.py [--seconds 60] [--ct] [--shot-every 10]
"""

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session


def tree(pid: int) -> list[int]:
    """The daemon and its worker processes (the live CT registration runs in one)."""
    try:
        kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return [pid]
    return [pid] + [q for k in kids for q in tree(int(k))]


def rss_mb(pid: int) -> float:
    total = 0.0
    for p in tree(pid):
        for line in Path(f"/proc/{p}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                total += int(line.split()[1]) / 1024
    return total


def cpu_s(pid: int) -> float:
    total = 0.0
    for p in tree(pid):
        f = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        total += (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    return total


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--ct", action="store_true", help="with the live video-CT mode on (the twin's 2 mm CT re-registered after each shot)")
    ap.add_argument("--shot-every", type=float, default=0.0, help="a new twin C-arm shot every this many seconds during the run (0: none)")
    ap.add_argument("--warmup", type=float, default=90.0,
                    help="seconds after the first axis before measuring: the twin renders its camera loop as it streams during its "
                         "first minute (about one core), a load a real camera does not add (0: measure from the first axis)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        ep = "tcp/127.0.0.1:17490"
        (d / "c.toml").write_text(f'twin = true\n[zenoh]\nlisten = ["{ep}"]\n[api]\nport = 18090\ntoken = "bench-token-of-16-chars"\n[dicom]\nwatch_folder = "{d / "in"}"\n[recording]\nfolder = "{d / "rec"}"\n' + ("[twin_scene]\nct_voxel_mm = 2.0\n" if args.ct else ""))
        proc = subprocess.Popen([sys.executable, "-m", "drillnav.service.cli", "serve", "--config", str(d / "c.toml")], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        lat, rss = [], []
        try:
            with open_session(connect=[ep]) as s:
                s.declare_subscriber(key("drillnav", "axis_carm"), lambda smp: lat.append(time.time_ns() - msg.decode_json(smp.payload.to_bytes())["source_frame_stamp_ns"]))
                t0 = time.monotonic()
                while not lat and time.monotonic() - t0 < 120:
                    time.sleep(0.2)
                time.sleep(args.warmup)
                lat.clear()
                status0 = httpx.get("http://127.0.0.1:18090/status", timeout=5).json()
                cpu0, t_start = cpu_s(proc.pid), time.monotonic()
                views, shots, next_shot = ["inlet", "outlet"], 0, args.shot_every
                while time.monotonic() - t_start < args.seconds:
                    time.sleep(1.0)
                    rss.append(rss_mb(proc.pid))
                    if args.shot_every and time.monotonic() - t_start >= next_shot:
                        # As a new fluoroscopy view arrives while drilling: re-registration while frames stream.
                        r = httpx.post("http://127.0.0.1:18090/carm/shots", json={"view": views[shots % 2]}, headers={"Authorization": "Bearer bench-token-of-16-chars"}, timeout=30)
                        r.raise_for_status()
                        shots, next_shot = shots + 1, next_shot + args.shot_every
                cpu1, t_end = cpu_s(proc.pid), time.monotonic()
                status1 = httpx.get("http://127.0.0.1:18090/status", timeout=5).json()
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
        rec_bytes = sum(p.stat().st_size for p in (d / "rec").glob("*.mcap"))
    lat_ms = np.array(lat) / 1e6
    frames = status1["frames_received"] - status0["frames_received"]
    dropped = status1["frames_dropped"] - status0["frames_dropped"]
    report("service_latency", [
        figure("frame-to-axis latency p50", float(np.percentile(lat_ms, 50)), "ms", 96.2),
        figure("frame-to-axis latency p99", float(np.percentile(lat_ms, 99)), "ms", 96.2),
        figure("axis rate", len(lat_ms) / (t_end - t_start), "Hz", 10.0, lower_is_better=False),
        figure("frames dropped", float(dropped), "n", None),
        figure("frames received", float(frames), "n", None),
        figure("registrations during the run", float(status1["registrations"] - status0["registrations"]), "n", None),
        figure("daemon CPU (with workers)", (cpu1 - cpu0) / (t_end - t_start) * 100, "%", None),
        figure("daemon RSS start (with workers)", rss[0], "MB", None),
        figure("daemon RSS end (with workers)", rss[-1], "MB", None),
        figure("recorder throughput", rec_bytes / 1e6 / (t_end - t_start), "MB/s", None),
    ], seconds=args.seconds, live_ct=args.ct, shot_every_s=args.shot_every, note="end-to-end through zenoh on loopback, latency measured by a separate subscriber; 2-core machine")


if __name__ == "__main__":
    main()
