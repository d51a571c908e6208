"""Running per-direction work on the machine's cores (threads: NumPy, SciPy's FFT and OpenCV release the GIL)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager


@contextmanager
def single_threaded_libraries() -> Iterator[None]:
    """OpenCV's and the BLAS's own thread pools held to one thread (the work is parallel across items:
    nested pools would oversubscribe the cores)."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(1):
            yield
    finally:
        cv2.setNumThreads(before)


def ordered_thread_map(fn: Callable, items: Iterable, workers: int | None = None) -> Iterator:
    """``fn(item)`` for every item, computed on ``workers`` threads (default: the cores, at most 4) two items
    ahead at most per thread, yielded in order (so results can be written as they come, memory bounded)."""
    items = list(items)
    workers = max(1, min(workers or os.cpu_count() or 1, 4))
    if workers == 1 or len(items) < 2:
        yield from (fn(x) for x in items)
        return
    with single_threaded_libraries(), ThreadPoolExecutor(workers) as pool:
        pending = []
        for x in items:
            pending.append(pool.submit(fn, x))
            if len(pending) >= 2 * workers:
                yield pending.pop(0).result()
        for f in pending:
            yield f.result()
