"""drillnav sim scene -> drillnav register, end to end through real files (DICOM, PNG, JSON)."""

import json
import shutil

import numpy as np
import pydicom
import pytest

from drillnav.drivers.fluoro_dicom import DicomGeometryMissing, DicomUnreadable, read_fluoro
from drillnav.service.cli import main


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    assert main(["sim", "scene", "--seed", "11", "--markers", "5", "--views", "inlet,outlet", "--out", str(out)]) == 0
    return out


def args(d, *fluoro, out=None):
    return ["register", "--markers", str(d / "markers.json"), "--camera", str(d / "camera.json"), "--drill", str(d / "drill.json"),
            "--video", str(d / "camera.png"), "--fluoro", *map(str, fluoro), "--out", str(out or d / "result.json")]


def test_scene_folder_contract(scene_dir):
    for name in ["camera.png", "camera.json", "drill.json", "markers.json", "plan.json", "truth.json", "fluoro/inlet.dcm", "fluoro/inlet.json"]:
        assert (scene_dir / name).is_file(), name
    ds = pydicom.dcmread(str(scene_dir / "fluoro" / "inlet.dcm"))
    assert ds.Modality == "XA" and float(ds.PositionerSecondaryAngle) == -25.0
    assert float(ds.DistanceSourceToDetector) == 1164.0 and float(ds.DistanceSourceToPatient) == 624.0
    assert [float(v) for v in ds.ImagerPixelSpacing] == [0.304, 0.304] and ds.PatientPosition == "HFS"
    truth = json.loads((scene_dir / "truth.json").read_text())
    assert {"carm_from_drill", "carm_from_ct", "drill_axis_carm", "corridor_entry_carm_mm", "markers"} <= truth.keys()


def test_register_two_views_against_truth(scene_dir, tmp_path):
    out = tmp_path / "result.json"
    assert main(args(scene_dir, scene_dir / "fluoro/inlet.dcm", scene_dir / "fluoro/outlet.dcm", out=out) + ["--overlays", str(tmp_path / "ov")]) == 0
    r = json.loads(out.read_text())
    t = json.loads((scene_dir / "truth.json").read_text())
    p, d = np.array(r["drill_axis_carm"]["point_mm"]), np.array(r["drill_axis_carm"]["direction"])
    e = np.array(t["corridor_entry_carm_mm"])
    q = p + np.dot(e - p, d) * d
    assert np.linalg.norm(q - t["drill_axis_carm"]["point_mm"]) < 2.5
    assert np.degrees(np.arccos(np.clip(d @ t["drill_axis_carm"]["direction"], -1, 1))) < 2.0
    assert len(r["views"]) == 2 and len(r["markers"]) == 5 and (tmp_path / "ov" / "inlet-0.png").is_file()
    assert all(m["fre_mm"] < 3 for m in r["markers"])


def test_the_drill_calibrations_stated_uncertainty_sets_the_bound(scene_dir, tmp_path):
    """drill.json's residuals are the axis's calibration uncertainty the predicted error carries: the same
    registration with a drill calibration stated 5 times worse predicts a larger error (the calibration part
    dominates at the entry, 290 mm from the camera); stated 0 (unknown), the defaults (the twin's own 0.1 mm / 0.12 deg)."""
    fluoro = (scene_dir / "fluoro/inlet.dcm", scene_dir / "fluoro/outlet.dcm")
    doc = json.loads((scene_dir / "drill.json").read_text())
    assert (doc["residual_mm"], doc["residual_deg"]) == (0.1, 0.12)
    got = {}
    for name, mm, deg in (("stated", 0.1, 0.12), ("worse", 0.5, 0.6), ("unknown", 0.0, 0.0)):
        d = tmp_path / name
        shutil.copytree(scene_dir, d, ignore=shutil.ignore_patterns("*.dcm"))
        (d / "drill.json").write_text(json.dumps({**doc, "residual_mm": mm, "residual_deg": deg}))
        assert main(args(d, *fluoro, out=d / "r.json")) == 0
        got[name] = json.loads((d / "r.json").read_text())
    pe = {k: (r["predicted_error"]["position_mm"], r["predicted_error"]["angle_deg"]) for k, r in got.items()}
    assert got["worse"]["drill_axis_carm"] == got["stated"]["drill_axis_carm"]  # the registration itself is the same
    assert pe["worse"][0] > 2.5 * pe["stated"][0] and pe["worse"][1] > 2.5 * pe["stated"][1], pe
    assert pe["unknown"] == pe["stated"], pe


def test_geometry_from_positioner_when_json_absent(scene_dir, tmp_path):
    shutil.copy(scene_dir / "fluoro/inlet.dcm", tmp_path / "a.dcm")
    (img,) = read_fluoro(tmp_path / "a.dcm")
    (ref,) = read_fluoro(scene_dir / "fluoro/inlet.dcm")
    assert img.geometry_source == "positioner" and ref.geometry_source == "projection-matrix"
    assert img.view_name == "p+0s-25"
    np.testing.assert_allclose(img.view.projection_matrix, ref.view.projection_matrix, rtol=1e-6, atol=1e-6)


def test_missing_geometry_names_the_attribute(scene_dir, tmp_path):
    ds = pydicom.dcmread(str(scene_dir / "fluoro/inlet.dcm"))
    del ds.DistanceSourceToPatient
    ds.save_as(str(tmp_path / "b.dcm"))
    with pytest.raises(DicomGeometryMissing, match=r"DistanceSourceToPatient \(0018,1111\)"):
        read_fluoro(tmp_path / "b.dcm")


def test_corrupt_dicom_and_wrong_sop_class(scene_dir, tmp_path):
    (tmp_path / "c.dcm").write_bytes((scene_dir / "fluoro/inlet.dcm").read_bytes()[:700])
    with pytest.raises(DicomUnreadable, match="c.dcm"):
        read_fluoro(tmp_path / "c.dcm")
    (tmp_path / "d.dcm").write_text("not dicom")
    with pytest.raises(DicomUnreadable, match="not a readable DICOM"):
        read_fluoro(tmp_path / "d.dcm")
    ds = pydicom.dcmread(str(scene_dir / "fluoro/inlet.dcm"))
    ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.2"  # CT
    ds.save_as(str(tmp_path / "e.dcm"))
    with pytest.raises(DicomUnreadable, match="not a fluoroscopy"):
        read_fluoro(tmp_path / "e.dcm")


def test_real_radiograph_without_geometry_is_refused():
    from pathlib import Path

    real = Path(__file__).resolve().parents[2] / "shared" / "data" / "xray" / "chest-pa-RG1_UNCI.dcm"
    if not real.is_file():
        pytest.skip("../shared/data/xray is not present on this machine")
    with pytest.raises(DicomGeometryMissing, match="PositionerPrimaryAngle"):
        read_fluoro(real)


def test_register_bad_inputs_one_line(scene_dir, tmp_path, capsys):
    blank = tmp_path / "blank.png"
    import cv2

    cv2.imwrite(str(blank), np.full((720, 1280), 120, np.uint8))
    a = args(scene_dir, scene_dir / "fluoro/inlet.dcm")
    a[a.index("--video") + 1] = str(blank)
    assert main(a) == 1
    assert "no marker of the marker set" in capsys.readouterr().err
    (tmp_path / "bad.png").write_bytes(b"\x89PNG garbage")
    a[a.index("--video") + 1] = str(tmp_path / "bad.png")
    assert main(a) == 1
    assert "not a readable image" in capsys.readouterr().err
    # A marker set whose ids are not in view.
    doc = json.loads((scene_dir / "markers.json").read_text())
    truth_ids = {m["id"] for m in doc["markers"]}
    from drillnav.registration.markers import default_marker_set
    from drillnav.schemas.markers import write_marker_set

    write_marker_set(tmp_path / "other.json", default_marker_set().subset([i for i in range(48) if i not in truth_ids][:5]))
    b = args(scene_dir, scene_dir / "fluoro/inlet.dcm")
    b[b.index("--markers") + 1] = str(tmp_path / "other.json")
    assert main(b) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "marker" in err


def test_scene_files_validate_against_their_schemas(scene_dir, tmp_path):
    from drillnav.schemas.projection import read_projection
    from drillnav.schemas.scene_files import read_plan, read_truth

    truth = read_truth(scene_dir / "truth.json")
    assert len(truth.carm_from_marker) == 5
    assert [t["name"] for t in read_plan(scene_dir / "plan.json")["trajectories"]] == ["AIIS-PSIS", "superior-ramus", "posterior-column"]
    assert read_projection(scene_dir / "fluoro" / "inlet.json").rows == 976
    doc = json.loads((scene_dir / "fluoro" / "inlet.json").read_text())
    doc["projection_matrix"] = doc["projection_matrix"][:2]
    (tmp_path / "p.json").write_text(json.dumps(doc))
    from drillnav.schemas.projection import read_projection as rp

    with pytest.raises(ValueError, match="invalid at projection_matrix"):
        rp(tmp_path / "p.json")
    bad = json.loads((scene_dir / "truth.json").read_text())
    del bad["carm_from_ct"]
    (tmp_path / "t.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="carm_from_ct"):
        read_truth(tmp_path / "t.json")


@pytest.mark.parametrize("relation, sign", [("LOG", -1), ("LOG", 1), ("LIN", 1), ("LIN", -1)])
def test_pixel_intensity_relationship_and_sign_are_honoured(scene_dir, tmp_path, relation, sign):
    """The same shot stored as each (0028,1040) / (0028,1041) pair reads back as the same log attenuation, and its markers
    are found where they are in the original: a LOG image whose values rise with intensity (Sign +1, which the standard allows)
    used as it was would have inverted every BB."""
    from drillnav.registration.fluoro_markers import detect_markers
    from drillnav.schemas.markers import read_marker_set

    (ref,) = read_fluoro(scene_dir / "fluoro/inlet.dcm")
    attenuation = ref.pixels_log.astype(np.float64)
    intensity = 60000.0 * np.exp(-attenuation)  # what the detector measured (up to a gain)
    stored = {("LOG", -1): 1000.0 * attenuation + 200.0, ("LOG", 1): 1000.0 * np.log(intensity),
              ("LIN", 1): intensity, ("LIN", -1): 65000.0 - intensity}[(relation, sign)]
    ds = pydicom.dcmread(str(scene_dir / "fluoro/inlet.dcm"))
    ds.RescaleSlope, ds.RescaleIntercept = "1", "0"
    ds.PixelData = np.clip(np.round(stored), 0, 65535).astype(np.uint16).tobytes()
    ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign = relation, sign
    ds.save_as(str(tmp_path / "x.dcm"))
    shutil.copy(scene_dir / "fluoro/inlet.json", tmp_path / "x.json")
    (img,) = read_fluoro(tmp_path / "x.dcm")
    # The same image up to a gain and an offset, with the same polarity (more attenuation = larger).
    a, b = np.polyfit(attenuation.ravel(), img.pixels_log.ravel().astype(np.float64), 1)
    assert a > 0, f"{relation} sign {sign} read with inverted polarity"
    # LIN with Sign -1 leaves the intensity's zero unknown (taken at the largest value): close, not exact.
    assert np.corrcoef(attenuation.ravel(), img.pixels_log.ravel())[0, 1] > (0.99 if (relation, sign) == ("LIN", -1) else 0.999)
    marker_set = read_marker_set(scene_dir / "markers.json")
    want = {m.marker_id: m for m in detect_markers(ref.pixels_log, marker_set).markers}
    got = {m.marker_id: m for m in detect_markers(img.pixels_log / a, marker_set).markers}
    assert set(got) == set(want) and len(want) >= 4
    for i, m in want.items():
        c0 = np.array(sorted(tuple(b.center_px) for b in m.bbs))
        c1 = np.array(sorted(tuple(b.center_px) for b in got[i].bbs))
        assert c0.shape == c1.shape and np.abs(c0 - c1).max() < (0.2 if (relation, sign) == ("LIN", -1) else 0.1)


def test_a_malformed_intensity_sign_is_named(scene_dir, tmp_path):
    ds = pydicom.dcmread(str(scene_dir / "fluoro/inlet.dcm"))
    ds.PixelIntensityRelationshipSign = 2
    ds.save_as(str(tmp_path / "s.dcm"))
    with pytest.raises(DicomUnreadable, match=r"Pixel Intensity Relationship Sign \(0028,1041\) is 2"):
        read_fluoro(tmp_path / "s.dcm")
