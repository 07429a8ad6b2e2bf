"""Twin fluoroscopy XA compressed losslessly (as real C-arms send it) registers markers exactly like the uncompressed one."""

import shutil

import numpy as np
import pydicom
import pytest

from drillnav.drivers.fluoro_dicom import read_fluoro
from drillnav.drivers.sim.devices import TwinCArm
from drillnav.drivers.sim.scene import make_scene
from drillnav.registration.fluoro_markers import detect_markers
from drillnav.registration.marker_pose import register_markers
from dicom_compress import SYNTAXES, compress_file


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    scene = make_scene(seed=5, render=False)
    carm = TwinCArm(scene=scene, folder=tmp_path_factory.mktemp("carm"))
    return scene, {view: carm.shoot(view) for view in scene.views}


def _register(scene, files):
    images = {view: read_fluoro(path)[0] for view, path in files.items()}
    dets = [detect_markers(images[v].pixels_log, scene.marker_set) for v in scene.views]
    poses = register_markers(dets, [images[v].view for v in scene.views], scene.marker_set)
    return images, {p.marker_id: p.position_carm_mm for p in poses}


@pytest.fixture(scope="module")
def uncompressed(shots):
    scene, files = shots
    return _register(scene, files)


@pytest.mark.parametrize("syntax", ["jpeg-lossless", "jpeg-ls", "jpeg2000"])
def test_compressed_xa_registers_like_uncompressed(tmp_path, shots, uncompressed, syntax):
    scene, files = shots
    plain_images, plain_positions = uncompressed
    compressed = {}
    for view, path in files.items():
        dst = compress_file(path, tmp_path / f"{view}.dcm", syntax)
        shutil.copy(path.with_suffix(".json"), dst.with_suffix(".json"))  # the twin's calibrated projection beside it
        assert pydicom.dcmread(str(dst), stop_before_pixels=True).file_meta.TransferSyntaxUID == SYNTAXES[syntax]
        assert dst.stat().st_size < path.stat().st_size  # really compressed
        compressed[view] = dst
    images, positions = _register(scene, compressed)
    for view in scene.views:
        np.testing.assert_array_equal(images[view].pixels_log, plain_images[view].pixels_log)  # lossless: same pixels
    assert sorted(positions) == sorted(plain_positions) == sorted(scene.carm_from_marker)
    for marker_id, p in positions.items():
        assert np.linalg.norm(p - plain_positions[marker_id]) < 1e-6
        # A noisy twin shot (not the noiseless render test_fluoro_pipeline uses): sane, and the same as uncompressed.
        assert np.linalg.norm(p - scene.carm_from_marker[marker_id][:3, 3]) < 2.0
