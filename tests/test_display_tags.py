"""The camera preview's tags: the node publishes each frame's detections on camera/markers, and the display hub
sends as previews frames the node tracked, each with its own tags (real zenoh, the real node, the reference recording)."""

import asyncio
import base64
import json
import threading
import time

import cv2
import numpy as np

from drillnav.drivers.sim.scene import make_scene
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.display_hub import DisplayHub
from drillnav.service.node import RegistrationNode
from drillnav.service.replay import iter_recording
from conftest import free_endpoint
from twin_replay import RECORDING, play_at_camera_rate


def test_each_frames_tags_are_published_and_the_hub_sends_those_of_its_previews():
    scene = make_scene(seed=21, render=False)
    frame_stamps = {msg.decode_compressed_image(d)[1] for t, _, d in iter_recording(RECORDING) if t.endswith("camera/image")}
    tags: list[msg.VideoMarkers] = []
    axes: dict[int, dict] = {}
    sent: list[dict] = []
    ep = free_endpoint()
    with open_session(listen=[ep]) as player, open_session(connect=[ep]) as node_session:
        with (RegistrationNode(session=node_session, prefix="drillnav", marker_set=scene.marker_set, camera=scene.calibrated_camera,
                               axis_drill=scene.calibrated_axis_drill) as node,
              DisplayHub(session=node_session, prefix="drillnav", camera_preview_hz=5.0) as hub):
            node_session.declare_subscriber(key("drillnav", "camera_markers"), lambda s: tags.append(msg.VideoMarkers.from_bytes(s.payload.to_bytes())))
            node_session.declare_subscriber(key("drillnav", "axis_carm"), lambda s: axes.__setitem__((a := msg.decode_json(s.payload.to_bytes()))["source_frame_stamp_ns"], a))
            stop = threading.Event()

            async def browser() -> None:  # what the WebSocket route does with the hub, without the socket
                client = hub.attach()
                try:
                    while not stop.is_set():
                        try:
                            sent.extend(json.loads(t) for t in await asyncio.wait_for(client.next_batch(), 0.2))
                        except TimeoutError:
                            pass
                finally:
                    hub.detach(client)

            reader = threading.Thread(target=asyncio.run, args=(browser(),), daemon=True)
            reader.start()
            try:
                node.joint.wait_ready()
                n = play_at_camera_rate(player, node, fps=15.0)  # ~1.3 s of frames: previews at 5 Hz
                deadline = time.monotonic() + 5
                while len(tags) < n - node.counters.frames_dropped and time.monotonic() < deadline:
                    time.sleep(0.05)
                time.sleep(0.3)
            finally:
                stop.set()
                reader.join(5)
    # The node: one message per frame it tracked, stamped with that frame's capture stamp, the markers of its axis.
    assert len(tags) >= 10 and {t.stamp_ns for t in tags} <= frame_stamps, len(tags)
    for t in tags:
        assert t.image_size == (scene.calibrated_camera.width, scene.calibrated_camera.height)
        ids = sorted(m.id for m in t.markers)
        assert set(ids) <= set(scene.marker_set.ids) and len(ids) >= 3
        if t.stamp_ns in axes:
            assert set(axes[t.stamp_ns]["markers_used"]) <= set(ids)
        for m in t.markers:
            xs, ys = zip(*m.corners_px)
            assert 0 <= min(xs) and max(xs) < t.image_size[0] and 0 <= min(ys) and max(ys) < t.image_size[1]
    # The hub: while the node tracks, each preview is a frame it tracked, sent with that frame's tags, a few per second.
    previews = [m for m in sent if m["type"] == "camera"]
    tagged = [m for m in previews if m["tags"] is not None]
    by_stamp = {t.stamp_ns: t for t in tags}
    assert len(tagged) >= 2 and len(previews) < len(tags), (len(tagged), len(previews), len(tags))
    for m in tagged:
        assert m["tags"]["stamp_ns"] == m["stamp_ns"] and m["stamp_ns"] in by_stamp
        assert [t["id"] for t in m["tags"]["markers"]] == [t.id for t in by_stamp[m["stamp_ns"]].markers]
    assert not any(m["type"] == "tags" for m in sent)  # no stream of tags apart from their pictures
    # A preview is a quarter of the frame's width (the page shows it 320 px wide), a JPEG of the same picture.
    for m in previews:
        small = cv2.imdecode(np.frombuffer(base64.b64decode(m["data_base64"]), np.uint8), cv2.IMREAD_GRAYSCALE)
        assert m["format"] == "jpeg" and small.shape == (scene.calibrated_camera.height // 4, scene.calibrated_camera.width // 4)
    frame = next(d for t, _, d in iter_recording(RECORDING) if t.endswith("camera/image") and msg.decode_compressed_image(d)[1] == previews[0]["stamp_ns"])
    full = msg.decode_compressed_image(frame)[0]
    full = full if full.ndim == 2 else cv2.cvtColor(full, cv2.COLOR_BGR2GRAY)
    small = cv2.imdecode(np.frombuffer(base64.b64decode(previews[0]["data_base64"]), np.uint8), cv2.IMREAD_GRAYSCALE)
    assert np.abs(cv2.resize(full, small.shape[::-1], interpolation=cv2.INTER_AREA).astype(float) - small).mean() < 4.0
