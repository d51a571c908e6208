"""Writing product-like directories (``product.json`` + ``panorama.zarr``) from six-band arrays or tile functions.

The relit panorama of :mod:`omnispectral.apps.relight` is such a product, so every tool that reads a
product (``export``, ``spectrum``, ``view``, ``render``) reads it too.  Levels ≥ 1 are the store's 2 × 2 box
averages (``PanoramaStore.downsample_chunk``); chunks are written whole and marked done.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from omnispectral.io import atomic_write_json
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.threads import kernel_threads

PANORAMA = "panorama.zarr"
INDEX = "product.json"


def create_band_product(root: str | Path, height: int, width: int, index: dict, attrs: dict, tile: int = 512,
                        overwrite: bool = True, n_bands: int = 6) -> PanoramaStore:
    """An empty product directory: the store (``(height, width, n_bands)`` + pyramid: six bands, or three for a
    one-camera rig) and ``product.json``."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    store = PanoramaStore.create(root / PANORAMA, height, width, n_bands, tile, attrs,
                                 fingerprint={"written_by": "apps"}, overwrite=overwrite)
    atomic_write_json(root / INDEX, {"format": "omnispectral-product", "panorama": str((root / PANORAMA).resolve()),
                                     "width": width, "height": height, **index})
    return store


def fill_pyramid(store: PanoramaStore) -> None:
    """Write every level ≥ 1 from the level below (2 × 2 box averages, NaN ignored)."""
    for k in range(1, len(store.shapes)):
        arr = store.array(k, mode="r+")
        ny, nx = store.n_chunks(k)
        for ty in range(ny):
            for tx in range(nx):
                store.write_chunk(k, ty, tx, store.downsample_chunk(k, ty, tx), array=arr)


def write_band_product(root: str | Path, bands: np.ndarray, index: dict, attrs: dict | None = None,
                       tile: int = 512) -> PanoramaStore:
    """A whole product from an in-memory panorama ``(H, W, bands)`` (tests, small results)."""
    h, w = bands.shape[:2]
    store = create_band_product(root, h, w, index, attrs or {"bands": index.get("bands")}, tile,
                                n_bands=bands.shape[2])
    write_level0(store, lambda r0, r1, c0, c1: bands[r0:r1, c0:c1])
    fill_pyramid(store)
    return store


def write_level0(store: PanoramaStore, tile_fn: Callable[[int, int, int, int], np.ndarray],
                 workers: int | None = None, progress: Callable[[int, int], None] | None = None) -> list:
    """Level 0 chunk by chunk: ``tile_fn(r0, r1, c0, c1) → (r1-r0, c1-c0, bands)``, run as Dask tasks on threads
    (each task holds one tile: memory is bounded by the tile size times the workers).  Returns each tile's
    ``stats`` when ``tile_fn`` returns ``(data, stats)``."""
    import dask


    arr = store.array(0, mode="r+")
    ny, nx = store.n_chunks(0)
    done = [0]

    def task(ty: int, tx: int):
        r0, r1, c0, c1 = store.chunk_rect(0, ty, tx)
        res = tile_fn(r0, r1, c0, c1)
        data, stats = res if isinstance(res, tuple) else (res, None)
        store.write_chunk(0, ty, tx, np.asarray(data, np.float32), stats=stats, array=arr)
        done[0] += 1
        if progress:
            progress(done[0], ny * nx)
        return stats

    tasks = [dask.delayed(task)(ty, tx) for ty in range(ny) for tx in range(nx)]
    return list(dask.compute(*tasks, scheduler="threads", num_workers=workers or max(1, min(4, kernel_threads()))))


def read_index(root: str | Path) -> dict:
    return json.loads((Path(root) / INDEX).read_text(encoding="utf-8"))
