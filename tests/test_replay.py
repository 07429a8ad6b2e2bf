"""Replay the reference recording through the registration node (real zenoh) and check the axis against the recorded truth."""

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.line import Line3D
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from conftest import free_endpoint
from drillnav.service.cli import main
from drillnav.service.node import RegistrationNode
from drillnav.service.replay import RecordingUnreadable, iter_recording, replay

RECORDING = Path(__file__).resolve().parents[1] / "recordings" / "twin-seed21.mcap"


def test_recording_holds_the_streams():
    topics = {}
    for topic, _, _ in iter_recording(RECORDING):
        topics[topic] = topics.get(topic, 0) + 1
    assert topics == {"drillnav/fluoro/shot": 2, "drillnav/camera/image": 20, "drillnav/twin/truth": 20}


def test_replay_through_the_node_matches_truth():
    scene = make_scene(seed=21, render=False)  # the product's inputs: marker design, calibrations with error
    truth, axes = {}, []
    ep = free_endpoint()
    with open_session(listen=[ep]) as player, open_session(connect=[ep]) as node_session:
        with RegistrationNode(session=node_session, prefix="drillnav", marker_set=scene.marker_set, camera=scene.calibrated_camera, axis_drill=scene.calibrated_axis_drill) as node:
            node_session.declare_subscriber(key("drillnav", "axis_carm"), lambda s: axes.append(msg.decode_json(s.payload.to_bytes())))
            node_session.declare_subscriber(key("drillnav", "twin_truth"), lambda s: truth.__setitem__((d := msg.decode_json(s.payload.to_bytes()))["frame_stamp_ns"], d))
            time.sleep(0.5)
            n = replay(RECORDING, player, rate=1.0)
            time.sleep(1.0)
    assert n == 42
    matched = [(a, truth[a["source_frame_stamp_ns"]]) for a in axes if a["source_frame_stamp_ns"] in truth]
    assert len(matched) >= 15, f"only {len(matched)} axes matched a recorded frame (status {node.status()})"
    entry = scene.corridor_entry_carm_mm
    errs = []
    for a, t in matched:
        est = Line3D(point_mm=a["point_mm"], direction=a["direction"])
        true = Line3D(point_mm=t["drill_axis_carm"]["point_mm"], direction=t["drill_axis_carm"]["direction"])
        errs.append((np.linalg.norm(est.closest_point(entry) - true.closest_point(entry)), est.angle_deg(true)))
    errs = np.array(errs)
    assert np.median(errs[:, 0]) < 2.0 and np.median(errs[:, 1]) < 1.5


def test_replay_cli_and_bad_file(tmp_path, capsys):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    assert main(["replay", str(bad), "--wait", "0"]) == 1
    assert "not a readable MCAP" in capsys.readouterr().err
    assert main(["replay", str(tmp_path / "none.mcap"), "--wait", "0"]) == 1
    assert "no such file" in capsys.readouterr().err
    with pytest.raises(ValueError, match="rate"):
        replay(RECORDING, None, rate=0)
