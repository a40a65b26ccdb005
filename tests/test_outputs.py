"""Output paths refused before any work (acq.outputs): one line naming the option and the path,
for a folder that cannot be written (``/proc``: os.access says yes to root, creating a file
fails), a missing folder, a folder given for a file, an input given as an output, an existing
file without --overwrite."""

from __future__ import annotations

from pathlib import Path

import pytest

from spdepth.acq.errors import OutputError
from spdepth.acq.outputs import PROBE_PREFIX, check_output_file, check_output_folder

UNWRITABLE = Path("/proc")


def test_an_output_file_is_checked_before_any_work(tmp_path):
    check_output_file("--png", tmp_path / "new.png")
    assert list(tmp_path.iterdir()) == []                     # the probe file is gone again
    (tmp_path / "old.png").write_bytes(b"x")
    with pytest.raises(OutputError, match=r"^--png .*old\.png exists \(pass --overwrite to replace it\)$"):
        check_output_file("--png", tmp_path / "old.png")
    check_output_file("--png", tmp_path / "old.png", overwrite=True)
    assert (tmp_path / "old.png").read_bytes() == b"x"        # checked, not touched
    with pytest.raises(OutputError, match=r"is a folder; give a file name"):
        check_output_file("--out", tmp_path)
    with pytest.raises(OutputError, match=r"folder .*nope does not exist"):
        check_output_file("--out", tmp_path / "nope" / "x.npz")
    with pytest.raises(OutputError, match=r"is the input"):
        check_output_file("--out", tmp_path / "old.png", overwrite=True,
                          inputs=(str(tmp_path / "old.png"),))


@pytest.mark.skipif(not (UNWRITABLE / "self").exists(), reason="no /proc here")
def test_a_folder_no_file_can_be_made_in_is_refused_naming_the_option():
    with pytest.raises(OutputError) as info:
        check_output_file("--png", "/proc/x.png")
    assert str(info.value) == "--png /proc/x.png: cannot be written (files cannot be created there)"
    with pytest.raises(OutputError, match=r"^--out /proc/batch: cannot be written"):
        check_output_folder("--out", "/proc/batch")


def test_an_output_folder_may_be_made_where_its_parent_is_writable(tmp_path):
    check_output_folder("--out", tmp_path / "a" / "b")
    assert not (tmp_path / "a").exists()                      # checking makes nothing
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match="exists and is not a folder"):
        check_output_folder("--out", tmp_path / "f")
    assert not any(p.name.startswith(PROBE_PREFIX) for p in tmp_path.iterdir())
