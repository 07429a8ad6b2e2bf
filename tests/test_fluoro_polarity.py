"""Fluoroscopy whose file does not say which way its values run (MONOCHROME2, no LIN / LOG: processed for display).

The same twin shot is stored as a display shows it: metal bright (a radiograph's convention) or metal dark (most
fluoroscopy displays), MONOCHROME2 or MONOCHROME1, linear or with a display gamma. Read by its display's convention
alone (as the product did), a metal-dark display shows no marker at all; the product takes the reading in which the markers are identified, in
``drillnav register``, in ``drillnav markers measure``'s detections and in the daemon's intake (a real zenoh session,
the shot and the warning as a client receives them).
"""

from __future__ import annotations

import json
import shutil
import time

import numpy as np
import pydicom
import pytest

from drillnav.drivers.fluoro_dicom import read_fluoro
from drillnav.registration.fluoro_markers import detect_in_view
from drillnav.schemas import messages as msg
from drillnav.schemas.markers import read_marker_set
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.cli import main
from drillnav.service.fluoro_polarity import settle_polarity

def _attenuation_display(a):
    return 4095.0 * np.clip((a - np.percentile(a, 0.5)) / np.ptp(np.percentile(a, [0.5, 99.5])), 0, 1)


def _intensity_display(a, gamma=1.0):
    return 4095.0 * np.clip(np.exp(-a) / np.percentile(np.exp(-a), 99.9), 0, 1) ** gamma


# name: (Photometric Interpretation, stored value 0-4095 from the log attenuation a); "metal dark" where the display
# (MONOCHROME2: high values white, MONOCHROME1: low values white) shows metal dark.
DISPLAYS = {
    "MONOCHROME2 metal bright": ("MONOCHROME2", _attenuation_display),
    "MONOCHROME2 metal dark": ("MONOCHROME2", _intensity_display),
    "MONOCHROME2 metal dark, gamma 0.5": ("MONOCHROME2", lambda a: _intensity_display(a, 0.5)),
    "MONOCHROME1 metal bright": ("MONOCHROME1", _intensity_display),
    "MONOCHROME1 metal dark": ("MONOCHROME1", _attenuation_display),
}


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    assert main(["sim", "scene", "--seed", "11", "--markers", "5", "--views", "inlet,outlet", "--out", str(out)]) == 0
    return out


def as_display(scene_dir, view: str, display: str, out_dir):
    """The twin's ``view`` stored as ``display`` shows it, without Pixel Intensity Relationship: (path, its log attenuation)."""
    (ref,) = read_fluoro(scene_dir / f"fluoro/{view}.dcm")
    attenuation = ref.pixels_log.astype(np.float64)
    ds = pydicom.dcmread(str(scene_dir / f"fluoro/{view}.dcm"))
    del ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign
    ds.RescaleSlope, ds.RescaleIntercept = "1", "0"
    photometric, stored = DISPLAYS[display]
    ds.PhotometricInterpretation = photometric
    ds.PixelData = np.round(stored(attenuation)).astype(np.uint16).tobytes()
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{view}.dcm"
    ds.save_as(str(path))
    shutil.copy(scene_dir / f"fluoro/{view}.json", out_dir / f"{view}.json")
    return path, attenuation


@pytest.mark.parametrize("display", list(DISPLAYS))
def test_a_display_image_is_read_the_way_its_markers_show(scene_dir, tmp_path, display):
    marker_set = read_marker_set(scene_dir / "markers.json")
    (ref,) = read_fluoro(scene_dir / "fluoro/inlet.dcm")
    assert ref.polarity_stated and settle_polarity(ref, marker_set).note == ""  # the twin's files say LOG, sign -1
    want = detect_in_view(ref.pixels_log, ref.view, marker_set).by_id()
    assert len(want) >= 4
    path, attenuation = as_display(scene_dir, "inlet", display, tmp_path)
    (img,) = read_fluoro(path)
    assert not img.polarity_stated
    metal_dark = "metal dark" in display
    if metal_dark:
        # What the product did before: a metal-dark display read metal bright shows its BBs as pits, and no marker.
        assert detect_in_view(img.pixels_log, img.view, marker_set).markers == ()
    settled = settle_polarity(img, marker_set)
    assert settled.image.polarity_stated  # one reading travels on
    assert ("read metal dark" in settled.note) == metal_dark and "polarity not stated" in settled.note
    assert settled.image.reading.startswith("metal dark" if metal_dark else "metal bright")
    assert np.corrcoef(attenuation.ravel(), settled.image.pixels_log.ravel())[0, 1] > 0.95  # more attenuation = larger
    got = settled.detections.by_id()
    assert len(set(want) - set(got)) <= 1 and set(got) <= set(marker_set.ids), (sorted(want), sorted(got))
    for i in set(want) & set(got):
        c0 = np.array(sorted(tuple(b.center_px) for b in want[i].bbs))
        c1 = np.array(sorted(tuple(b.center_px) for b in got[i].bbs))
        if c0.shape == c1.shape:
            assert np.abs(c0 - c1).max() < 0.5, (display, i)


def test_with_no_marker_in_either_reading_the_display_convention_stands_and_says_so(scene_dir, tmp_path):
    ds = pydicom.dcmread(str(scene_dir / "fluoro/inlet.dcm"))
    del ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign
    ds.RescaleSlope, ds.RescaleIntercept = "1", "0"
    rng = np.random.default_rng(3)
    ds.PixelData = rng.integers(1500, 2500, size=(ds.Rows, ds.Columns)).astype(np.uint16).tobytes()
    ds.save_as(str(tmp_path / "blank.dcm"))
    shutil.copy(scene_dir / "fluoro/inlet.json", tmp_path / "blank.json")
    (img,) = read_fluoro(tmp_path / "blank.dcm")
    settled = settle_polarity(img, read_marker_set(scene_dir / "markers.json"))
    assert settled.detections.markers == () and settled.image.polarity_stated
    assert np.array_equal(settled.image.pixels_log, img.pixels_log)
    assert "no reading identifies more markers (0 either way): read metal bright" in settled.note


def test_register_on_metal_dark_displays_reaches_the_truth(scene_dir, tmp_path):
    paths = [as_display(scene_dir, v, "MONOCHROME2 metal dark, gamma 0.5", tmp_path / "disp")[0] for v in ("inlet", "outlet")]
    out = tmp_path / "result.json"
    d = scene_dir
    assert main(["register", "--markers", str(d / "markers.json"), "--camera", str(d / "camera.json"), "--drill", str(d / "drill.json"),
                 "--video", str(d / "camera.png"), "--fluoro", *map(str, paths), "--out", str(out)]) == 0
    r, t = json.loads(out.read_text()), json.loads((d / "truth.json").read_text())
    assert all("read metal dark" in v["polarity"] for v in r["views"]) and all(len(v["markers_identified"]) >= 3 for v in r["views"])
    p, u = np.array(r["drill_axis_carm"]["point_mm"]), np.array(r["drill_axis_carm"]["direction"])
    e = np.array(t["corridor_entry_carm_mm"])
    assert np.linalg.norm(p + np.dot(e - p, u) * u - t["drill_axis_carm"]["point_mm"]) < 2.5
    assert np.degrees(np.arccos(np.clip(u @ t["drill_axis_carm"]["direction"], -1, 1))) < 2.0


def test_the_daemons_intake_publishes_the_reading_that_shows_the_markers(scene_dir, tmp_path):
    from drillnav.service.daemon import Daemon

    from test_serve_lifecycle import config, settings_of

    cfg = config(tmp_path / "d", recording="record_on_start = false")
    cfg.write_text(f'markers_file = "{scene_dir / "markers.json"}"\n' + cfg.read_text())  # a top-level key, before the sections
    settings = settings_of(cfg)
    shots, events = [], []
    path, attenuation = as_display(scene_dir, "inlet", "MONOCHROME2 metal dark", tmp_path / "src")
    with Daemon(settings) as daemon, open_session(connect=list(settings.zenoh.listen)) as s:
        s.declare_subscriber(key("drillnav", "fluoro_shot"), lambda smp: shots.append(msg.FluoroShot.from_bytes(smp.payload.to_bytes())))
        s.declare_subscriber(key("drillnav", "events"), lambda smp: events.append(msg.decode_json(smp.payload.to_bytes())))
        time.sleep(0.5)
        watch = settings.dicom.watch_folder
        shutil.copy(path.with_suffix(".json"), watch / "inlet.json")
        shutil.copy(path, watch / ".inlet.dcm")
        (watch / ".inlet.dcm").rename(watch / "inlet.dcm")  # whole, as a C-arm's export lands
        deadline = time.monotonic() + 60
        while not shots and time.monotonic() < deadline:
            time.sleep(0.1)
        assert shots, f"no shot published; daemon errors {daemon.errors}"
        deadline = time.monotonic() + 5
        while not any("read metal dark" in e.get("message", "") for e in events) and time.monotonic() < deadline:
            time.sleep(0.1)
    warned = [e for e in events if "read metal dark" in e.get("message", "")]
    assert warned and warned[0]["level"] == "warning" and "inlet.dcm" in warned[0]["message"], events
    image = shots[0].image_log.astype(np.float64)
    assert np.corrcoef(attenuation.ravel(), image.ravel())[0, 1] > 0.95  # the shot carries attenuation, metal bright
