"""Start-up: the CLI imports nothing heavy before a command needs it; the twin camera renders as it streams."""

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from drillnav.drivers.sim.devices import RENDER_NICE, TwinDrillCamera, freehand_loop
from drillnav.drivers.sim.scene import make_scene
from drillnav.drivers.webcam import CameraUnavailable

HEAVY = ("cma", "matplotlib", "numba", "zenoh", "fastapi")

PROBE = """
import sys
from drillnav.service.cli import main
try:
    main({argv!r})
except SystemExit:
    pass
print("LOADED:" + ",".join(sorted(m for m in {heavy!r} if m in sys.modules)))
"""


def loaded_after(argv: list[str], heavy: tuple[str, ...]) -> list[str]:
    """The modules of ``heavy`` that ``drillnav *argv`` has imported (run in a fresh interpreter)."""
    out = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv, heavy=heavy)], capture_output=True, text=True, timeout=60, check=True)
    last = out.stdout.splitlines()[-1]
    assert last.startswith("LOADED:"), out.stdout
    return [m for m in last.removeprefix("LOADED:").split(",") if m]


def test_drillnav_help_imports_no_heavy_library():
    assert loaded_after(["--help"], HEAVY) == []


@pytest.mark.parametrize("command", [["markers", "--help"], ["markers", "sheet", "--help"], ["sim", "scene", "--help"],
                                     ["calibrate", "drill-axis", "--help"], ["listen", "--help"], ["replay", "--help"]])
def test_command_help_imports_neither_heavy_libraries_nor_numpy(command):
    assert loaded_after(command, HEAVY + ("numpy", "cv2", "scipy")) == []


def test_the_probe_sees_a_heavy_import():
    # The check above can fail: a command that does load zenoh is seen doing so.
    assert "zenoh" in loaded_after(["listen", "drill-axis", "--connect", "tcp/127.0.0.1:1", "--timeout", "0.01", "--count", "1"], HEAVY)


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=3, n_markers=3, views="inlet", render=False)


def rendered_up_front(scene, *, loop_frames: int, keyposes: int, seed: int) -> list[np.ndarray]:
    """The loop as the twin camera rendered it before it streamed (all frames in its constructor)."""
    rng = np.random.default_rng(seed)
    poses = freehand_loop(scene, rng, loop_frames=loop_frames, keyposes=keyposes)
    return [scene.render_camera(rng, carm_from_drill=p) for p in poses]


def test_streamed_frames_are_the_frames_rendered_up_front_at_the_frame_rate_from_the_first(scene):
    expected = rendered_up_front(scene, loop_frames=3, keyposes=4, seed=5)
    camera = TwinDrillCamera(scene=scene, fps=20.0, loop_frames=3, seed=5)
    frames = []
    with camera as cam:
        while cam.rendered_frames < 3 or len(frames) < 4:
            frames.append(cam.read())
        complete = len(frames)
        frames += [cam.read() for _ in range(6)]
    index = [next(k for k, p in enumerate(camera.poses) if p is f.carm_from_drill) for f in frames]
    for f, k in zip(frames, index):
        np.testing.assert_array_equal(f.image, expected[k])  # every frame is the loop's frame k, as rendered up front
    assert [f.frame_id for f in frames] == list(range(1, len(frames) + 1))
    # While the loop renders (~0.5 s a frame, 50 ms a frame period) the newest frame is served again: the stream keeps
    # the frame rate, the drill pauses, and the loop is never played out of order.
    first_pass = index[: index.index(2) + 1]
    assert first_pass == sorted(first_pass) and len(first_pass) > 3, first_pass
    assert index[complete:] == [(index[complete - 1] + 1 + n) % 3 for n in range(6)]  # then every frame a new pose
    first_served: dict[int, np.ndarray] = {}
    for f, k in zip(frames, index):
        assert f.image is first_served.setdefault(k, f.image)  # rendered once, served from memory after
    stamps = np.array([f.stamp_ns for f in frames], dtype=np.int64)
    span_s = (stamps[-1] - stamps[0]) / 1e9
    assert span_s >= 0.9 * (len(frames) - 1) / 20.0, np.diff(stamps) / 1e6  # 50 ms apart at the least, repeats included


def test_the_first_frame_comes_after_one_render_not_the_whole_loop(scene):
    camera = TwinDrillCamera(scene=scene, fps=30.0, loop_frames=90, seed=1)
    assert camera.rendered_frames == 0  # nothing rendered before the camera is opened
    t0 = time.monotonic()
    with camera as cam:
        first = cam.read()
        waited_s = time.monotonic() - t0
        rendered = cam.rendered_frames
        if sys.platform == "linux":  # the twin's rendering yields to the product's threads
            (render,) = [t for t in threading.enumerate() if t.name == "twin-camera-render"]
            assert os.getpriority(os.PRIO_PROCESS, render.native_id) == RENDER_NICE
    t_closed = time.monotonic()
    assert first.frame_id == 1 and first.image.shape == (scene.true_camera.height, scene.true_camera.width)
    assert rendered < 90, f"all {rendered} frames were rendered before the first was served"
    # Closing waits for at most the render in progress; reopening resumes where rendering stopped.
    assert t_closed - t0 < 3 * waited_s + 5.0
    kept = camera.rendered_frames
    with camera as cam:
        assert cam.read().frame_id == 2
    assert camera.rendered_frames >= kept


class BrokenLensScene:
    """A scene whose renderer fails: the camera must say so instead of leaving the reader waiting."""

    def __init__(self, scene) -> None:
        self._scene = scene

    def drill_pose_towards(self, rng, **kwargs):
        return self._scene.drill_pose_towards(rng, **kwargs)

    def render_camera(self, rng, **kwargs):
        raise MemoryError("no room for the frame")


def test_a_failing_render_is_a_camera_error_not_a_hang(scene):
    with TwinDrillCamera(scene=BrokenLensScene(scene), loop_frames=5, seed=0) as cam:
        with pytest.raises(CameraUnavailable, match="stopped rendering: MemoryError: no room for the frame"):
            cam.read()


KERNEL_PROBE = """
import numpy as np
from drillnav.registration import distance_kernels as dk
dk.sample_trilinear(np.zeros((4, 4, 4), np.float32), np.eye(4), np.zeros((2, 3)), outside=-1.0)
print("HITS", sum(dk._sample.stats.cache_hits.values()), "MISSES", sum(dk._sample.stats.cache_misses.values()))
"""


def test_compiled_kernels_are_written_to_the_numba_cache_and_loaded_from_it(tmp_path):
    """A second process loads the kernel compiled by the first (cache=True, NUMBA_CACHE_DIR writable) instead of compiling."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    first, second = (subprocess.run([sys.executable, "-c", KERNEL_PROBE], capture_output=True, text=True, env=env, timeout=120, check=True).stdout.split()
                     for _ in range(2))
    assert first[-4:] == ["HITS", "0", "MISSES", "1"], first
    assert second[-4:] == ["HITS", "1", "MISSES", "0"], second
    assert list((tmp_path / "numba").rglob("distance_kernels._sample-*.nbi"))
