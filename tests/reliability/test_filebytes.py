"""A frame file's bytes (:mod:`omnispectral.filebytes`): mapped from the page cache when it holds them, read past
the cache with direct I/O when it does not; the same bytes either way, and the cache left as it was."""

from __future__ import annotations

import gc
import os

import numpy as np
import pytest
import tifffile

from omnispectral.capture.session import decode_frame, frame_content
from omnispectral.filebytes import direct_bytes, file_bytes, resident_fraction


def _write(path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())  # clean pages: the cache can drop them


def _evict(path) -> None:
    with open(path, "rb") as fh:
        os.posix_fadvise(fh.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)


def _resident(path) -> float:
    with open(path, "rb") as fh:
        return resident_fraction(fh.fileno(), os.fstat(fh.fileno()).st_size)


def _direct_io_here(path) -> bool:
    """Whether this file system evicts on request and reads with direct I/O (ext4, XFS, btrfs do; tmpfs may not)."""
    _write(path, b"x" * 5000)
    _evict(path)
    return _resident(path) == 0.0 and direct_bytes(path, 5000) is not None


@pytest.mark.parametrize("size", [1, 4095, 4096, 4097, 3 * 4096 + 5])
def test_bytes_read_past_the_cache_are_the_file_and_leave_the_cache_alone(tmp_path, size):
    if not hasattr(os, "posix_fadvise") or not _direct_io_here(tmp_path / "probe"):
        pytest.skip("no eviction or direct I/O on this file system")
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    path = tmp_path / "f.bin"
    _write(path, data)
    assert _resident(path) == 1.0  # just written: cached, so mapped
    cached = file_bytes(path)
    assert len(cached) == size and cached[:] == data
    del cached  # a mapped page stays in the cache while mapped
    _evict(path)
    assert _resident(path) == 0.0
    content = file_bytes(path)
    assert len(content) == size and content[:] == data
    assert _resident(path) == 0.0, "the bytes came through the page cache, not past it"


def test_a_file_shorter_than_asked_is_not_read_directly(tmp_path):
    path = tmp_path / "f.bin"
    _write(path, b"y" * 6000)
    assert direct_bytes(path, 9000) is None  # the size changed under the reader: the caller maps what is there


def test_an_empty_file_is_empty(tmp_path):
    (tmp_path / "e").write_bytes(b"")
    assert file_bytes(tmp_path / "e") == b""


def test_a_frame_decodes_the_same_from_the_cache_and_from_the_disk(tmp_path):
    pixels = np.random.default_rng(3).integers(0, 4096, (37, 53, 3), dtype=np.uint16)
    path = tmp_path / "A_e00.tif"
    tifffile.imwrite(path, pixels, photometric="rgb", description='{"exposure_s": 0.01}', metadata=None)
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())
    cached, meta = decode_frame(path, frame_content(path))
    cached = cached.copy()
    gc.collect()  # tifffile's page and file objects refer to each other: the mapping goes with them
    _evict(path)
    assert _resident(path) == 0.0 or not hasattr(os, "O_DIRECT")
    uncached, meta_uncached = decode_frame(path, frame_content(path))
    assert np.array_equal(cached, pixels) and np.array_equal(uncached, pixels)
    assert meta == meta_uncached == {"exposure_s": 0.01}
