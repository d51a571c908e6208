"""A whole file's bytes, read the cheapest way: mapped from the page cache when it holds them, else read past it.

A raw frame is read once, by the stage that uses it (checksum, decoding and merge all read the same bytes).

- **In the page cache** (a session just captured or read before): the file is mapped read-only, and the bytes
  are the cache's own pages, with no copy (:func:`mapped_bytes`).
- **Not in the page cache** (a session read back from disk): mapping it makes the kernel give the page cache a
  fresh page for every 4 KiB. On the development virtual machine that cost 14.6–20.6 CPU-s and 23–30 s for the
  14.5 GiB of a full-scale session, against 2.5–3.1 CPU-s and 9–12 s for the same bytes read with direct I/O
  (``O_DIRECT``, open(2)) into a fresh buffer per file: the disk's controller writes them straight into the
  process's buffer (:func:`direct_bytes`; docs/benchmarks.md, Processing).  The cache is left as it was, so a
  session larger than memory does not evict what else the machine holds.

Which case holds is asked of the kernel, page by page, with mincore(2) (:func:`resident_fraction`).  A file
system that refuses direct I/O (tmpfs on older kernels, some network file systems) gets the mapping.
Both return the file's bytes exactly (``len`` is the file's size), as an :class:`mmap.mmap` that
:mod:`tifffile`, :mod:`hashlib` and :func:`numpy.frombuffer` read in place.

References
----------
.. [1] Linux man-pages: open(2) (``O_DIRECT`` and its alignment rules), mincore(2), mmap(2), mremap(2).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import mmap
import os
from pathlib import Path

import numpy as np

__all__ = ["DIRECT_ALIGN_BYTES", "RESIDENT_FRACTION_FOR_MAP", "direct_bytes", "file_bytes", "mapped_bytes",
           "resident_fraction"]

#: Offsets and lengths of direct reads are multiples of this: the largest logical block size of common disks
#: (512-byte and 4 KiB sectors), and the page size, which aligns the buffer.
DIRECT_ALIGN_BYTES = 4096
#: A file with at least this fraction of its pages in the page cache is mapped; below it, read directly.
RESIDENT_FRACTION_FOR_MAP = 0.5

_LIBC: dict = {}


def file_bytes(path: str | Path) -> bytes | mmap.mmap:
    """The bytes of the file at ``path``: mapped when the page cache holds most of them, else read directly
    (module docstring); an empty file gives ``b""``.

    Raises
    ------
    OSError
        When the file cannot be opened or read.
    """
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size == 0:
            return b""
        if resident_fraction(fh.fileno(), size) < RESIDENT_FRACTION_FOR_MAP:
            content = direct_bytes(path, size)
            if content is not None:
                return content
        return mapped_bytes(fh.fileno(), size)


def mapped_bytes(fd: int, size: int) -> bytes | mmap.mmap:
    """The file open as ``fd`` mapped read-only, page tables filled in one call where the system can; read
    into memory when it cannot be mapped."""
    try:
        if hasattr(mmap, "MAP_POPULATE"):  # Linux: the page tables filled in one call, not page by page
            return mmap.mmap(fd, 0, flags=mmap.MAP_SHARED | mmap.MAP_POPULATE, prot=mmap.PROT_READ)
        return mmap.mmap(fd, 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError):  # a file system without mmap
        return os.pread(fd, size, 0)


def direct_bytes(path: str | Path, size: int) -> mmap.mmap | None:
    """The first ``size`` bytes of the file at ``path`` read with direct I/O into a fresh anonymous mapping, or
    ``None`` where the system or the file system has no direct I/O.

    Reads are whole multiples of :data:`DIRECT_ALIGN_BYTES` into the page-aligned mapping; the mapping is then
    shrunk to ``size`` (mremap(2)), so its length is the file's."""
    flag = getattr(os, "O_DIRECT", None)
    if flag is None or not hasattr(mmap, "MAP_ANONYMOUS"):
        return None
    try:
        fd = os.open(path, os.O_RDONLY | flag)
    except OSError:  # EINVAL: the file system refuses direct I/O
        return None
    try:
        padded = -(-size // DIRECT_ALIGN_BYTES) * DIRECT_ALIGN_BYTES
        buffer = mmap.mmap(-1, padded, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | getattr(mmap, "MAP_POPULATE", 0))
        done = _read_aligned(fd, buffer, size)
        if done < size:  # the file shrank, or a short read left an unaligned offset: the rest read plainly
            buffer[done:size] = _read_rest(path, done, size)
        if padded != size:
            buffer.resize(size)
        return buffer
    except OSError:
        return None
    finally:
        os.close(fd)


def _read_aligned(fd: int, buffer: mmap.mmap, size: int) -> int:
    """Direct reads into ``buffer`` from offset 0 until ``size`` bytes, the end of the file or a short read;
    returns the bytes read."""
    view = memoryview(buffer)
    done = 0
    try:
        while done < size and done % DIRECT_ALIGN_BYTES == 0:
            n = os.preadv(fd, [view[done:]], done)
            if n <= 0:
                break
            done += n
    finally:
        view.release()
    return min(done, size)


def _read_rest(path: str | Path, start: int, stop: int) -> bytes:
    with open(path, "rb") as fh:
        rest = os.pread(fh.fileno(), stop - start, start)
    if len(rest) != stop - start:
        raise OSError(f"{path}: file shorter than its size while read")
    return rest


def resident_fraction(fd: int, size: int) -> float:
    """Fraction of the file's pages in the page cache (mincore(2) on a mapping that touches none of them);
    1.0 where the system cannot say, so that the file is mapped."""
    mincore = _mincore()
    if mincore is None:
        return 1.0
    try:
        mapping = mmap.mmap(fd, 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError):
        return 1.0
    pages = -(-size // mmap.PAGESIZE)
    vec = np.zeros(pages, np.uint8)
    view = np.frombuffer(mapping, np.uint8)
    try:
        failed = mincore(ctypes.c_void_p(view.ctypes.data), ctypes.c_size_t(size), vec.ctypes.data_as(ctypes.c_void_p))
    finally:
        del view  # the mapping cannot close while an array exports it
        mapping.close()
    return 1.0 if failed else float(np.count_nonzero(vec & 1)) / pages


def _mincore():
    """libc's ``mincore``, or ``None`` where there is none."""
    if "mincore" not in _LIBC:
        try:
            fn = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True).mincore
            fn.argtypes, fn.restype = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p], ctypes.c_int
        except (OSError, AttributeError):
            fn = None
        _LIBC["mincore"] = fn
    return _LIBC["mincore"]
