"""drillnav sim scene --anatomy: a CT (DICOM folder or NIfTI) as the twin's patient, then register --ct against it."""

import json
from pathlib import Path

import numpy as np
import pytest

from drillnav.drivers.ct_volume import read_ct
from drillnav.drivers.sim.ct_phantom import make_pelvis_ct
from drillnav.drivers.sim.dicom_io import write_ct_series
from drillnav.registration.transforms import apply, invert
from drillnav.service.cli import main

CHEST = Path(__file__).resolve().parents[2] / "shared" / "data" / "ct"
PLAN = Path(__file__).resolve().parents[1] / "docs" / "examples" / "chest-plan.json"


def register_args(d: Path, out: Path) -> list[str]:
    return ["register", "--markers", str(d / "markers.json"), "--camera", str(d / "camera.json"), "--drill", str(d / "drill.json"),
            "--video", str(d / "camera.png"), "--fluoro", *sorted(str(p) for p in (d / "fluoro").glob("*.dcm")), "--out", str(out),
            "--ct", str(d / "ct"), "--plan", str(d / "plan.json")]


def ct_error_at_entry_mm(d: Path, result: Path) -> float:
    truth, res = json.loads((d / "truth.json").read_text()), json.loads(result.read_text())
    entry = np.asarray(truth["corridor_entry_carm_mm"])
    entry_ct = apply(invert(np.asarray(truth["carm_from_ct"])), entry)
    return float(np.linalg.norm(apply(np.asarray(res["ct"]["carm_from_ct"]), entry_ct) - entry))


@pytest.fixture(scope="module")
def phantom_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("anatomy") / "ct-in"
    write_ct_series(folder, make_pelvis_ct(seed=4, voxel_mm=(1.5, 1.5, 2.0)), series_description="a CT handed to the twin")
    return folder


def test_dicom_folder_as_anatomy_end_to_end(phantom_folder, tmp_path, capsys):
    scene = tmp_path / "scene"
    assert main(["sim", "scene", "--seed", "5", "--anatomy", str(phantom_folder), "--entry=-95,-15,15", "--target=-92.3,62.6,47.0", "--out", str(scene)]) == 0
    handed, truth = read_ct(scene / "ct"), read_ct(phantom_folder)
    np.testing.assert_allclose(handed.spacing_mm, [1.875, 1.875, 2.0])  # coarser in-plane than the truth
    plan = json.loads((scene / "plan.json").read_text())
    assert [t["name"] for t in plan["trajectories"]] == ["planned"]
    assert main(register_args(scene, tmp_path / "r.json")) == 0
    assert "CT registered" in capsys.readouterr().out
    assert ct_error_at_entry_mm(scene, tmp_path / "r.json") < 1.0
    assert abs(float(np.median(np.asarray(handed.data, float))) - float(np.median(np.asarray(truth.data, float)))) < 50


@pytest.mark.parametrize("extra, message", [
    ([], "needs the planned trajectory"),
    (["--entry=1,2,3"], "go together"),
    (["--entry=1,2", "--target=1,2,3"], "X,Y,Z"),
    (["--entry=0,0,900", "--target=0,0,0"], "outside the CT"),
])
def test_anatomy_bad_requests_one_line(phantom_folder, tmp_path, capsys, extra, message):
    assert main(["sim", "scene", "--anatomy", str(phantom_folder), *extra, "--out", str(tmp_path / "s")]) == 1
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_anatomy_options_need_anatomy_and_a_readable_ct(tmp_path, capsys):
    assert main(["sim", "scene", "--entry=1,2,3", "--target=4,5,6", "--out", str(tmp_path / "a")]) == 1
    assert "need --anatomy" in capsys.readouterr().err
    assert main(["sim", "scene", "--anatomy", str(tmp_path / "missing.nii.gz"), "--entry=1,2,3", "--target=4,5,6", "--out", str(tmp_path / "b")]) == 1
    assert "no such file" in capsys.readouterr().err


@pytest.mark.skipif(not (CHEST / "cxr.nii.gz").exists(), reason="the real chest CT (../shared/data/ct) is not on this machine")
def test_real_chest_ct_as_anatomy_with_label_acceptance(tmp_path, capsys):
    """Real anatomy the simulator did not make: the product gets a resampled, noisier copy and registers to it."""
    scene = tmp_path / "chest"
    assert main(["sim", "scene", "--seed", "2", "--anatomy", str(CHEST / "cxr.nii.gz"), "--plan", str(PLAN), "--out", str(scene)]) == 0
    assert main(register_args(scene, tmp_path / "r.json")) == 0
    res = json.loads((tmp_path / "r.json").read_text())
    assert ct_error_at_entry_mm(scene, tmp_path / "r.json") < 1.0
    (conf,) = res["ct"]["conformance"]
    assert conf["trajectory"] == "L1-anterior" and conf["evaluated"]
    assert conf["min_clearance_mm"] > 1.5  # inside the vertebral body label (TotalSegmentator L1)
