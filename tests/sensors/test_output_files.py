"""Writing never destroys: an output that is an input (by any name) is found, a place no file
can be created is found before the work by trying, and a write that fails halfway leaves what
was there and no half file."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from armfusion.sensors.output_files import cannot_create_in, replaced_when_done, same_file
from armfusion.sensors.recording import read_recording, write_recording
from armfusion.sensors.samples import Recording, Stream


def test_an_output_that_is_an_input_by_any_name_is_found(tmp_path: Path) -> None:
    rec = tmp_path / "in.csv"
    rec.write_text("t\n0\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "link.csv").symlink_to(rec)
    os.link(rec, tmp_path / "hard.csv")
    for out in (rec, tmp_path / "sub" / ".." / "in.csv", tmp_path / "link.csv", tmp_path / "hard.csv"):
        assert same_file(out, [None, tmp_path / "other.csv", rec]) == rec, out
    assert same_file(tmp_path / "new.csv", [rec, None]) is None


def test_a_place_no_file_can_be_created_in_is_found_by_trying(tmp_path: Path) -> None:
    # /sys refuses a new file even to root, whom a permission check alone lets through
    assert cannot_create_in(Path("/sys/r.html")) == "cannot create files in /sys (Permission denied)"
    assert cannot_create_in(tmp_path / "a" / "b" / "r.html") is None  # its first existing parent
    (tmp_path / "f").write_text("")
    assert cannot_create_in(tmp_path / "f" / "r.html") == f"{tmp_path / 'f'} is a file, not a directory"
    assert list(tmp_path.iterdir()) == [tmp_path / "f"]  # the trial left nothing


def test_a_write_that_fails_halfway_leaves_the_old_file_and_no_half_file(tmp_path: Path) -> None:
    out = tmp_path / "est.csv"
    out.write_text("the old estimates\n")
    with pytest.raises(RuntimeError), replaced_when_done(out) as tmp:
        tmp.write_text("half of the new")
        raise RuntimeError("the disk is full")
    assert out.read_text() == "the old estimates\n"
    assert list(tmp_path.iterdir()) == [out]
    with replaced_when_done(out) as tmp:
        tmp.write_text("the new estimates\n")
    assert out.read_text() == "the new estimates\n" and list(tmp_path.iterdir()) == [out]


@pytest.mark.parametrize("suffix", [".csv", ".mcap"])
def test_a_recording_that_cannot_be_written_leaves_the_old_one_whole(tmp_path: Path, suffix: str) -> None:
    t = np.arange(10) * 0.01
    good = Recording({"enc": Stream("enc", "encoder", t, np.arange(10)[:, None], ("enc1",))})
    out = tmp_path / f"rec{suffix}"
    write_recording(good, out)
    before = out.read_bytes()
    # a stream of a kind the formats do not know: the MCAP writer meets it after its header
    bad = Recording({**good.streams, "odd": Stream("odd", "bogus", t, np.arange(10)[:, None], ("x",))})
    with pytest.raises(ValueError):
        write_recording(bad, out)
    assert out.read_bytes() == before and sorted(tmp_path.iterdir()) == [out]
    assert read_recording(out).get("enc").values[:, 0].tolist() == list(range(10))


def test_a_file_written_has_the_permissions_an_open_would_give_it(tmp_path: Path) -> None:
    new, old = tmp_path / "new.csv", tmp_path / "old.csv"
    old.write_text("x")
    old.chmod(0o640)
    umask = os.umask(0o022)
    try:
        for p in (new, old):
            with replaced_when_done(p) as tmp:
                tmp.write_text("y")
    finally:
        os.umask(umask)
    assert (new.stat().st_mode & 0o777, old.stat().st_mode & 0o777) == (0o644, 0o640)
