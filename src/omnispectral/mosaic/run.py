"""Running a mosaic's tasks: level 0 tile by tile, then the pyramid level by level, on Dask.

Tiles are independent tasks (:func:`omnispectral.mosaic.tile.tile_task`) run by Dask: the local threaded
scheduler, or a distributed cluster given its address or client (:func:`run_tasks`).  The job every tile
needs is sent once (one graph node locally, one scattered future on a cluster), never per task.  Pyramid
level ``k`` (chunks keep their size, levels halve: chunk ``(ty, tx)`` of level ``k`` covers the level-0
chunks ``(ty·2^k … , tx·2^k …)``) follows chunk by chunk from level ``k − 1``
(:func:`omnispectral.mosaic.tile.pyramid_task`).  An interrupted run resumes: chunks whose completion
markers exist are skipped, and new level-0 chunks mark the pyramid chunks above them stale.

Progress is reported as ``progress("tiles", done, total)`` and ``progress("pyramid", done, total)``
(:data:`omnispectral.progress.ProgressCallback`).
"""

from __future__ import annotations

import uuid
from collections.abc import Callable

from omnispectral.errors import ConfigurationError
from omnispectral.mosaic.options import MosaicOptions
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.mosaic.tile import MosaicJob, pyramid_task, tile_task
from omnispectral.progress import ProgressCallback, report_progress
from omnispectral.threads import single_threaded_libraries, worker_call

__all__ = ["ancestors", "run_level0", "run_pyramid", "run_tasks", "tiles_in"]


def run_tasks(fn, shared, items: list[tuple], scheduler, workers: int | None,
              on_result: Callable[[dict], None] | None) -> list[dict]:
    """Run ``fn(shared, *item)`` for every item with Dask: threads locally, or on the cluster at ``scheduler``.

    Parameters
    ----------
    fn
        The task, ``fn(shared, *item) -> dict``.
    shared
        The object every task receives (sent to the cluster once).
    items
        The tasks' other arguments.
    scheduler
        ``None`` (local threaded scheduler, ``workers`` threads), a scheduler address (``tcp://…``) or a
        ``distributed.Client``.
    workers
        Local threads (``None``: all cores).
    on_result
        Called with each result as it finishes, or ``None``.

    Returns
    -------
    list of dict
        The results (in the order of ``items`` locally, in the order they finished on a cluster).
    """
    if not items:
        return []
    if scheduler is None:
        import dask  # lazy: dask (~0.4 s) and distributed (~0.5 s) serve only the task runner
        from dask.callbacks import Callback

        # one graph node holds ``shared``; the tasks name it by its key.  Passed as an argument as it is,
        # Dask would traverse the job (a dataclass with every source) once per task: ~0.4 ms per source
        # per task, 2 h of graph building for the 7000 tiles × 2520 sources of a gigapixel panorama
        leaf = dask.delayed(shared, name=f"shared-{uuid.uuid4().hex}", traverse=False)
        tasks = [dask.delayed(fn, pure=False)(leaf, *item) for item in items]
        keys = {t.key for t in tasks}

        def posttask(key, result, dsk, state, worker_id):
            if on_result is not None and key in keys:
                on_result(result)

        # Dask's threads are the parallelism: OpenCV's and BLAS's own would oversubscribe the cores (idle OpenBLAS
        # threads spin: 4 CPU-s of a full-scale mosaic's 52 went to spinning before BLAS was held to one thread)
        with Callback(posttask=posttask), single_threaded_libraries():
            return list(dask.compute(*tasks, scheduler="threads", num_workers=workers or None))
    from distributed import Client, as_completed

    # not the default client: dask collections elsewhere in this process keep their own scheduler
    client = scheduler if isinstance(scheduler, Client) else Client(scheduler, set_as_default=False)
    try:
        # hash=False: a new key each time; with the value's hash as key, a client that has just closed (the
        # previous pyramid level) could release the same key under the new one ("lost dependencies")
        remote = client.scatter(shared, broadcast=True, hash=False)
        futures = [client.submit(worker_call, fn, remote, *item, pure=False) for item in items]
        results = []
        for future in as_completed(futures, loop=client.loop):
            results.append(future.result())
            if on_result is not None:
                on_result(results[-1])
        return results
    finally:
        if client is not scheduler:
            client.close()


def tiles_in(store: PanoramaStore, region: tuple[int, int, int, int] | None) -> list[tuple[int, int]]:
    """Level-0 chunks meeting ``region`` (all by default).

    Parameters
    ----------
    store
        The panorama store.
    region
        ``(row0, row1, col0, col1)`` px of level 0, or ``None``.

    Returns
    -------
    list of (int, int)
        ``(ty, tx)`` of the chunks, row by row.
    """
    ny, nx = store.n_chunks(0)
    if region is None:
        return [(ty, tx) for ty in range(ny) for tx in range(nx)]
    r0, r1, c0, c1 = (int(x) for x in region)
    h, w = store.shapes[0]
    if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
        raise ConfigurationError(f"region {region} is not a window of the {w} x {h} panorama")
    t = store.tile
    return [(ty, tx) for ty in range(r0 // t, (r1 - 1) // t + 1) for tx in range(c0 // t, (c1 - 1) // t + 1)]


def ancestors(tiles: list[tuple[int, int]], level: int) -> list[tuple[int, int]]:
    """Chunks of pyramid ``level`` computed from the given level-0 chunks (chunks keep their size, levels halve).

    Parameters
    ----------
    tiles
        Level-0 chunks ``(ty, tx)``.
    level
        The pyramid level.

    Returns
    -------
    list of (int, int)
        ``(ty >> level, tx >> level)``, sorted, each once.
    """
    return sorted({(ty >> level, tx >> level) for ty, tx in tiles})


def run_level0(job: MosaicJob, store: PanoramaStore, tiles: list[tuple[int, int]], options: MosaicOptions,
               progress: ProgressCallback | None) -> int:
    """Render and write the level-0 chunks ``tiles`` not done yet (``progress("tiles", done, total)``).

    Parameters
    ----------
    job
        The run's job.
    store
        The panorama store.
    tiles
        The level-0 chunks the run covers.
    options
        The run's options (scheduler, workers).
    progress
        The progress callback, or ``None``.

    Returns
    -------
    int
        How many chunks were computed (the others were done already).
    """
    done = set(store.done_markers(0))
    todo = [t for t in tiles if t not in done]
    for level in range(1, len(store.shapes)):  # new level-0 chunks make their pyramid chunks stale
        for ty, tx in ancestors(todo, level):
            store.unmark(level, ty, tx)
    total = len(tiles)
    counter = [total - len(todo)]

    def on_tile(result):
        counter[0] += 1
        report_progress(progress, "tiles", counter[0], total)

    run_tasks(tile_task, job, todo, options.scheduler, options.workers, on_tile)
    return len(todo)


def run_pyramid(store: PanoramaStore, tiles: list[tuple[int, int]], options: MosaicOptions,
                progress: ProgressCallback | None) -> None:
    """Make the pyramid chunks above the level-0 chunks ``tiles`` not done yet (``progress("pyramid", done,
    total)``), level by level.

    Parameters
    ----------
    store
        The panorama store.
    tiles
        The level-0 chunks the run covers.
    options
        The run's options (scheduler, workers).
    progress
        The progress callback, or ``None``.
    """
    wanted = {k: ancestors(tiles, k) for k in range(1, len(store.shapes))}
    done = {k: set(store.done_markers(k)) for k in wanted}
    total = sum(len(v) for v in wanted.values())
    counter = [sum(len(done[k] & set(v)) for k, v in wanted.items())]

    def on_chunk(result):
        counter[0] += 1
        report_progress(progress, "pyramid", counter[0], total)

    for level, chunks in wanted.items():
        todo = [c for c in chunks if c not in done[level]]
        run_tasks(pyramid_task, store.path, [(level, ty, tx) for ty, tx in todo], options.scheduler, options.workers,
                  on_chunk)
