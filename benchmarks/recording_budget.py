"""Recording disk budget: GB per hour at 720p30 with the [recording] defaults, beside the old default (every frame as sent).

The twin's drill camera renders 1280x720 frames, published at 30 frames/s at JPEG quality 92 (a camera process
elsewhere; ``drillnav serve``'s own camera encodes once at the recording's quality, which the recorder then keeps as
received: the same bytes on disk as the re-encode measured here); the twin's two C-arm shots go to a live RegistrationNode, which publishes what it does in the
daemon (axes, overlays, marker poses, status, events). Two real Recorders on one zenoh session record the
same bus: one built from the default settings (``Recorder.from_settings``), one keeping every frame as
received (the old default). Issue 14's bar: at most 3 GB per hour at 720p30.
Run: nice -n 10 .venv/bin/python benchmarks/recording_budget.py [--seconds 60]
"""

import argparse
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _report import figure, report  # noqa: E402

from drillnav.drivers.sim.devices import TwinDrillCamera
from drillnav.drivers.sim.scene import make_scene
from drillnav.schemas import messages as msg
from drillnav.schemas.calibration_message import calibration_message_from_models
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.node import RegistrationNode
from drillnav.service.recorder import Recorder
from drillnav.service.replay import RecordingReader
from drillnav.service.settings import RecordingSettings

BAR_GB_PER_HOUR = 3.0
P = "drillnav"


def per_topic(files: list[Path]) -> dict[str, tuple[int, int]]:
    """topic -> (messages, payload bytes), read back with the stream reader."""
    out: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for f in files:
        for m in RecordingReader(f):
            out[m.topic][0] += 1
            out[m.topic][1] += len(m.data)
    return {t: (n, b) for t, (n, b) in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=21)
    args = ap.parse_args()
    scene = make_scene(seed=args.seed)
    camera = TwinDrillCamera(scene=scene, fps=30.0, loop_frames=30, seed=args.seed)
    product = make_scene(seed=args.seed, render=False)  # the node's inputs: calibrations with their error
    defaults = RecordingSettings()
    with tempfile.TemporaryDirectory() as d, open_session() as bus:
        settings = defaults.model_copy(update={"folder": Path(d) / "defaults"})
        node = RegistrationNode(session=bus, prefix=P, marker_set=product.marker_set, camera=product.calibrated_camera, axis_drill=product.calibrated_axis_drill).__enter__()
        new = Recorder.from_settings(settings, session=bus, prefix=P, name="defaults")
        old = Recorder(session=bus, prefix=P, folder=Path(d) / "old", name="old")
        bus.put(key(P, "calibration"), calibration_message_from_models(camera=product.calibrated_camera, axis_drill=product.calibrated_axis_drill,
                                                                       stamp_ns=time.time_ns(), marker_set=product.marker_set, source="twin"))
        for name in scene.views:
            bus.put(key(P, "fluoro_shot"), msg.FluoroShot.build(scene.fluoro_log[name], scene.views[name], stamp_ns=time.time_ns(), view_name=name).to_bytes())
        deadline = time.monotonic() + 60
        while node.counters.registrations < len(scene.views) and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.0)  # the one-off start (calibration, shots: ~3.6 MB) is written; the hour's rate is what follows
        start_bytes = {r.name: r.bytes for r in (new, old)}
        t0 = time.monotonic()
        sent = 0
        with camera as cam:
            while time.monotonic() - t0 < args.seconds:
                frame = cam.read()
                bus.put(key(P, "camera_image"), msg.compressed_image(frame.image, stamp_ns=frame.stamp_ns, frame_id="drill_camera", quality=92))
                sent += 1
        elapsed = time.monotonic() - t0
        node.close()
        new_files, old_files = new.close(), old.close()
        on_disk = {"new": sum(p.stat().st_size for p in new_files), "old": sum(p.stat().st_size for p in old_files)}
        # Steady state: the payload written during the frame window, scaled by the file's overhead (compression, index).
        new_bytes = (new.bytes - start_bytes["defaults"]) * on_disk["new"] / new.bytes
        old_bytes = (old.bytes - start_bytes["old"]) * on_disk["old"] / old.bytes
        topics = per_topic(new_files)
        st = new.status()
    gb_h = new_bytes / elapsed * 3600 / 1e9
    old_gb_h = old_bytes / elapsed * 3600 / 1e9
    print(f"{sent} frames in {elapsed:.1f} s ({sent / elapsed:.1f} frames/s); node: {node.counters.axes_published} axes, {node.counters.frames_dropped} frames dropped")
    print(f"defaults: camera {defaults.camera_fps:g} frames/s at JPEG {defaults.camera_jpeg_quality}; recorder dropped {st.dropped}, frames skipped by design {st.camera_frames_skipped}")
    print(f"files on disk: defaults {on_disk['new'] / 1e6:.1f} MB, old default {on_disk['old'] / 1e6:.1f} MB, each with the one-off start; payload per topic (defaults):")
    for t, (n, b) in sorted(topics.items(), key=lambda kv: -kv[1][1]):
        print(f"  {t:36s} {n:6d} msgs {b / 1e6:9.2f} MB")
    report("recording_budget", [
        figure("recorded, defaults (steady state)", gb_h, "GB/h", BAR_GB_PER_HOUR),
        figure("recorded, old default (every frame as sent)", old_gb_h, "GB/h", BAR_GB_PER_HOUR),
        figure("one-off start per file (calibration, shots)", start_bytes["defaults"] / 1e6, "MB", None),
        figure("camera frames recorded per second", topics.get(key(P, "camera_image"), (0, 0))[0] / elapsed, "1/s", None),
        figure("axes recorded per second", topics.get(key(P, "axis_carm"), (0, 0))[0] / elapsed, "1/s", None),
    ], seconds=round(elapsed, 1), frames_sent=sent, recorder_dropped=st.dropped, bar_gb_per_hour=BAR_GB_PER_HOUR,
        within_bar=gb_h <= BAR_GB_PER_HOUR)


if __name__ == "__main__":
    main()
