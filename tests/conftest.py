"""Shared test plumbing: ports the OS hands out, so two suites on one machine never meet."""

import os
import socket
import sys
from pathlib import Path

import pytest

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `drillnav` sets it (service/cli.py): small matrices, threads only spin

sys.path.insert(0, str(Path(__file__).parent))


_HANDED_OUT: set[int] = set()  # every port free_port gave this process


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bound to 0, read back, released), never one it gave this
    process before: the OS may hand the same port out again once it is released, and a test that draws several (one
    per server, seven daemons at once in test_serve_lifecycle) must not get one twice."""
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port not in _HANDED_OUT:
            _HANDED_OUT.add(port)
            return port


def free_endpoint() -> str:
    """A zenoh TCP endpoint on loopback at a free port."""
    return f"tcp/127.0.0.1:{free_port()}"


def wait_for(cond, timeout_s: float) -> bool:
    """Poll ``cond()`` every 20 ms until it holds or ``timeout_s`` passes; its last value."""
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return bool(cond())


def put_when_matched(session, key_expr: str, payloads, timeout_s: float = 30.0) -> None:
    """Each payload put once on ``key_expr`` as the daemon puts a shot: blocking under congestion (zenoh's default for a
    put drops it when the link is full, and a loaded CI machine lost a megabyte shot that way), and only once a
    subscriber has reached ``session`` (a put before that is lost)."""
    import zenoh

    publisher = session.declare_publisher(key_expr, congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        assert wait_for(lambda: publisher.matching_status.matching, timeout_s), f"no subscriber on {key_expr} reached the publisher"
        for p in payloads:
            publisher.put(p)
    finally:
        publisher.undeclare()


# Modules of pure computation: no server, process, thread, session or browser, and no clock read. `make test` runs
# them on several workers (`pytest -m compute -n ...`), then the rest in one process, where every wall-clock bound a
# test states holds on a 2-core machine. tests/test_suite_split.py checks each module listed here against that.
COMPUTE_MODULES = frozenset({
    "test_aruco_detect.py", "test_bb_shape.py", "test_calibration.py", "test_camera_yaml.py", "test_cli_anatomy.py", "test_cli_ct.py", "test_cli_markers.py",
    "test_cli_register.py", "test_continuity.py", "test_ct_intake.py", "test_ct_registration.py", "test_display_overlays.py",
    "test_few_markers.py", "test_fluoro_candidates.py", "test_fluoro_enhanced.py", "test_loose_rings.py", "test_fluoro_compressed.py", "test_fluoro_hard.py", "test_fluoro_pipeline.py", "test_intensifier.py", "test_intensifier_mirror.py",
    "test_joint_solve.py", "test_kcr.py", "test_marker_as_built.py", "test_marker_pose_views.py", "test_marker_set_video.py", "test_markers.py",
    "test_pki.py", "test_predicted_error.py", "test_unsettled_mirror.py", "test_unposed_named.py", "test_ring_outline.py", "test_xray_shapes.py", "test_real_anatomy_background.py", "test_scene.py", "test_soak_analysis.py", "test_symmetric_pairing.py",
    "test_tag_border.py", "test_tag_detection.py", "test_tag_hypotheses.py", "test_tracked_markers.py", "test_tracking_covariance.py", "test_tag_recovery.py", "test_tag_search.py", "test_tag_square_fit.py", "test_twin_aim.py", "test_twin_degradations.py", "test_twin_detector.py", "test_video_claims.py",
    "test_ring_split.py", "test_lone_marker_mirror.py", "test_tag_misread.py", "test_tag_displaced_corner.py", "test_tag_beam_slide.py",
    "test_named_second_view.py", "test_named_then_recovered.py", "test_named_alone.py", "test_lone_marker_views.py", "test_face_on_mirror.py", "test_two_markers_alone.py", "test_blob_split.py", "test_ring_crowding.py", "test_edge_on_ring.py", "test_edge_on_roll.py",
    "test_cut_corners.py", "test_tag_cover.py", "test_unposed_tag_search.py", "test_claim_ties.py", "test_ring_taken_back.py", "test_edge_corner_sigma.py",
})


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in COMPUTE_MODULES:
            item.add_marker(pytest.mark.compute)
