"""Soak: the twin daemon for --minutes with a shot every 20 s, garbage on every input key once a minute, the camera
unplugged every 5 minutes for a few seconds and a camera calibration installed through REST midway (issue 13 part 7).

The unplug is the twin camera's own (``[twin_scene] camera_unplug_every_s``, ``camera_unplug_s``): the device raises
what a V4L2 camera raises and the daemon's reconnection path brings it back; each window is read off the daemon's
events (``camera twin ...`` lost, then back). Prints the longest gap in the axis stream outside the unplug windows
(bar 0.5 s), the longest gap within 1 s after each garbage burst (bar 200 ms), the time from each replug to the first
axis after it, axes published against frames captured, frames dropped, the daemon's RSS at start and end (bar +10 %),
registrations, thread restarts (bar: none left dead, /health 200 at the end) and events; ends with one JSON line.

Unattended: every request has a timeout, a failed request is counted and the soak goes on, the daemon's output goes
to files (never a pipe that fills), and the daemon is stopped in a ``finally`` (SIGTERM, then SIGKILL after 30 s),
on SIGTERM or Ctrl-C of the soak too.

    nice -n 10 .venv/bin/python benchmarks/soak.py --minutes 30
"""

from __future__ import annotations

import argparse
import json
import os
import signal
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
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _daemon import daemon_config, stop  # noqa: E402
from twin_images import board_views  # noqa: E402  (the calibration tests' own board renderer)

TOKEN = "soak-token-1-of-16-chars"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
BAR_GAP_OUTSIDE_UNPLUG_S = 0.5
BAR_GAP_AFTER_GARBAGE_S = 0.2
BAR_RSS_GROWTH_PCT = 10.0
RSS_EVERY_S = 10.0
GARBAGE_WINDOW_S = 1.0  # a garbage burst's gap is the longest one that overlaps this long after it

# Every input key the node decodes (service/node.py subscribes to these two), each with bytes that are not its message.
GARBAGE = {
    "camera_image": [b"\x00\xff garbage", b'{"stamp_ns": 1}', b""],
    "fluoro_shot": [b"\x89PNG garbage", b'{"stamp_ns": 1, "view": "inlet"}', b'{"stamp_ns":1,"view":"x","projection":{},"png16_base64":""}'],
}


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def rss_growth_pct(samples_mb: list[float]) -> float:
    """Growth of the median of the last quarter of the samples over the median of the first quarter, in %.

    The daemon's RSS swings by ~±15 % within a minute (frames in flight, the allocator returning memory), so one
    sample at each end would judge the swing, not a leak; quarter medians follow a trend and ignore the swing.
    """
    if len(samples_mb) < 2:
        return float("nan")
    q = max(1, len(samples_mb) // 4)
    return 100 * (float(np.median(samples_mb[-q:])) / float(np.median(samples_mb[:q])) - 1)


def gaps_s(arrivals: list[float]) -> list[tuple[float, float]]:
    """(start, end) of each interval between consecutive arrivals (monotonic s)."""
    return list(zip(arrivals, arrivals[1:]))


def overlaps(gap: tuple[float, float], lo: float, hi: float) -> bool:
    return gap[0] < hi and gap[1] > lo


def longest_outside(gaps: list[tuple[float, float]], windows: list[tuple[float, float]]) -> tuple[float, float]:
    """(longest gap in s that overlaps none of ``windows``, where it began); (0, nan) when there is none."""
    outside = [g for g in gaps if not any(overlaps(g, lo, hi) for lo, hi in windows)]
    if not outside:
        return 0.0, float("nan")
    g = max(outside, key=lambda g: g[1] - g[0])
    return g[1] - g[0], g[0]


def longest_within(gaps: list[tuple[float, float]], lo: float, hi: float) -> float:
    """The longest gap in s that overlaps [lo, hi]: an axis stream that stopped there shows one at least as long."""
    return max((g[1] - g[0] for g in gaps if overlaps(g, lo, hi)), default=float("inf"))


def garbage_gaps_s(gaps: list[tuple[float, float]], garbage_at: list[float], windows: list[tuple[float, float]]) -> list[float | None]:
    """The longest gap within ``GARBAGE_WINDOW_S`` after each burst; None for a burst that met an unplug (no axis to judge)."""
    out: list[float | None] = []
    for g in garbage_at:
        hit = any(overlaps((g - 0.5, g + GARBAGE_WINDOW_S + 0.5), lo, hi) for lo, hi in windows)
        out.append(None if hit else longest_within(gaps, g, g + GARBAGE_WINDOW_S))
    return out


class Soak:
    """What the soak's own zenoh subscribers see: axis arrivals, events, camera frames (all stamped on arrival)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.axes: list[tuple[float, int]] = []  # (monotonic arrival, wall ns arrival)
        self.events: list[tuple[float, dict]] = []
        self.frames_on_bus = 0

    def on_axis(self, _sample) -> None:
        with self.lock:
            self.axes.append((time.monotonic(), time.time_ns()))

    def on_event(self, sample) -> None:
        try:
            e = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self.lock:
            self.events.append((time.monotonic(), e))

    def on_frame(self, _sample) -> None:
        self.frames_on_bus += 1

    def unplugs(self, camera: str = "camera twin") -> list[dict]:
        """Each unplug from the events: when it was lost (monotonic arrival and the daemon's stamp) and when it was back."""
        out: list[dict] = []
        with self.lock:
            events = list(self.events)
        for t, e in events:
            if e.get("level") == "error" and camera in e.get("message", "") and "unplugged" in e.get("message", ""):
                out.append({"lost": t, "lost_stamp_ns": e["stamp_ns"], "back": None})
            elif e.get("level") == "info" and e.get("message", "") == f"{camera} is back" and out and out[-1]["back"] is None:
                out[-1]["back"] = t
        return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--shot-every", type=float, default=20.0, help="seconds between twin shots")
    ap.add_argument("--garbage-every", type=float, default=60.0, help="seconds between bursts of garbage on every input key")
    ap.add_argument("--unplug-every", type=float, default=300.0, help="seconds between camera unplugs (from the camera's first open)")
    ap.add_argument("--unplug-s", type=float, default=3.0, help="how long each unplug lasts")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--first-axis-timeout", type=float, default=600.0)
    args = ap.parse_args(argv)

    def stop_soak(signum, _frame):  # SIGTERM unwinds like Ctrl-C, so the finally below stops the daemon
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, stop_soak)
    work = Path(tempfile.mkdtemp(prefix="drillnav-soak-"))
    cfg, ep, api_port, _ = daemon_config(work, token=TOKEN, top="twin = true\n", twin_scene=(
        f"seed = {args.seed}\ncamera_unplug_every_s = {args.unplug_every}\ncamera_unplug_s = {args.unplug_s}"))
    base = f"http://127.0.0.1:{api_port}"
    print(f"soak in {work} (daemon output in daemon.out/daemon.err there); load average {os.getloadavg()[0]:.2f}", flush=True)
    seen = Soak()
    t_start = time.monotonic()
    out, err = open(work / "daemon.out", "wb"), open(work / "daemon.err", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "drillnav.service.cli", "serve", "--config", str(cfg)], stdout=out, stderr=err,
                            cwd=work, start_new_session=True)  # its own session: a Ctrl-C of the soak reaches it only through the finally
    failures: list[str] = []
    try:
        with open_session(connect=[ep]) as s, httpx.Client(base_url=base, timeout=30) as client:
            s.declare_subscriber(key("drillnav", "axis_carm"), seen.on_axis)
            s.declare_subscriber(key("drillnav", "events"), seen.on_event)
            s.declare_subscriber(key("drillnav", "camera_image"), seen.on_frame)
            while not seen.axes:
                if proc.poll() is not None or time.monotonic() - t_start > args.first_axis_timeout:
                    tail = (work / "daemon.err").read_text(errors="replace").strip().splitlines()[-3:]
                    raise SystemExit(f"the daemon did not stream an axis (rc {proc.poll()}): {tail}")
                time.sleep(0.2)
            first_axis_s = time.monotonic() - t_start
            # The twin camera keeps the frames of its loop as it renders them (~250 MB at 720p): memory the product
            # does not have. The soak, and its RSS baseline, begin once the loop is whole.
            while (rendered := client.get("/status").json()["twin_camera_rendered"])[0] < rendered[1]:
                if proc.poll() is not None or time.monotonic() - t_start > args.first_axis_timeout:
                    raise SystemExit(f"the twin camera did not render its loop ({rendered}; daemon rc {proc.poll()})")
                time.sleep(1.0)
            warmup_s = time.monotonic() - t_start
            print(f"first axis {first_axis_s:.1f} s after start, the twin's camera loop rendered after {warmup_s:.1f} s; "
                  f"soaking {args.minutes:g} min", flush=True)
            rss_start = rss_mb(proc.pid)
            rss_each_minute: list[float] = []
            rss_samples = [rss_start]  # every RSS_EVERY_S, for the growth figure
            marks: list[tuple[float, str]] = []  # (monotonic, what the soak did): to place the longest gap
            st0 = client.get("/status").json()
            t0 = time.monotonic()
            end = t0 + args.minutes * 60
            views = ["inlet", "outlet"]  # the twin's view names (its default [twin_scene] views)
            garbage_at: list[float] = []
            next_shot, next_garbage, installed = t0 + args.shot_every, t0 + args.garbage_every, []
            installer = threading.Thread(target=lambda: installed.append(install_camera_calibration(base, args.seed)), daemon=True)
            shots = garbage_sent = 0
            next_progress, next_rss = t0 + 60, t0 + RSS_EVERY_S
            while time.monotonic() < end:
                if proc.poll() is not None:
                    raise SystemExit(f"the daemon exited (rc {proc.returncode}) {time.monotonic() - t0:.0f} s into the soak")
                now = time.monotonic()
                if now >= next_shot:
                    view = views[shots % len(views)]
                    try:
                        marks.append((now, f"shot {view}"))
                        client.post("/carm/shots", json={"view": view}, headers=AUTH).raise_for_status()
                        shots += 1
                    except httpx.HTTPError as exc:
                        failures.append(f"shot {view} at {now - t0:.0f} s: {exc}")
                    next_shot += args.shot_every
                if now >= next_garbage:
                    garbage_at.append(time.monotonic())
                    marks.append((garbage_at[-1], "garbage on every input key"))
                    for topic, payloads in GARBAGE.items():
                        for p in payloads:
                            s.put(key("drillnav", topic), p)
                            garbage_sent += 1
                    next_garbage += args.garbage_every
                if installer.ident is None and now >= t0 + (end - t0) / 2:
                    installer.start()  # in a thread: the shots and garbage keep their cadence while the job computes
                    marks.append((now, "calibration job submitted"))
                if now >= next_rss:
                    rss_samples.append(rss_mb(proc.pid))
                    next_rss += RSS_EVERY_S
                if now >= next_progress:
                    with seen.lock:
                        n_axes = len(seen.axes)
                    rss_each_minute.append(round(rss_mb(proc.pid), 1))
                    print(f"  {(now - t0) / 60:4.1f} min: {n_axes} axes, {shots} shots, {len(garbage_at)} garbage bursts, "
                          f"{len(seen.unplugs())} unplugs, RSS {rss_each_minute[-1]:.0f} MB", flush=True)
                    next_progress += 60
                time.sleep(0.1)
            time.sleep(GARBAGE_WINDOW_S)  # the last burst's window
            st = client.get("/status").json()
            health = client.get("/health")
            rss_end = rss_mb(proc.pid)
            rss_samples.append(rss_end)
            installer.join(timeout=1)
        result = summarise(args, seen, t0=t0, first_axis_s=first_axis_s, warmup_s=warmup_s, rss_each_minute=rss_each_minute, st0=st0, st=st, health=health, rss=(rss_start, rss_end), rss_samples=rss_samples, marks=marks,
                           garbage_at=garbage_at, shots=shots, garbage_sent=garbage_sent, installed=installed, failures=failures)
        for k, v in result.items():
            print(f"  {k:34s} {v}")
        print(json.dumps(result), flush=True)
        return 0 if all(result["bars_met"].values()) else 1
    finally:
        stop(proc)
        out.close()
        err.close()


def summarise(args, seen: Soak, *, t0: float, first_axis_s: float, warmup_s: float, rss_each_minute: list[float], st0: dict, st: dict, health: httpx.Response, rss: tuple[float, float],
              rss_samples: list[float], marks: list[tuple[float, str]],
              garbage_at: list[float], shots: int, garbage_sent: int, installed: list[str], failures: list[str]) -> dict:
    with seen.lock:
        axes = [a for a in seen.axes if a[0] >= t0]
        events = [e for t, e in seen.events if t >= t0]
    arrivals = [t for t, _ in axes]
    gaps = gaps_s(arrivals)
    unplugs = [u for u in seen.unplugs() if u["back"] is None or u["back"] >= t0]  # every window that reaches into the soak
    windows, resumes = [], []
    for u in unplugs:
        # The window: from the loss to the first axis after the camera came back (to the end if it never did).
        after = [(t, wall) for t, wall in axes if u["back"] is not None and t > u["back"]]
        windows.append((u["lost"], after[0][0] if after else float("inf")))
        if after:  # the replug happened unplug_s after the failed read the loss event was stamped at
            resumes.append(round((after[0][1] - u["lost_stamp_ns"]) / 1e9 - args.unplug_s, 2))
    outside_s, outside_at = longest_outside(gaps, windows)
    each_garbage = garbage_gaps_s(gaps, garbage_at, windows)
    garbage_gaps = [g for g in each_garbage if g is not None]
    rss_start, rss_end = rss
    growth = rss_growth_pct(rss_samples)
    near = [f"{what} {outside_at - t:.1f} s before" for t, what in marks if 0 <= outside_at - t < 5.0]
    near += [f"camera back {outside_at - u['back']:.1f} s before" for u in unplugs if u["back"] is not None and 0 <= outside_at - u["back"] < 5.0]
    bars = {
        "gap_outside_unplug_le_0.5s": outside_s <= BAR_GAP_OUTSIDE_UNPLUG_S,
        "gap_after_garbage_le_200ms": bool(garbage_gaps) and max(garbage_gaps) <= BAR_GAP_AFTER_GARBAGE_S,
        "rss_growth_le_10pct": growth <= BAR_RSS_GROWTH_PCT,
        "no_thread_left_dead": health.status_code == 200,
        "every_unplug_resumed": len(resumes) == len(unplugs),
    }
    return {
        "minutes": args.minutes, "load_avg_1min_end": round(os.getloadavg()[0], 2), "first_axis_s": round(first_axis_s, 1),
        "twin_loop_rendered_s": round(warmup_s, 1),
        "frames_captured": st["frames_received"] - st0["frames_received"], "frames_on_bus_seen": seen.frames_on_bus,
        "frames_dropped": st["frames_dropped"] - st0["frames_dropped"],
        "axes_published": st["axes_published"] - st0["axes_published"], "axes_received": len(axes),
        "longest_gap_outside_unplugs_ms": round(outside_s * 1000, 1),
        "longest_gap_outside_at_s": None if outside_at != outside_at else round(outside_at - t0, 1),
        "longest_gap_outside_after": near,
        "gaps_over_200ms_outside_unplugs": sum(1 for g in gaps if g[1] - g[0] > 0.2 and not any(overlaps(g, lo, hi) for lo, hi in windows)),
        "garbage_bursts": len(garbage_at), "garbage_sent": garbage_sent,
        "longest_gap_after_garbage_ms": round(max(garbage_gaps) * 1000, 1) if garbage_gaps else None,
        "gap_after_each_garbage_ms": [None if g is None else round(g * 1000) for g in each_garbage],  # None: during an unplug
        "unplugs": len(unplugs), "unplug_windows_s": [round(hi - lo, 2) if hi != float("inf") else "never back" for lo, hi in windows],
        "resume_after_replug_s": resumes,
        "rss_mb_start": round(rss_start, 1), "rss_mb_end": round(rss_end, 1), "rss_growth_pct": round(growth, 1),  # quarter medians: see rss_growth_pct()
        "rss_mb_each_minute": rss_each_minute,
        "shots_sent": shots, "shots": {k: st["shots"][k] - st0["shots"][k] for k in st["shots"]},
        "registrations": st["registrations"] - st0["registrations"], "registration_failures": st["registration_failures"],
        "bad_messages": st["bad_messages"], "thread_restarts": st["thread_restarts"], "loop_errors": st["loop_errors"],
        "events": len(events), "error_events": sum(e.get("level") == "error" for e in events),
        "calibration_installed": installed[0] if installed else "not finished",
        "health_at_end": health.status_code if health.status_code == 200 else f"{health.status_code} {health.text}",
        "state_at_end": st["state"], "soak_request_failures": failures, "bars_met": bars,
    }


def install_camera_calibration(base: str, seed: int) -> str:
    """A camera calibration job on board views through the twin's true camera, uploaded and installed through REST."""
    try:
        scene = make_scene(seed=seed, render=False)
        views = board_views(scene.true_camera, 10, seed=seed)
        files = [("files", (f"v{i}.png", cv2.imencode(".png", v)[1].tobytes(), "image/png")) for i, v in enumerate(views)]
        with httpx.Client(base_url=base, timeout=60) as client:
            r = client.post("/calibration/jobs", data={"kind": "camera", "board": "checkerboard:9x6:25mm"}, files=files, headers=AUTH)
            r.raise_for_status()
            url = f"/calibration/jobs/{r.json()['id']}"
            deadline = time.monotonic() + 300
            while (job := client.get(url).json())["state"] not in ("succeeded", "failed", "cancelled") and time.monotonic() < deadline:
                time.sleep(0.5)
            if job["state"] != "succeeded":
                return f"job {job['state']}: {job['message']}"
            r = client.post(url + "/install", headers=AUTH)
            return f"{job['message']} -> {r.status_code}"
    except (httpx.HTTPError, ValueError) as exc:
        return f"failed: {type(exc).__name__}: {exc}"


if __name__ == "__main__":
    sys.exit(main())
