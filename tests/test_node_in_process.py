"""A camera in the node's process hands it pixels (``take_frame``): each is tracked to the drill's axis, bad pixels are
refused and counted, and the camera key on the bus is no longer the node's input (the daemon's own camera publishes
there for the recorder and the display)."""

import contextlib
import json
import threading
import time
from pathlib import Path

import numpy as np

from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, make_scene
from drillnav.registration.line import Line3D
from drillnav.schemas import messages as msg
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.node import RegistrationNode
from drillnav.service.replay import iter_recording

from conftest import free_endpoint, put_when_matched, wait_for

RECORDING = Path(__file__).resolve().parents[1] / "recordings" / "twin-seed21.mcap"


def register_both_views(pub, prefix, node, shots):
    """Both recorded views registered."""
    put_when_matched(pub, key(prefix, "fluoro_shot"), shots)
    if not wait_for(lambda: len(node.status().views) == len(shots), 60):
        raise AssertionError(f"the node did not register both views: {node.status()}")


def _why(node: RegistrationNode) -> str:
    """The status fields that say why a frame gave no axis (pytest shortens a whole Status past them)."""
    st = node.status()
    return (f"state {st.state!r}, registration {st.registration_id} of views {st.views}, frames received / processed / dropped "
            f"{st.frames_received} / {st.frames_processed} / {st.frames_dropped}, axes {st.axes_published}, last error {st.last_error!r}, "
            f"loop errors {st.loop_errors}")


def test_frames_handed_in_process_are_tracked_and_bad_pixels_refused():
    scene = make_scene(seed=21, render=False)
    recorded = list(iter_recording(RECORDING))
    shots = [data for topic, _, data in recorded if topic.endswith("fluoro/shot")]
    jpegs = [data for topic, _, data in recorded if topic.endswith("camera/image")][:6]
    truth = {(d := msg.decode_json(data))["frame_stamp_ns"]: Line3D(**d["drill_axis_carm"]) for topic, _, data in recorded if topic.endswith("twin/truth")}
    ep = free_endpoint()
    axes: list[dict] = []
    events: list[dict] = []
    lock = threading.Lock()

    def on_sample(sample):
        with lock:
            if str(sample.key_expr).endswith("/axis/carm"):
                axes.append(json.loads(sample.payload.to_bytes()))
            elif str(sample.key_expr).endswith("/registration/events"):
                events.append(json.loads(sample.payload.to_bytes()))

    with open_session(listen=[ep]) as pub, open_session(connect=[ep]) as node_session:
        sub = pub.declare_subscriber("drillnav/**", on_sample)
        try:
            with RegistrationNode(session=node_session, prefix="drillnav", marker_set=scene.marker_set, camera=scene.calibrated_camera,
                                  axis_drill=scene.calibrated_axis_drill, camera_on_bus=False) as node:
                register_both_views(pub, "drillnav", node, shots)

                # The camera key on the bus: not the node's input in this mode (a frame there is neither taken nor counted).
                pub.put(key("drillnav", "camera_image"), jpegs[0])
                time.sleep(0.3)
                assert node.counters.frames_received == 0

                # Pixels as a camera in this process hands them: every one tracked (paced, so none waits behind another).
                decoded = [msg.decode_compressed_image(d) for d in jpegs]
                for image, stamp, _ in decoded:
                    node.take_frame(image, stamp)
                    assert wait_for(lambda s=stamp: any(a["source_frame_stamp_ns"] == s for a in list(axes)), 10), _why(node)
                assert node.counters.frames_received == len(decoded)

                # Each axis is the drill's: within the replay test's bounds of the recorded truth at the corridor entry.
                entry = scene.corridor_entry_carm_mm
                for _, stamp, _ in decoded:
                    a = next(x for x in axes if x["source_frame_stamp_ns"] == stamp)
                    est, true = Line3D(point_mm=a["point_mm"], direction=a["direction"]), truth[stamp]
                    assert np.linalg.norm(est.closest_point(entry) - true.closest_point(entry)) < 2.0 and est.angle_deg(true) < 1.5

                # Pixels that are not an image: refused, named, counted; the stream goes on.
                before = node.counters.axes_published
                node.take_frame(np.zeros((720, 1280), np.float32), 1)
                node.take_frame("not an image", 2)
                assert node.counters.bad_messages.get("drillnav/camera/image") == 2
                image, stamp, _ = decoded[0]
                node.take_frame(image, stamp + 10**9)
                assert wait_for(lambda: node.counters.axes_published > before, 10)
                assert wait_for(lambda: any("camera frame: expected" in e.get("message", "") for e in list(events)), 5), events
        finally:
            sub.undeclare()


@contextlib.contextmanager
def node_and_axes(scene):
    """A node on a real zenoh bus (its camera in this process) and the axes it publishes: yields (publisher session, node, axes)."""
    ep = free_endpoint()
    axes: list[dict] = []
    with open_session(listen=[ep]) as pub, open_session(connect=[ep]) as node_session:
        sub = pub.declare_subscriber(key("drillnav", "axis_carm"), lambda s: axes.append(json.loads(s.payload.to_bytes())))
        try:
            with RegistrationNode(session=node_session, prefix="drillnav", marker_set=scene.marker_set, camera=scene.calibrated_camera,
                                  axis_drill=scene.calibrated_axis_drill, camera_on_bus=False) as node:
                yield pub, node, axes
        finally:
            sub.undeclare()


def test_the_status_names_a_view_only_once_frames_are_tracked_against_it(monkeypatch):
    """A shot is held before its registration is done: the status's ``views`` wait for the registration, so a client
    that hands frames once the status names both views gets an axis for each (a frame with no registration yet gives none)."""
    import drillnav.service.node as node_module

    scene = make_scene(seed=21, render=False)
    recorded = list(iter_recording(RECORDING))
    shots = [data for topic, _, data in recorded if topic.endswith("fluoro/shot")]
    image, stamp, _ = msg.decode_compressed_image(next(data for topic, _, data in recorded if topic.endswith("camera/image")))
    registering = threading.Event()

    def slow_register(*args, **kwargs):
        registering.set()
        time.sleep(1.5)  # a loaded machine: the shots are held well before their registration is done
        return register_markers(*args, **kwargs)

    register_markers = node_module.register_markers
    monkeypatch.setattr(node_module, "register_markers", slow_register)
    with node_and_axes(scene) as (pub, node, axes):
        put_when_matched(pub, key("drillnav", "fluoro_shot"), shots)
        assert registering.wait(30), _why(node)
        assert len(node.shots) >= 1 and node.status().views == (), _why(node)  # held, not yet registered: not named
        assert wait_for(lambda: len(node.status().views) == len(shots), 30), _why(node)
        node.take_frame(image, stamp)
        assert wait_for(lambda: any(a["source_frame_stamp_ns"] == stamp for a in list(axes)), 10), _why(node)


def test_an_intensifier_views_distortion_rides_on_every_axis():
    """Shots from an image intensifier (the twin's ``ii_distortion``: the views say so): the joint solve estimates
    each view's distortion, and every axis carries it by view name, the first frame's (joint-solved) and the
    frames tracked on its refinement alike, so a display draws the axis where that intensifier shows it."""
    from drillnav.drivers.sim.degradations import Degradations
    from drillnav.drivers.sim.scene import render_fluoro

    scene = make_scene(seed=23, render=False, degradations=Degradations(ii_distortion=True))
    rng = np.random.default_rng(23)
    assert all(v.distortion_sigma_px > 0 for v in scene.views.values())
    shots = [msg.FluoroShot.build(render_fluoro(scene, name, rng), view, stamp_ns=time.time_ns(), view_name=name).to_bytes()
             for name, view in scene.views.items()]
    carm_from_drill = scene.drill_pose_towards(rng)
    image = scene.render_camera(rng, carm_from_drill=carm_from_drill)
    with node_and_axes(scene) as (pub, node, axes):
        register_both_views(pub, "drillnav", node, shots)
        stamp0 = time.time_ns()
        for n in range(3):  # 33 ms apart in capture time: the first joint-solved, the others tracked on its refinement
            node.take_frame(image, stamp0 + n * 33_000_000)
            assert wait_for(lambda s=stamp0 + n * 33_000_000: any(a["source_frame_stamp_ns"] == s for a in list(axes)), 20), _why(node)
    first, *tracked = [next(a for a in axes if a["source_frame_stamp_ns"] == stamp0 + n * 33_000_000) for n in range(3)]
    assert set(first["detector_distortion_px"]) == set(scene.views), first["detector_distortion_px"]
    for a in tracked:
        assert a["detector_distortion_px"] == first["detector_distortion_px"]
    # The estimate is the intensifier's: the twin's pincushion at the field's corner (8 px; seeded: 8.1 and 8.4 px).
    pincushion = np.array([k[0] for k in first["detector_distortion_px"].values()])
    assert np.all(np.abs(pincushion - scene.degradations.ii_pincushion_px) < 3.0), first["detector_distortion_px"]


def test_a_view_whose_markers_all_wait_on_the_camera_registers_and_its_frames_give_axes(monkeypatch):
    """A view the detector leaves with no marker identified, one ring matched only loosely (tests/loose_scene.py; the
    node's detector is handed those detections): the node registers the view, its poses waiting on the camera,
    publishes no loose match as a marker, and a frame whose camera sees the three tags gets its axis, the camera's
    constellation bearing the loose match out."""
    import drillnav.service.node as node_module

    from loose_scene import VIEW, loose_shot

    scene, bare, ring_id, others, image, carm_from_drill = loose_shot()
    monkeypatch.setattr(node_module, "detect_in_view", lambda *args, **kwargs: bare)
    shot = msg.FluoroShot.build(scene.fluoro_log[VIEW], scene.views[VIEW], stamp_ns=time.time_ns(), view_name=VIEW)
    published: list[dict] = []
    with node_and_axes(scene) as (pub, node, axes):
        sub = pub.declare_subscriber(key("drillnav", "fluoro_markers"), lambda s: published.append(json.loads(s.payload.to_bytes())))
        try:
            put_when_matched(pub, key("drillnav", "fluoro_shot"), [shot.to_bytes()])
            assert wait_for(lambda: node.status().views == (VIEW,), 30), _why(node)
            assert wait_for(lambda: bool(published), 5), _why(node)
            assert published[-1]["markers"] == [], published[-1]  # the loose match is a hypothesis, not a marker's pose
            stamp = time.time_ns()
            node.take_frame(image, stamp)
            assert wait_for(lambda: any(a["source_frame_stamp_ns"] == stamp for a in list(axes)), 20), _why(node)
        finally:
            sub.undeclare()
    axis = next(a for a in axes if a["source_frame_stamp_ns"] == stamp)
    assert sorted(axis["markers_used"]) == sorted(scene.carm_from_marker), axis["markers_used"]
    drawn = Line3D(point_mm=np.array(axis["point_mm"]), direction=np.array(axis["direction"]))
    truth = TRUE_DRILL_AXIS_CAMERA.transformed(carm_from_drill)
    entry = scene.corridor_entry_carm_mm
    assert np.linalg.norm(drawn.closest_point(entry) - truth.closest_point(entry)) < 2.0 and drawn.angle_deg(truth) < 1.0
