"""The reference twin recording played into a real node at the camera's 30 Hz (shared by the interop tests)."""

import time
from pathlib import Path

import zenoh

from drillnav.service.replay import iter_recording

RECORDING = Path(__file__).resolve().parents[1] / "recordings" / "twin-seed21.mcap"


def play_at_camera_rate(player, node, fps=30.0):
    """The recording's shots, then (once both are registered) its 20 camera frames at ``fps``; returns the frame count.

    The recording's camera ran at 15 Hz and its frames follow the shots by less than a registration takes on a
    loaded machine, so a plain replay would race the registration; this plays what the 30 Hz camera would.
    """
    recorded = list(iter_recording(RECORDING))
    # Shots are megabytes: zenoh's default for a put is to drop it when the link is congested, so they block instead.
    publishers = {t: player.declare_publisher(t, congestion_control=zenoh.CongestionControl.BLOCK if t.endswith("fluoro/shot") else zenoh.CongestionControl.DROP)
                  for t, _, _ in recorded if not t.endswith("twin/truth")}
    # A put before the node's subscription has reached the player's session is lost: wait until each key matches.
    deadline = time.monotonic() + 30
    while not all(p.matching_status.matching for p in publishers.values()) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert all(p.matching_status.matching for p in publishers.values()), "the node's subscriptions never reached the player"
    for topic, _, data in recorded:
        if topic.endswith("fluoro/shot"):
            publishers[topic].put(data)
    deadline = time.monotonic() + 60
    # Shots that arrive together may be registered together (one registration from both views): count the shots.
    while (len(node.shots) < 2 or node.status().shots.registered < 2) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert node.status().shots.registered >= 2 and len(node.shots) == 2, f"the node did not register both shots: {node.status()}"
    start = time.monotonic()
    frames = [(t, d) for t, _, d in recorded if t.endswith("camera/image")]
    for i, (topic, data) in enumerate(frames):
        time.sleep(max(0.0, start + i / fps - time.monotonic()))
        taken = node.counters.frames_processed
        publishers[topic].put(data)
        # On a loaded machine (two suites at once) the node may not take a frame within a camera period and would drop
        # the next; the tests that play this look at what each frame gives, not at the rate: wait (bounded) until the
        # node has taken this frame before the next one is due.
        deadline = time.monotonic() + 2.0
        while node.counters.frames_processed == taken and time.monotonic() < deadline:
            time.sleep(0.002)
    for p in publishers.values():
        p.undeclare()
    return len(frames)


def recorded_live_inputs():
    """What the live pipeline works from in the reference recording: (scene, marker poses, calibration, camera frames)."""
    from drillnav.drivers.sim.scene import make_scene
    from drillnav.registration.fluoro_markers import detect_markers
    from drillnav.registration.marker_pose import register_markers
    from drillnav.registration.pipeline import LiveCalibration
    from drillnav.schemas import messages as msg

    scene = make_scene(seed=21, render=False)
    rec = list(iter_recording(RECORDING))
    shots = [msg.FluoroShot.from_bytes(d) for t, _, d in rec if t.endswith("fluoro/shot")]
    dets = [detect_markers(s.image_log, scene.marker_set, pixel_spacing_mm=s.carm_view.pixel_spacing_mm[1]) for s in shots]
    poses = tuple(register_markers(dets, [s.carm_view for s in shots], scene.marker_set))
    cal = LiveCalibration.build(camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill, marker_set=scene.marker_set)
    frames = [msg.decode_compressed_image(d)[0] for t, _, d in rec if t.endswith("camera/image")]
    return scene, poses, cal, frames
