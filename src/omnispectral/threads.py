"""Thread control for the per-pixel kernels (Wiener estimator, HDR merge).

The kernels split an image into blocks of pixels and run them on a few Python threads (NumPy
releases the GIL in ufuncs and matrix products); BLAS itself is held to one thread meanwhile, so
two levels of parallelism never multiply (OpenBLAS threads spin while waiting: oversubscribed,
they cost 5-8x on a loaded 2-core machine).  Inside somebody else's pool (a Dask worker thread,
a ``ThreadPoolExecutor``) the kernels use one thread: the pool is already the parallelism.

``OMNISPECTRAL_THREADS`` overrides the thread count.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import cv2
from threadpoolctl import ThreadpoolController

__all__ = ["blocks", "kernel_threads", "ordered_thread_map", "single_threaded_blas", "single_threaded_libraries",
           "worker_call"]

_LOCK = threading.Lock()
_DEPTH = 0
_LIMITER = None
_CONTROLLER: ThreadpoolController | None = None


def kernel_threads() -> int:
    """Threads for a per-pixel kernel: ``OMNISPECTRAL_THREADS``, else all usable cores on the main thread, else 1."""
    env = os.environ.get("OMNISPECTRAL_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    if threading.current_thread() is not threading.main_thread():
        return 1
    return max(1, len(os.sched_getaffinity(0)))


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Hold BLAS to one thread while the block is running (re-entrant and safe across threads).

    threadpoolctl limits are process-wide, so nested or concurrent users share one limit: the
    first to enter sets it, the last to leave restores the original.
    """
    global _DEPTH, _LIMITER, _CONTROLLER
    with _LOCK:
        if _DEPTH == 0:
            if _CONTROLLER is None:
                _CONTROLLER = ThreadpoolController()
            _LIMITER = _CONTROLLER.limit(limits=1, user_api="blas")
        _DEPTH += 1
    try:
        yield
    finally:
        with _LOCK:
            _DEPTH -= 1
            if _DEPTH == 0 and _LIMITER is not None:
                _LIMITER.restore_original_limits()
                _LIMITER = None


def blocks(n_items: int, block: int) -> list[slice]:
    """Consecutive slices of at most ``block`` items covering ``range(n_items)``."""
    return [slice(s, min(s + block, n_items)) for s in range(0, n_items, max(1, int(block)))]


@contextmanager
def single_threaded_libraries() -> Iterator[None]:
    """BLAS and OpenCV's own thread pool held to one thread (for work that is parallel across items)."""

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with single_threaded_blas():
            yield
    finally:
        cv2.setNumThreads(before)


def ordered_thread_map(fn: Callable, items: Iterable, workers: int | None = None) -> Iterator:
    """``fn(item)`` for every item on ``workers`` threads (default :func:`kernel_threads`, at most 4), at most
    two items ahead per thread, yielded in order (results can be written as they come; memory bounded).

    Used for per-direction work (camera B's block measurements and parallax): NumPy, SciPy's FFT and
    OpenCV release the GIL, and the libraries' own pools are held to one thread meanwhile.
    """
    items = list(items)
    workers = max(1, min(workers or kernel_threads(), 4))
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


def worker_call(fn: Callable, *args):
    """``fn(*args)`` as a task on a Dask distributed worker, with the libraries' own pools at one thread.

    The worker's threads (``dask worker --nthreads``) and processes are the parallelism: OpenCV's pool
    is set to one thread for the rest of the worker's life (its setting is process-wide, so it is not
    restored while other tasks may run), BLAS to one thread during the call (the nanny usually starts
    workers with ``OPENBLAS_NUM_THREADS=1`` already; a worker started with ``--no-nanny`` does not).
    """
    if cv2.getNumThreads() != 1:
        cv2.setNumThreads(1)
    with single_threaded_blas():
        return fn(*args)
