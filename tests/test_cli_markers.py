"""drillnav markers export / sheet, and their refusals."""

import json

import cv2
import jsonschema
import numpy as np
import pypdfium2 as pdfium
import pytest

from drillnav.registration.aruco_detect import detect_aruco
from drillnav.registration.markers import default_marker_set
from drillnav.schemas.jig import JIG_SCHEMA
from drillnav.schemas.markers import read_marker_set
from drillnav.service.cli import main
from drillnav.service.cli_markers import PAGE_MARGIN_MM, SHEET_CELL_MM
from drillnav.service.print_pages import PAPER_MM


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


def test_sheet_svg_is_one_paper_page(tmp_path):
    out = tmp_path / "sheet.svg"
    assert main(["markers", "sheet", "--ids", "0-4", "--out", str(out)]) == 0
    head = out.read_text()[:2000]
    # An A4 page, 210 x 297 mm = 595.276 x 841.89 pt, drawn at 1:1.
    assert 'width="595.27' in head and 'height="841.88' in head


DPI = 400
PX_PER_MM = DPI / 25.4


def raster(pdf_path, page=0):
    """The PDF page as PDFium prints it: RGB (rows, columns, 3) at DPI, and the page size in points."""
    doc = pdfium.PdfDocument(str(pdf_path))
    try:
        pg = doc[page]
        return np.asarray(pg.render(scale=DPI / 72).to_pil().convert("RGB")), pg.get_size()
    finally:
        doc.close()


def runs(mask_row):
    """(start, length) of each run of True in a 1-D mask."""
    padded = np.concatenate([[False], mask_row, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b - a)) for a, b in zip(edges[::2], edges[1::2])]


def scale_bar_mm(rgb, paper):
    """The scale bar as printed, in mm: from its first tick's centre to its last's, on a row 3 mm above the bar
    where only the tall ticks (0, 50, 100 mm) reach."""
    w, h = PAPER_MM[paper]
    row = round((h - (PAGE_MARGIN_MM + 8.0 + 3.0)) * PX_PER_MM)
    ticks = runs(rgb[row].min(axis=1) < 100)
    assert len(ticks) == 3, ticks
    centres = [start + length / 2 for start, length in ticks]
    return (centres[-1] - centres[0]) / PX_PER_MM


@pytest.mark.parametrize("paper,size_pt", [("A4", (595.28, 841.89)), ("Letter", (612.0, 792.0))])
def test_sheet_ring_is_as_wide_as_its_wire_and_the_scale_bar_is_100_mm(tmp_path, paper, size_pt):
    out = tmp_path / "sheet.pdf"
    assert main(["markers", "sheet", "--ids", "0-1", "--paper", paper, "--out", str(out)]) == 0
    rgb, size = raster(out)
    np.testing.assert_allclose(size, size_pt, atol=0.01)
    assert abs(scale_bar_mm(rgb, paper) - 100.0) < 0.1
    # Along the row through marker 0's centre, the blue ring crosses twice: each crossing as wide as the wire.
    w, h = PAPER_MM[paper]
    per_row = int((w - 2 * PAGE_MARGIN_MM) // SHEET_CELL_MM)
    x0 = (w - per_row * SHEET_CELL_MM) / 2
    row = round((PAGE_MARGIN_MM + SHEET_CELL_MM / 2) * PX_PER_MM)
    cols = slice(round(x0 * PX_PER_MM), round((x0 + SHEET_CELL_MM) * PX_PER_MM))
    r, g, b = (rgb[row, cols, k].astype(int) for k in range(3))
    blue = (b - r > 80) & (b > 120)
    crossings = runs(blue)
    assert len(crossings) == 2, crossings
    design = default_marker_set().by_id(0)
    for _, length in crossings:
        assert abs(length / PX_PER_MM - design.ring_wire_diameter_mm) < 0.15, length / PX_PER_MM  # was ~7 mm
    centres = [start + length / 2 for start, length in crossings]
    assert abs((centres[1] - centres[0]) / PX_PER_MM - 2 * design.ring_radius_mm) < 0.2


def test_a_long_sheet_takes_several_pages_and_an_svg_refuses_them(tmp_path, capsys):
    out = tmp_path / "all.pdf"
    assert main(["markers", "sheet", "--ids", "0-47", "--paper", "Letter", "--out", str(out)]) == 0
    assert len(pdfium.PdfDocument(str(out))) == 6  # 3 x 3 markers a Letter page
    assert main(["markers", "sheet", "--ids", "0-47", "--out", str(tmp_path / "all.svg")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "4 pages do not fit one SVG" in err


def test_jig_prints_at_1_to_1_as_its_geometry_says(tmp_path):
    out = tmp_path / "jig.pdf"
    assert main(["markers", "jig", "--out", str(out), "--paper", "Letter"]) == 0
    doc = json.loads((tmp_path / "jig.json").read_text())
    jsonschema.validate(doc, JIG_SCHEMA)
    rgb, _ = raster(out)
    assert abs(scale_bar_mm(rgb, "Letter") - 100.0) < 0.1
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    ids, corners = detect_aruco(cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)), grey)
    found = {i: c / PX_PER_MM for i, c in zip(ids, corners)}
    geometry = {t["id"]: np.asarray(t["corners_mm"])[:, :2] for t in doc["tags"]}
    assert sorted(found) == sorted(geometry) == list(range(100, 116))
    # Page mm (x right, y down from the top) minus the printed origin = the board frame of the geometry file.
    origin = found[100][0] - geometry[100][0]
    for tag_id, corners_mm in geometry.items():
        np.testing.assert_allclose(found[tag_id] - origin, corners_mm, atol=0.1)


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
    out = tmp_path / "m.json"
    main(["markers", "export", "--ids", "0", "--out", str(out)])
    doc = json.loads(out.read_text())
    del doc["markers"][0]["ring"]["radius_mm"]
    out.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="markers/0/ring"):
        read_marker_set(out)
