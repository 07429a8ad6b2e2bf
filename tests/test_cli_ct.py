"""drillnav sim scene --ct -> drillnav register --ct --plan --ct-views, end to end through a DICOM CT series."""

import json

import numpy as np
import pydicom
import pytest

from drillnav.registration.transforms import apply, invert, rotation_angle_deg
from drillnav.service.cli import main


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("ctscene")
    assert main(["sim", "scene", "--seed", "12", "--ct-voxel-mm", "1.5", "--out", str(out)]) == 0
    return out


def args(d, out):
    return ["register", "--markers", str(d / "markers.json"), "--camera", str(d / "camera.json"), "--drill", str(d / "drill.json"),
            "--video", str(d / "camera.png"), "--fluoro", str(d / "fluoro/inlet.dcm"), str(d / "fluoro/outlet.dcm"), "--out", str(out)]


def test_ct_series_is_written_as_ct_images(scene_dir):
    files = sorted((scene_dir / "ct").glob("*.dcm"))
    assert len(files) == 200
    ds = pydicom.dcmread(files[0])
    assert ds.Modality == "CT" and ds.RescaleType == "HU" and [float(v) for v in ds.PixelSpacing] == [1.5, 1.5]


def test_register_with_ct_plan_and_views(scene_dir, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert main(args(scene_dir, out) + ["--ct", str(scene_dir / "ct"), "--plan", str(scene_dir / "plan.json"), "--ct-views", str(tmp_path / "v")]) == 0
    assert "CT registered" in capsys.readouterr().out
    r = json.loads(out.read_text())["ct"]
    truth = json.loads((scene_dir / "truth.json").read_text())
    diff = np.array(r["carm_from_ct"]) @ invert(np.array(truth["carm_from_ct"]))
    entry = np.array(truth["corridor_entry_carm_mm"])
    assert np.linalg.norm(apply(diff, [entry])[0] - entry) < 1.0 and rotation_angle_deg(diff) < 0.5
    assert r["registration"]["converged"]
    # The axis in CT follows L_V = ct_from_carm @ carm_from_drill @ L_D: compare with the truth carried the same way.
    axis_d = np.array(r["drill_axis_ct"]["direction"])
    true_ct_dir = invert(np.array(truth["carm_from_ct"]))[:3, :3] @ np.array(truth["drill_axis_carm"]["direction"])
    assert np.degrees(np.arccos(np.clip(axis_d @ true_ct_dir, -1, 1))) < 2.0
    aiis = next(c for c in r["conformance"] if c["trajectory"] == "AIIS-PSIS")
    assert aiis["evaluated"] and not aiis["breach"] and aiis["min_clearance_mm"] > 1.5
    assert r["nearest_trajectory"] == "AIIS-PSIS"
    assert all(not c["evaluated"] for c in r["conformance"] if c["trajectory"] != "AIIS-PSIS")  # other corridors point elsewhere
    for name in ["axial", "coronal", "sagittal", "oblique", "mosaic"]:
        assert (tmp_path / "v" / f"ct-{name if name != 'mosaic' else 'views'}.png").is_file()


def test_ct_bad_inputs_one_line(scene_dir, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert main(args(scene_dir, out) + ["--plan", str(scene_dir / "plan.json")]) == 1
    assert "need --ct" in capsys.readouterr().err
    assert main(args(scene_dir, out) + ["--ct", str(tmp_path / "nowhere")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such file or folder" in err
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in sorted((scene_dir / "ct").glob("*.dcm"))[:20]:
        if f.name != "CT0010.dcm":
            (broken / f.name).write_bytes(f.read_bytes())
    assert main(args(scene_dir, out) + ["--ct", str(broken)]) == 1
    assert "CT0009.dcm-CT0011.dcm" in capsys.readouterr().err
    bad_plan = tmp_path / "plan.json"
    bad_plan.write_text(json.dumps({"schema": "drillnav.plan/1", "trajectories": [{"name": "x", "entry_mm": [0, 0], "target_mm": [1, 2, 3], "corridor": {"type": "cylinder", "radius_mm": 3}}]}))
    assert main(args(scene_dir, out) + ["--ct", str(scene_dir / "ct"), "--plan", str(bad_plan)]) == 1
    assert "invalid at trajectories/0/entry_mm" in capsys.readouterr().err
    assert not out.exists()  # nothing half-written
