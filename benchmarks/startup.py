"""Start-up: seconds from ``drillnav serve --twin`` to the first published drill axis, and CLI import times.

The daemon runs as a subprocess (config in a temp dir, ports the OS hands out);
a zenoh subscriber of our own times the first message on the axis topic. Two
starts: numba's cache empty (cold, ``NUMBA_CACHE_DIR`` a new folder) and then
filled by the first (warm). The CLI figures are the wall time of
``drillnav <command> --help`` and its import time (``python -X importtime``,
the sum over every module imported).

``--devices``: the daemon on its real drivers instead (no ``--twin``): the
OpenCV webcam driver on an MJPG file of twin frames (what it opens as it opens
/dev/videoN; no V4L2 device needed), the calibrations and marker set as files,
and the DICOM intake receiving a C-STORE of the twin's two shots, sent as soon
as the SCP accepts connections. Timed: start to the first frame on the bus,
start to the shots stored, first frame to the first axis, start to the first
axis.

Issue bars (issue 13): first axis at most 10 s after ``drillnav serve --twin`` on
an idle 2-core machine; with real devices, from start to the first axis after
the first frame at most 3 s; the CLI well under a second. The reference
(Vagdargi et al. 2021) gives no start-up figure.
Run: .venv/bin/python benchmarks/startup.py [--starts 2] [--ct] [--devices] [--timeout 180]
"""

import argparse
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _daemon import daemon_config, stop  # noqa: E402
from _report import figure, report  # noqa: E402

from drillnav.schemas.topics import key  # noqa: E402
from drillnav.service.bus import open_session  # noqa: E402

BAR_FIRST_AXIS_S = 10.0
BAR_DEVICES_S = 3.0
TOKEN = "startup-bench-token-16"
CLI_COMMANDS = ([], ["markers"], ["sim"], ["register"], ["calibrate"], ["serve"], ["listen"], ["replay"])


def drillnav_command() -> list[str]:
    """The ``drillnav`` console script beside this interpreter, else the module."""
    script = Path(sys.executable).with_name("drillnav")
    return [str(script)] if script.exists() else [sys.executable, "-m", "drillnav.service.cli"]


def cpu_s(pid: int) -> float:
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def first_axis(folder: Path, numba_cache: Path, *, ct: bool, timeout_s: float) -> dict:
    """One start of the twin daemon: seconds to the first axis, CPU spent by then, and its progress lines, timed."""
    conf, ep, _, _ = daemon_config(folder, token=TOKEN, top="twin = true\n", **({"twin_scene": "ct_voxel_mm = 2.0"} if ct else {}))
    got = threading.Event()
    lines: list[tuple[float, str]] = []
    env = {**os.environ, "NUMBA_CACHE_DIR": str(numba_cache), "PYTHONUNBUFFERED": "1"}
    with open_session(connect=[ep]) as session:
        session.declare_subscriber(key("drillnav", "axis_carm"), lambda _sample: got.set())
        t0 = time.monotonic()
        proc = subprocess.Popen([*drillnav_command(), "serve", "--twin", "--config", str(conf)], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env=env, cwd=folder)
        try:
            def read_lines() -> None:
                for line in proc.stdout:
                    lines.append((time.monotonic() - t0, line.rstrip()))

            reader = threading.Thread(target=read_lines, daemon=True)
            reader.start()
            while not got.wait(0.05):
                if proc.poll() is not None:
                    raise RuntimeError(f"the daemon exited ({proc.returncode}) before the first axis: {[l for _, l in lines][-5:]}")
                if time.monotonic() - t0 > timeout_s:
                    raise RuntimeError(f"no axis within {timeout_s:.0f} s: {[l for _, l in lines][-5:]}")
            seconds = time.monotonic() - t0
            cpu = cpu_s(proc.pid)
        finally:
            stop(proc)
    return {"seconds": seconds, "cpu_s": cpu, "lines": [(t, l) for t, l in lines if t <= seconds]}


def device_files(folder: Path, *, seed: int, frames: int) -> dict[str, Path]:
    """A twin scene as real devices see it: ``sim scene``'s calibrations, marker set and XA shots, and an MJPG file of
    ``frames`` camera frames along a freehand path (the webcam driver opens it as it opens /dev/videoN)."""
    import cv2
    import numpy as np

    from drillnav.drivers.sim.devices import freehand_loop
    from drillnav.drivers.sim.scene import make_scene
    from drillnav.service.cli_sim import write_scene

    scene = make_scene(seed=seed)
    folder.mkdir(parents=True, exist_ok=True)
    write_scene(scene, folder)
    rng = np.random.default_rng(seed)
    images = [scene.render_camera(rng, carm_from_drill=pose) for pose in freehand_loop(scene, rng, loop_frames=frames, keyposes=3)]
    video = folder / "video0.avi"
    h, w = images[0].shape[:2]
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (w, h))
    for image in images:
        writer.write(image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    return {"video": video, "camera": folder / "camera.json", "drill": folder / "drill.json", "markers": folder / "markers.json",
            "shots": sorted((folder / "fluoro").glob("*.dcm"))}


def devices_start(folder: Path, files: dict, *, timeout_s: float) -> dict:
    """One start on the real drivers; the shots go by C-STORE as soon as the SCP accepts. Seconds from the start."""
    from drillnav.drivers.dicom_scp import send_files

    conf, ep, _, dicom_port = daemon_config(
        folder, token=TOKEN, top=f'markers_file = "{files["markers"]}"\n',
        camera=f'device = "{files["video"]}"\ncalibration = "{files["camera"]}"\ndrill_calibration = "{files["drill"]}"')
    first: dict[str, float] = {}
    lines: list[tuple[float, str]] = []

    def mark(what: str) -> None:
        first.setdefault(what, time.monotonic() - t0)

    def send_shots() -> None:
        while proc.poll() is None and time.monotonic() - t0 < timeout_s:
            try:
                with socket.create_connection(("127.0.0.1", dicom_port), timeout=1):
                    break
            except OSError:
                time.sleep(0.02)
        mark("scp_up")
        first["statuses"] = send_files(host="127.0.0.1", port=dicom_port, called_ae="DRILLNAV", paths=files["shots"], calling_ae="CARM")
        mark("shots_stored")

    with open_session(connect=[ep]) as session:
        session.declare_subscriber(key("drillnav", "axis_carm"), lambda _sample: mark("axis"))
        session.declare_subscriber(key("drillnav", "camera_image"), lambda _sample: mark("frame"))
        t0 = time.monotonic()
        proc = subprocess.Popen([*drillnav_command(), "serve", "--config", str(conf)], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}, cwd=folder)
        try:
            def read_lines() -> None:
                for line in proc.stdout:
                    lines.append((time.monotonic() - t0, line.rstrip()))

            threading.Thread(target=read_lines, daemon=True).start()
            sender = threading.Thread(target=send_shots, daemon=True)
            sender.start()
            while "axis" not in first:
                if proc.poll() is not None:
                    raise RuntimeError(f"the daemon exited ({proc.returncode}) before the first axis: {[l for _, l in lines][-5:]}")
                if time.monotonic() - t0 > timeout_s:
                    raise RuntimeError(f"no axis within {timeout_s:.0f} s: {[l for _, l in lines][-5:]}; so far {first}")
                time.sleep(0.01)
            sender.join(timeout=10)
        finally:
            stop(proc)
    return {**first, "lines": [(t, l) for t, l in lines if t <= first["axis"]]}


def cli_times(argv: list[str]) -> tuple[float, float]:
    """(wall s of ``drillnav *argv --help``, its import time in s from ``-X importtime``)."""
    t0 = time.monotonic()
    subprocess.run([*drillnav_command(), *argv, "--help"], capture_output=True, check=True, timeout=120)
    wall = time.monotonic() - t0
    probe = f"from drillnav.service.cli import main\ntry:\n    main({[*argv, '--help']!r})\nexcept SystemExit:\n    pass\n"
    out = subprocess.run([sys.executable, "-X", "importtime", "-c", probe], capture_output=True, text=True, check=True, timeout=120)
    us = sum(int(m.group(1)) for m in re.finditer(r"^import time:\s+(\d+) \|", out.stderr, re.M))
    return wall, us / 1e6


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--starts", type=int, default=2, help="daemon starts: the first with an empty numba cache, the rest warm")
    ap.add_argument("--ct", action="store_true", help="with the twin's live video-CT mode (2 mm CT; numba's DRR kernel in use)")
    ap.add_argument("--timeout", type=float, default=180.0, help="give up on a start after this many seconds")
    ap.add_argument("--devices", action="store_true", help="start on the real drivers (a webcam file, a DICOM C-STORE) instead of the twin")
    ap.add_argument("--seed", type=int, default=0, help="--devices: the twin scene the device files are made from")
    args = ap.parse_args()
    load = os.getloadavg()[0]
    if args.devices:
        return main_devices(args, load)
    figures = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        numba_cache = d / "numba-cache"
        runs = []
        for n in range(args.starts):
            folder = d / f"start{n}"
            folder.mkdir()
            run = first_axis(folder, numba_cache, ct=args.ct, timeout_s=args.timeout)
            shutil.rmtree(folder, ignore_errors=True)
            label = "cold" if n == 0 else "warm"
            print(f"start {n + 1} ({label} numba cache): first axis after {run['seconds']:.2f} s, daemon CPU {run['cpu_s']:.2f} s")
            for t, line in run["lines"]:
                print(f"  {t:6.2f} s  {line}")
            runs.append(run)
            figures.append(figure(f"first axis, {label} numba cache" + (f" (start {n + 1})" if n > 1 else ""), run["seconds"], "s", BAR_FIRST_AXIS_S))
            figures.append(figure(f"daemon CPU to first axis, {label}" + (f" (start {n + 1})" if n > 1 else ""), run["cpu_s"], "s", None))
    for argv in CLI_COMMANDS:
        wall, imports = cli_times(argv)
        name = " ".join(["drillnav", *argv, "--help"])
        figures.append(figure(f"{name} wall", wall, "s", 1.0))
        figures.append(figure(f"{name} imports", imports, "s", 1.0))
    report("startup", figures, load_before=load, live_ct=args.ct,
           note="reference column: the issue's bars (10 s to the first axis on an idle 2-core machine; CLI under 1 s); "
                "the reference paper gives no start-up figure. Load average before the run in load_before.")


def main_devices(args: argparse.Namespace, load: float) -> None:
    figures = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        t = time.monotonic()
        files = device_files(d / "devices", seed=args.seed, frames=15)
        print(f"device files (scene, calibrations, 15 camera frames, {len(files['shots'])} XA shots) made in {time.monotonic() - t:.1f} s")
        for n in range(args.starts):
            folder = d / f"start{n}"
            folder.mkdir()
            run = devices_start(folder, files, timeout_s=args.timeout)
            shutil.rmtree(folder, ignore_errors=True)
            after_frame = run["axis"] - run["frame"]
            print(f"start {n + 1} on real drivers: first frame {run['frame']:.2f} s, shots stored {run['shots_stored']:.2f} s "
                  f"(C-STORE statuses {run['statuses']}), first axis {run['axis']:.2f} s = {after_frame:.2f} s after the first frame")
            for t, line in run["lines"]:
                print(f"  {t:6.2f} s  {line}")
            suffix = f" (start {n + 1})" if n else ""
            figures.append(figure("devices: first frame after start" + suffix, run["frame"], "s", None))
            figures.append(figure("devices: shots stored (C-STORE) after start" + suffix, run["shots_stored"], "s", None))
            figures.append(figure("devices: first axis after the first frame" + suffix, after_frame, "s", BAR_DEVICES_S))
            figures.append(figure("devices: first axis after start" + suffix, run["axis"], "s", None))
    report("startup_devices", figures, load_before=load,
           note="real drivers: the OpenCV webcam driver on an MJPG file of twin frames, the DICOM SCP receiving the twin's "
                "two XA shots by C-STORE once it accepts; reference column: the issue's 3 s bar from the first frame to the "
                "first axis. Load average before the run in load_before.")


if __name__ == "__main__":
    main()
