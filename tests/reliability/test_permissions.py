"""Files and directories we write follow the umask, like any other tool's: not mkstemp's 0600."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from omnispectral.imaging.bracket import write_float_image
from omnispectral.io import atomic_write_json, current_umask
from omnispectral.product.exports import write_rgb_exr
from omnispectral.product.layout import write_band_product


@pytest.fixture
def umask():
    old = os.umask(0o022)
    os.umask(old)

    def set_mask(mask: int) -> None:
        os.umask(mask)

    yield set_mask
    os.umask(old)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", [0o002, 0o022, 0o077])
def test_written_files_and_directories_follow_the_umask(umask, tmp_path, mask):
    umask(mask)
    assert current_umask() == mask
    file_mode, dir_mode = 0o666 & ~mask, 0o777 & ~mask
    atomic_write_json(tmp_path / "a.json", {"x": 1})
    write_float_image(tmp_path / "f.tif", np.ones((4, 4, 3), np.float32))
    write_rgb_exr(tmp_path / "env.exr", np.ones((4, 8, 3), np.float32))
    store = write_band_product(tmp_path / "prod", np.ones((32, 64, 6), np.float32), {"bands": list("abcdef")},
                               tile=16)
    files = [tmp_path / "a.json", tmp_path / "f.tif", tmp_path / "env.exr", tmp_path / "prod" / "product.json"]
    dirs = [store.path]
    for p in store.path.rglob("*"):  # group and array metadata, chunks, completion markers, metadata group
        (dirs if p.is_dir() else files).append(p)
    assert len(files) > 20
    assert {str(p.relative_to(tmp_path)): oct(_mode(p)) for p in files if _mode(p) != file_mode} == {}
    assert {str(p.relative_to(tmp_path)): oct(_mode(p)) for p in dirs if _mode(p) != dir_mode} == {}
