"""drillnav markers export / sheet, and their refusals."""

import json

from drillnav.schemas.markers import read_marker_set
from drillnav.service.cli import main


def test_export_round_trip(tmp_path):
    out = tmp_path / "markers.json"
    assert main(["markers", "export", "--out", str(out)]) == 0
    ms = read_marker_set(out)
    assert ms.ids == tuple(range(48))
    doc = json.loads(out.read_text())
    assert doc["markers"][3]["ring"]["radius_mm"] == 24.0


def test_export_subset(tmp_path):
    out = tmp_path / "m.json"
    assert main(["markers", "export", "--ids", "0-2,9", "--out", str(out)]) == 0
    assert read_marker_set(out).ids == (0, 1, 2, 9)


def test_sheet_svg_is_one_to_one(tmp_path):
    out = tmp_path / "sheet.svg"
    assert main(["markers", "sheet", "--ids", "0-4", "--out", str(out)]) == 0
    head = out.read_text()[:2000]
    # 3 columns x 60 mm = 180 mm = 510.236 pt wide, 2 rows = 120 mm = 340.157 pt high.
    assert 'width="510.236' in head and 'height="340.157' in head


def test_bad_inputs_give_one_line(tmp_path, capsys):
    assert main(["markers", "export", "--ids", "99", "--out", str(tmp_path / "m.json")]) == 1
    assert "unknown marker id 99" in capsys.readouterr().err
    assert main(["markers", "export", "--ids", "4-2", "--out", str(tmp_path / "m.json")]) == 1
    assert "backwards" in capsys.readouterr().err
    assert main(["markers", "export", "--out", str(tmp_path / "no" / "such" / "m.json")]) == 1
    assert "does not exist" in capsys.readouterr().err
    assert main(["markers", "sheet", "--ids", "1", "--out", str(tmp_path / "s.png")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and ".pdf" in err


def test_malformed_markers_file_names_the_field(tmp_path):
    import pytest

    out = tmp_path / "m.json"
    main(["markers", "export", "--ids", "0", "--out", str(out)])
    doc = json.loads(out.read_text())
    del doc["markers"][0]["ring"]["radius_mm"]
    out.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="markers/0/ring"):
        read_marker_set(out)
