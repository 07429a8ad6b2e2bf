"""A signal that interrupts the node's start-up, even inside a thread's start(), unwinds it cleanly.

The CLI's SIGTERM handler raises during start-up, at whatever line the main thread is on. When it landed inside
``Thread.start()`` of a node worker (before the thread had started), the unwinding joined that listed-but-unstarted
thread and raised RuntimeError ("cannot join thread before it is started"): a clean stop became a failed start-up
with exit code 1 (seen once in tests/test_serve_lifecycle.py). Here ``start()`` of one worker raises first.
"""

import threading

import pytest

from drillnav.drivers.sim.scene import make_scene
from drillnav.service.bus import open_session
from drillnav.service.node import RegistrationNode

from conftest import free_endpoint, wait_for


class _Signal(Exception):
    """Stands for the CLI's _Interrupted, raised by its signal handler."""


def test_an_interrupted_worker_start_unwinds_without_a_join_error(monkeypatch):
    scene = make_scene(seed=21, render=False)
    real_start = threading.Thread.start

    def start(thread):
        if thread.name == "node-shots":
            raise _Signal("SIGTERM")  # the signal lands before this worker started
        real_start(thread)

    monkeypatch.setattr(threading.Thread, "start", start)
    with open_session(listen=[free_endpoint()]) as session:
        with pytest.raises(_Signal):
            with RegistrationNode(session=session, prefix="drillnav", marker_set=scene.marker_set, camera=scene.calibrated_camera,
                                  axis_drill=scene.calibrated_axis_drill):
                pass
    monkeypatch.undo()
    # The worker started before it (frames) saw the stop and ended.
    assert wait_for(lambda: not any(t.name.startswith("node-") for t in threading.enumerate()), 5), [t.name for t in threading.enumerate()]
