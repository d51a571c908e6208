"""Large arrays reused by the C allocator instead of being returned to the system and faulted in again.

The pipeline allocates and frees arrays of 10-30 MB per frame and per direction (frames read, merged
radiance, float16 copies, parallax maps) on several threads.  glibc's malloc serves such sizes with
fresh ``mmap`` pages, or from per-thread arenas that it trims back to the system, so every new array
costs one page fault per 4 KiB and the kernel zeroes the page: on a full-scale frame, 1.3 million page
faults and 10 s of system time in the merge alone (measured with ``getrusage``; 0.2 million and 3.7 s
after :func:`reuse_freed_memory`).  The settings are glibc's documented ``mallopt`` parameters
(``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD``, ``M_ARENA_MAX``, see mallopt(3)); they change speed and the
memory the process keeps between arrays, never results.  Other C libraries are left alone.

References
----------
.. [1] The GNU C Library manual, "Malloc Tunable Parameters"; Linux man-pages, mallopt(3).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

__all__ = ["MMAP_THRESHOLD_BYTES", "reuse_freed_memory"]

#: Allocations below this come from the heap and are reused after ``free``; glibc's largest allowed value
#: on 64-bit systems (``DEFAULT_MMAP_THRESHOLD_MAX``, 32 MiB): a full-scale frame (13 MiB) and its float32
#: radiance (27 MiB) both fit.
MMAP_THRESHOLD_BYTES = 32 * 2**20
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8
_DONE: dict = {}


def reuse_freed_memory() -> bool:
    """Tell glibc's malloc to keep freed memory for the next arrays (module docstring); once per process.

    Returns
    -------
    bool
        Whether the settings were applied (``False`` on a C library other than glibc).

    References
    ----------
    .. [1] Linux man-pages, mallopt(3): ``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD``, ``M_ARENA_MAX``.
    """
    if "applied" not in _DONE:
        _DONE["applied"] = _apply()
    return _DONE["applied"]


def _apply() -> bool:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # pragma: no cover - glibc always has mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # one arena: threads' freed arrays are reused by the others instead of trimmed from their own heaps
    return all(mallopt(param, value) == 1 for param, value in (
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES), (_M_TRIM_THRESHOLD, 2**31 - 1), (_M_ARENA_MAX, 1)))
