"""Crash-safe writing (:mod:`omnispectral.io`): an error while writing names the output the user asked for,
never the temporary file it is written to first."""

from __future__ import annotations

import errno
import os
import tempfile

import numpy as np
import pytest
import tifffile

from omnispectral.cli import main
from omnispectral.io import TEMP_MARK, atomic_path


def _temp_files(directory):
    return [p for p in directory.rglob("*") if TEMP_MARK in p.name]


@pytest.mark.parametrize("filename", ["temporary", None])
def test_a_failed_write_names_the_output(tmp_path, filename):
    """A full disk while writing the temporary file (``write`` names no file; ``open`` names the temporary one)."""
    out = tmp_path / "x.png"
    with pytest.raises(OSError) as info, atomic_path(out) as tmp:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), *([str(tmp)] if filename else []))
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(out) and info.value.filename2 is None
    assert not out.exists() and not _temp_files(tmp_path)


def test_an_unwritable_directory_names_the_output(tmp_path, monkeypatch):
    """``mkstemp`` refused (permission denied: what a non-root user gets in a read-only directory)."""
    out = tmp_path / "x.png"

    def refused(prefix="", suffix="", dir=None):
        raise PermissionError(errno.EACCES, "Permission denied", os.path.join(dir, f"{prefix}abc123{suffix}"))

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    with pytest.raises(PermissionError) as info, atomic_path(out):
        pass
    assert info.value.filename == str(out)


def test_errors_of_other_files_are_left_alone(tmp_path):
    with pytest.raises(FileNotFoundError) as info, atomic_path(tmp_path / "x.png"):
        open(tmp_path / "input.tif", "rb")
    assert info.value.filename == str(tmp_path / "input.tif")


def test_cli_output_that_is_a_directory_names_it_in_one_line(tmp_path, capsys):
    """A real rename failure (``os.replace`` onto a directory): one line naming the output, exit 1."""
    frames = []
    for k, level in enumerate((200, 800, 3200)):
        tifffile.imwrite(tmp_path / f"f{k}.tif", np.full((8, 10), level, np.uint16))
        frames.append(str(tmp_path / f"f{k}.tif"))
    out = tmp_path / "merged.tif"
    (out / "inside").mkdir(parents=True)
    assert main(["hdr", "merge", *frames, "--times", "0.0025", "0.01", "0.04", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"{out}: is a directory" in err and TEMP_MARK not in err and err.count("\n") == 1
    assert not _temp_files(tmp_path)
