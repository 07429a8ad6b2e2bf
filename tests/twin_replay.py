"""The reference twin recording played into a real node at the camera's 30 Hz (shared by the interop tests)."""

import time
from pathlib import Path

from drillnav.service.replay import iter_recording

RECORDING = Path(__file__).resolve().parents[1] / "recordings" / "twin-seed21.mcap"


def play_at_camera_rate(player, node, fps=30.0):
    """The recording's shots, then (once both are registered) its 20 camera frames at ``fps``; returns the frame count.

    The recording's camera ran at 15 Hz and its frames follow the shots by less than a registration takes on a
    loaded machine, so a plain replay would race the registration; this plays what the 30 Hz camera would.
    """
    recorded = list(iter_recording(RECORDING))
    for topic, _, data in recorded:
        if topic.endswith("fluoro/shot"):
            player.put(topic, data)
    deadline = time.monotonic() + 30
    while (len(node.shots) < 2 or node.counters.registrations < 2) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert node.counters.registrations >= 2, f"the node did not register both shots: {node.status()}"
    start = time.monotonic()
    frames = [(t, d) for t, _, d in recorded if t.endswith("camera/image")]
    for i, (topic, data) in enumerate(frames):
        time.sleep(max(0.0, start + i / fps - time.monotonic()))
        player.put(topic, data)
    return len(frames)
