"""The watched DICOM folder: content not names, half-written files retried, a persistent journal, retention, permissions."""

import os
import stat
import time

import numpy as np
import pytest

from drillnav.drivers.folder_watch import JOURNAL_NAME, FolderWatcher, apply_retention
from drillnav.drivers.sim.dicom_io import write_xa
from dicom_compress import compress_file


def _xa(path, seed=0):
    img = np.random.default_rng(seed).uniform(0, 3, (48, 40)).astype(np.float32)
    return write_xa(path, img, primary_deg=0, secondary_deg=-25, source_to_detector_mm=1164, source_to_isocenter_mm=624,
                    pixel_spacing_mm=(0.304, 0.304), study_uid="1.2.3", series_uid="1.2.3.4", instance_number=1)


def _poll_until(watcher, deadline_s=3.0):
    end = time.monotonic() + deadline_s
    got = []
    while time.monotonic() < end:
        got += watcher.poll()
        if got:
            return got
        time.sleep(0.02)
    return got


@pytest.fixture()
def source(tmp_path):
    return _xa(tmp_path / "source.dcm")


def test_any_name_with_the_preamble_is_taken_and_other_files_are_named(tmp_path, source):
    folder = tmp_path / "in"
    errors = []
    w = FolderWatcher(folder=folder, give_up_s=0.0, on_error=lambda p, m: errors.append(m))
    data = source.read_bytes()
    for name in ["IMG0001", "SHOT.DCM", "view.Dcm", "a b.ima"]:
        (folder / name).write_bytes(data)
    (folder / "notes.txt").write_bytes(b"not an image" * 20)
    (folder / ".hidden.part").write_bytes(data)
    assert w.poll() == []  # first sight: sizes not yet known to be stable
    got = sorted(p.name for p in w.poll())
    assert got == ["IMG0001", "SHOT.DCM", "a b.ima", "view.Dcm"]
    assert len(errors) == 1 and "notes.txt" in errors[0] and "not a DICOM file" in errors[0]
    assert w.poll() == []  # each offered once


@pytest.mark.parametrize("syntax", [None, "jpeg2000"])
def test_a_file_written_slowly_is_retried_then_taken(tmp_path, source, syntax):
    folder = tmp_path / "in"
    if syntax:
        source = compress_file(source, tmp_path / "c.dcm", syntax)
    data = source.read_bytes()
    errors = []
    w = FolderWatcher(folder=folder, give_up_s=0.2, on_error=lambda p, m: errors.append(m))
    target = folder / "slow.dcm"
    target.write_bytes(data[: len(data) - 100])  # the writer stalls with the last 100 bytes to come
    deadline = time.monotonic() + 0.6
    while time.monotonic() < deadline:
        assert w.poll() == []
        time.sleep(0.05)
    assert len(errors) == 1 and "slow.dcm" in errors[0]  # reported once, naming the file
    with open(target, "ab") as f:
        f.write(data[len(data) - 100:])
    assert _poll_until(w) == [target]


def test_a_file_shorter_than_a_preamble_is_refused_only_after_give_up(tmp_path):
    """Under 132 bytes a file may be a DICOM whose writer has not reached 'DICM' yet: it waits give_up_s, then is named."""
    folder = tmp_path / "in"
    errors = []
    w = FolderWatcher(folder=folder, give_up_s=0.3, on_error=lambda p, m: errors.append(m))
    (folder / "broken.dcm").write_bytes(b"garbage" * 10)
    t0 = time.monotonic()
    while not errors and time.monotonic() - t0 < 3.0:
        assert w.poll() == []
        time.sleep(0.02)
    assert time.monotonic() - t0 >= 0.3, "refused before give_up_s"
    assert len(errors) == 1 and "broken.dcm" in errors[0] and "not a DICOM file" in errors[0]
    assert w.poll() == [] and len(errors) == 1  # reported once


def test_journal_survives_a_restart(tmp_path, source):
    folder = tmp_path / "in"
    old = os.umask(0o022)
    try:
        w = FolderWatcher(folder=folder)
        for name in ["a.dcm", "b.dcm", "c.dcm"]:
            (folder / name).write_bytes(source.read_bytes())
        got = []
        while len(got) < 3:
            got += _poll_until(w)
        w.mark_processed(folder / "a.dcm")
        w.mark_processed(folder / "c.dcm")  # b.dcm was acknowledged but the process died before handling it
    finally:
        os.umask(old)
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert stat.S_IMODE((folder / JOURNAL_NAME).stat().st_mode) == 0o600
    with open(folder / JOURNAL_NAME, "a") as f:
        f.write("d.dcm\t12")  # a line cut by a crash
    w2 = FolderWatcher(folder=folder)
    assert _poll_until(w2) == [folder / "b.dcm"]
    assert w2.is_processed(folder / "a.dcm") and not w2.is_processed(folder / "b.dcm")
    # A file rewritten under a processed name is new content: offered again.
    time.sleep(0.01)
    (folder / "a.dcm").write_bytes(_xa(tmp_path / "other.dcm", seed=1).read_bytes())
    assert _poll_until(w2) == [folder / "a.dcm"]


def test_failed_read_is_offered_again_when_the_file_changes(tmp_path, source):
    folder = tmp_path / "in"
    w = FolderWatcher(folder=folder)
    (folder / "x.dcm").write_bytes(source.read_bytes())
    (p,) = _poll_until(w)
    w.failed(p, "pixel data cannot be decoded")
    time.sleep(0.1)
    assert w.poll() == [] and w.poll() == []
    (folder / "x.dcm").write_bytes(_xa(tmp_path / "y.dcm", seed=2).read_bytes())
    assert _poll_until(w) == [p]


def test_retention_by_age_then_budget_oldest_first(tmp_path, source):
    folder = tmp_path / "in"
    w = FolderWatcher(folder=folder)
    size = source.stat().st_size
    now = time.time()
    paths = []
    for i, age_h in enumerate([50, 30, 10, 5, 1]):
        p = folder / f"img{i}.dcm"
        p.write_bytes(source.read_bytes())
        os.utime(p, (now - age_h * 3600, now - age_h * 3600))
        paths.append(p)
    for p in paths[:4]:
        w.mark_processed(p)  # img4 has not been processed yet
    (folder / ".stale.part").write_bytes(b"x")
    os.utime(folder / ".stale.part", (now - 40 * 3600,) * 2)
    removed = w.apply_retention(max_age_s=24 * 3600, max_total_bytes=int(1.5 * size), now_s=now)
    # Age: img0, img1 and the stale part. Budget 1.5 files: img2 then img3 go (oldest first); img4 is spared, unprocessed.
    assert [p.name for p in removed] == ["img0.dcm", ".stale.part", "img1.dcm", "img2.dcm", "img3.dcm"]
    assert sorted(p.name for p in folder.iterdir() if not p.name.startswith(".")) == ["img4.dcm"]  # spared: unprocessed
    assert (folder / JOURNAL_NAME).read_text() == ""  # entries for deleted files are gone
    with pytest.raises(ValueError, match="max_age_s"):
        apply_retention(folder, max_age_s=0, max_total_bytes=1)
