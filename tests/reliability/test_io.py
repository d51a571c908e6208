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


def test_a_writer_librarys_error_about_the_temporary_file_names_the_output(tmp_path):
    """OpenEXR reports a full disk as ``RuntimeError: Failed to write pixel data to image file ".x.exr.omnitmp-…"``:
    it becomes one error naming the output, and no temporary file is left (was: a traceback from ``export``)."""
    from omnispectral.errors import InputFileError

    out = tmp_path / "pano.exr"
    with pytest.raises(InputFileError) as info, atomic_path(out) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError(f'Failed to write pixel data to image file "{tmp}". File too large.')
    assert str(info.value).startswith(f"{out}: could not be written") and TEMP_MARK not in str(info.value)
    assert not list(tmp_path.iterdir())
    with pytest.raises(RuntimeError, match="unrelated"), atomic_path(out):
        raise RuntimeError("unrelated")


def test_tifffiles_own_warnings_do_not_precede_the_one_line(tmp_path, capsys):
    """A TIFF whose tags are missing: tifffile logs three warnings of its own; only our line reaches stderr."""
    import struct

    ifd = struct.pack("<H", 4) + b"".join(struct.pack("<HHII", tag, 4, 1, v) for tag, v in
                                          ((256, 65535), (257, 65535), (258, 16), (277, 3))) + b"\0\0\0\0"
    files = []
    for k in range(2):
        files.append(tmp_path / f"t{k}.tif")
        files[-1].write_bytes(b"II*\0" + struct.pack("<I", 8) + ifd + b"\0" * 1024)
    assert main(["hdr", "merge", *map(str, files), "--times", "0.01", "0.02", "-o", str(tmp_path / "o.exr")]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "65535" in err, err


def test_count_options_refuse_zero(tmp_path, capsys):
    """``mosaic --workers 0`` is a usage error (was: accepted, every core used)."""
    with pytest.raises(SystemExit) as info:
        main(["mosaic", str(tmp_path), "-o", str(tmp_path.parent / "pano.zarr"), "--workers", "0"])
    assert info.value.code == 2 and "not a count" in capsys.readouterr().err
    from omnispectral.errors import ConfigurationError
    from omnispectral.mosaic.options import MosaicOptions

    with pytest.raises(ConfigurationError, match="workers must be at least 1"):
        MosaicOptions(workers=0)
