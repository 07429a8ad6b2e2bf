"""Soak: the twin daemon for --minutes with a shot every 20 s, garbage on every input key once a minute and a camera
calibration installed through REST midway (issue 13 part 7).

Prints axes published against frames captured, the longest gap in the axis stream, frames dropped, the daemon's RSS
at start and end, registrations, thread restarts and events; ends with one JSON line. The twin's camera has no
unplug, so the issue's unplug every 5 minutes is not exercised here.

    .venv/bin/python benchmarks/soak.py --minutes 3
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import httpx
import numpy as np

from drillnav.drivers.sim.scene import make_scene
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from twin_images import board_views  # noqa: E402  (the calibration tests' own board renderer)

TOKEN = "soak-token-1-of-16-chars"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


GARBAGE = {
    "camera_image": [b"\x00\xff garbage", b'{"stamp_ns": 1}', b""],
    "fluoro_shot": [b"\x89PNG garbage", b'{"stamp_ns": 1, "view": "inlet"}', b'{"stamp_ns":1,"view":"x","projection":{},"png16_base64":""}'],
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--shot-every", type=float, default=20.0, help="seconds between twin shots")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="drillnav-soak-"))
    ep, api_port = f"tcp/127.0.0.1:{free_port()}", free_port()
    cfg = work / "drillnav.toml"
    cfg.write_text(f'twin = true\n[zenoh]\nlisten = ["{ep}"]\n[api]\nport = {api_port}\ntoken = "{TOKEN}"\n'
                   f'[dicom]\nwatch_folder = "{work / "in"}"\nscp_port = {free_port()}\n[recording]\nfolder = "{work / "rec"}"\n'
                   f'[calibration]\nfolder = "{work / "cal"}"\n[twin_scene]\nseed = {args.seed}\n')
    base = f"http://127.0.0.1:{api_port}"
    axes: list[tuple[float, int]] = []  # (monotonic arrival, sequence)
    events: list[dict] = []
    frames_on_bus = [0]
    t_start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "drillnav.service.cli", "serve", "--config", str(cfg)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        with open_session(connect=[ep]) as s:
            s.declare_subscriber(key("drillnav", "axis_carm"), lambda smp: axes.append((time.monotonic(), json.loads(smp.payload.to_bytes())["sequence"])))
            s.declare_subscriber(key("drillnav", "events"), lambda smp: events.append(json.loads(smp.payload.to_bytes())))
            s.declare_subscriber(key("drillnav", "camera_image"), lambda smp: frames_on_bus.__setitem__(0, frames_on_bus[0] + 1))
            while not axes:
                if proc.poll() is not None or time.monotonic() - t_start > 600:
                    raise SystemExit(f"the daemon did not stream an axis: rc {proc.poll()}")
                time.sleep(0.2)
            first_axis_s = time.monotonic() - t_start
            print(f"first axis {first_axis_s:.1f} s after start; soaking {args.minutes:g} min", flush=True)
            rss_start = rss_mb(proc.pid)
            st0 = httpx.get(f"{base}/status", timeout=10).json()
            t0 = time.monotonic()
            end = t0 + args.minutes * 60
            views = [v.strip() for v in "inlet,outlet".split(",")]  # the twin's view names (its default [twin_scene] views)
            marks: list[tuple[float, str]] = []  # (monotonic, what the soak did), to place the longest gap
            next_shot, next_garbage, installed = t0 + args.shot_every, t0 + 60.0, []
            installer = threading.Thread(target=lambda: installed.append(install_camera_calibration(base, args.seed)), daemon=True)
            shots = garbage_sent = 0
            while time.monotonic() < end:
                now = time.monotonic()
                if now >= next_shot:
                    r = httpx.post(f"{base}/carm/shots", json={"view": views[shots % len(views)]}, headers=AUTH, timeout=30)
                    r.raise_for_status()
                    marks.append((now, f"shot {views[shots % len(views)]}"))
                    shots += 1
                    next_shot += args.shot_every
                if now >= next_garbage:
                    for topic, payloads in GARBAGE.items():
                        for p in payloads:
                            s.put(key("drillnav", topic), p)
                            garbage_sent += 1
                    marks.append((now, "garbage on every input key"))
                    next_garbage += 60.0
                if not installer.is_alive() and not installed and now >= t0 + (end - t0) / 2 and installer.ident is None:
                    installer.start()  # in a thread: the shots and garbage keep their cadence while the job computes
                    marks.append((now, "calibration job submitted"))
                time.sleep(0.2)
            st = httpx.get(f"{base}/status", timeout=10).json()
            rss_end = rss_mb(proc.pid)
        window = [t for t, _ in axes if t >= t0]
        gaps = np.diff(window) if len(window) > 1 else np.array([float("inf")])
        seqs = [q for t, q in axes if t >= t0]
        worst = int(np.argmax(gaps)) if len(window) > 1 else 0
        gap_at = window[worst] if window else t0
        before = [f"{what} {gap_at - t:.1f} s before" for t, what in marks if 0 <= gap_at - t < 5.0]
        result = {
            "minutes": args.minutes, "first_axis_s": round(first_axis_s, 1),
            "frames_captured": st["frames_received"] - st0["frames_received"], "frames_on_bus_seen": frames_on_bus[0],
            "axes_published": st["axes_published"] - st0["axes_published"], "axes_received": len(window),
            "axis_sequence_gaps": int(sum(b - a - 1 for a, b in zip(seqs, seqs[1:]) if b > a + 1)),
            "longest_axis_gap_ms": round(float(gaps.max()) * 1000, 1), "axis_gap_p99_ms": round(float(np.percentile(gaps, 99)) * 1000, 1),
            "longest_gap_at_s": round(gap_at - t0, 1), "longest_gap_after": before, "gaps_over_200ms": int(np.sum(gaps > 0.2)),
            "frames_dropped": st["frames_dropped"] - st0["frames_dropped"],
            "rss_mb_start": round(rss_start, 1), "rss_mb_end": round(rss_end, 1), "rss_growth_pct": round(100 * (rss_end / rss_start - 1), 1),
            "shots_sent": shots, "shots": {k: st["shots"][k] - st0["shots"][k] for k in st["shots"]}, "registrations": st["registrations"] - st0["registrations"],
            "registration_failures": st["registration_failures"], "garbage_sent": garbage_sent, "bad_messages": st["bad_messages"],
            "thread_restarts": st["thread_restarts"], "loop_errors": st["loop_errors"], "events": len(events),
            "error_events": sum(e["level"] == "error" for e in events), "calibration_installed": installed[0] if installed else "not finished",
            "state_at_end": st["state"],
        }
        for k, v in result.items():
            print(f"  {k:24s} {v}")
        print(json.dumps(result), flush=True)
        return 0
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def install_camera_calibration(base: str, seed: int) -> str:
    """A camera calibration job on board views through the twin's true camera, uploaded and installed through REST."""
    scene = make_scene(seed=seed, render=False)
    views = board_views(scene.true_camera, 10, seed=seed)
    files = [("files", (f"v{i}.png", cv2.imencode(".png", v)[1].tobytes(), "image/png")) for i, v in enumerate(views)]
    r = httpx.post(f"{base}/calibration/jobs", data={"kind": "camera", "board": "checkerboard:9x6:25mm"}, files=files, headers=AUTH, timeout=60)
    r.raise_for_status()
    url = f"{base}/calibration/jobs/{r.json()['id']}"
    deadline = time.monotonic() + 120
    while (job := httpx.get(url, timeout=10).json())["state"] not in ("succeeded", "failed", "cancelled") and time.monotonic() < deadline:
        time.sleep(0.5)
    if job["state"] != "succeeded":
        return f"job {job['state']}: {job['message']}"
    r = httpx.post(url + "/install", headers=AUTH, timeout=30)
    return f"{job['message']} -> {r.status_code}"


if __name__ == "__main__":
    sys.exit(main())
