"""Enhanced XA: the geometry, intensity relationship and rescale a frame states in its functional groups.

An enhanced XA (or XRF) image keeps per frame, or shared by all, what the older XA module keeps at the top level
(PS3.3 C.8.19.6): positioner angles in the Positioner Position Sequence, source distances in the X-Ray Geometry
Sequence, the imager pixel spacing and the intensity relationship in the Frame Pixel Data Properties Sequence, the
rescale in the Pixel Value Transformation Sequence. The twin's two single-frame XA shots are stored here as one
two-frame enhanced XA, each frame with its own angles, and must read back as the same two views and register.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence
from pydicom.uid import EnhancedXAImageStorage

from drillnav.drivers.fluoro_dicom import DicomGeometryMissing, read_fluoro
from drillnav.service.cli import main

MOVED = ("PositionerPrimaryAngle", "PositionerSecondaryAngle", "DistanceSourceToDetector", "DistanceSourceToPatient", "ImagerPixelSpacing",
         "PixelIntensityRelationship", "PixelIntensityRelationshipSign", "RescaleSlope", "RescaleIntercept", "RescaleType")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    assert main(["sim", "scene", "--seed", "11", "--markers", "5", "--views", "inlet,outlet", "--out", str(out)]) == 0
    return out


def _item(**attributes) -> Sequence:
    ds = Dataset()
    for k, v in attributes.items():
        setattr(ds, k, v)
    return Sequence([ds])


def enhanced(classic: list, path, *, drop_second_angles: bool = False):
    """The single-frame XA files ``classic`` as one multi-frame enhanced XA at ``path``."""
    shots = [pydicom.dcmread(str(c)) for c in classic]
    angles = [(s.PositionerPrimaryAngle, s.PositionerSecondaryAngle) for s in shots]
    ds = shots[0]
    first = {k: ds[k] for k in MOVED}  # the data elements (their .value)
    for k in MOVED:
        delattr(ds, k)
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = EnhancedXAImageStorage
    ds.NumberOfFrames = len(shots)
    ds.PixelData = b"".join(s.PixelData for s in shots)
    shared = Dataset()
    shared.XRayGeometrySequence = _item(DistanceSourceToDetector=first["DistanceSourceToDetector"].value,
                                        DistanceSourceToIsocenter=first["DistanceSourceToPatient"].value)
    shared.FramePixelDataPropertiesSequence = _item(ImagerPixelSpacing=first["ImagerPixelSpacing"].value,
                                                    PixelIntensityRelationship=first["PixelIntensityRelationship"].value,
                                                    PixelIntensityRelationshipSign=first["PixelIntensityRelationshipSign"].value)
    shared.PixelValueTransformationSequence = _item(RescaleSlope=first["RescaleSlope"].value, RescaleIntercept=first["RescaleIntercept"].value, RescaleType="US")
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    frames = []
    for k, (primary, secondary) in enumerate(angles):
        f = Dataset()
        if not (drop_second_angles and k == 1):
            f.PositionerPositionSequence = _item(PositionerPrimaryAngle=primary, PositionerSecondaryAngle=secondary)
        frames.append(f)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.save_as(str(path))
    return path


def test_each_frame_reads_as_its_single_frame_twin(scene_dir, tmp_path):
    singles = []
    for v in ("inlet", "outlet"):  # without the projection JSON beside them: their geometry from the positioner too
        shutil.copy(scene_dir / f"fluoro/{v}.dcm", tmp_path / f"{v}.dcm")
        singles += read_fluoro(tmp_path / f"{v}.dcm")
    frames = read_fluoro(enhanced([tmp_path / "inlet.dcm", tmp_path / "outlet.dcm"], tmp_path / "run.dcm"))
    assert [f.sop_class for f in frames] == ["Enhanced XA"] * 2 and [f.frame_index for f in frames] == [0, 1]
    for single, frame in zip(singles, frames):
        assert frame.view_name == single.view_name and frame.geometry_source == "positioner"
        assert np.allclose(frame.view.projection_matrix, single.view.projection_matrix)
        assert np.array_equal(frame.pixels_log, single.pixels_log) and frame.polarity_stated  # LOG, -1 read from the shared group
    assert frames[0].view_name != frames[1].view_name


def test_a_frame_without_its_angles_is_refused_naming_the_frame_and_sequence(scene_dir, tmp_path):
    path = enhanced([scene_dir / "fluoro/inlet.dcm", scene_dir / "fluoro/outlet.dcm"], tmp_path / "run.dcm", drop_second_angles=True)
    with pytest.raises(DicomGeometryMissing, match=r"missing PositionerPrimaryAngle \(0018,1510\) \(or PositionerPrimaryAngle in frame 2's PositionerPositionSequence\)"):
        read_fluoro(path)


def test_register_on_one_two_frame_enhanced_file_reaches_the_truth(scene_dir, tmp_path):
    path = enhanced([scene_dir / "fluoro/inlet.dcm", scene_dir / "fluoro/outlet.dcm"], tmp_path / "run.dcm")
    out, d = tmp_path / "result.json", scene_dir
    assert main(["register", "--markers", str(d / "markers.json"), "--camera", str(d / "camera.json"), "--drill", str(d / "drill.json"),
                 "--video", str(d / "camera.png"), "--fluoro", str(path), "--out", str(out)]) == 0
    r, t = json.loads(out.read_text()), json.loads((d / "truth.json").read_text())
    assert [v["frame"] for v in r["views"]] == [0, 1] and all(len(v["markers_identified"]) >= 3 for v in r["views"])
    p, u = np.array(r["drill_axis_carm"]["point_mm"]), np.array(r["drill_axis_carm"]["direction"])
    e = np.array(t["corridor_entry_carm_mm"])
    assert np.linalg.norm(p + np.dot(e - p, u) * u - t["drill_axis_carm"]["point_mm"]) < 2.5
    assert np.degrees(np.arccos(np.clip(u @ t["drill_axis_carm"]["direction"], -1, 1))) < 2.0
