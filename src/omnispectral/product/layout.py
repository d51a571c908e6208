"""A product directory's layout: where its parts live, how to open one, and how to write a product-like one.

A product directory (docs/product.md) holds ``product.json`` (the index), ``panorama.zarr`` (the
six-band panorama, :class:`~omnispectral.mosaic.store.PanoramaStore`), ``merged/`` (the merged
directions), ``rig-calibration.json`` and ``report/``.  Every module that reads or writes a product
takes the paths from here.

Reading: :func:`product_paths`, :func:`read_index` (a missing or unreadable index is an
:class:`~omnispectral.errors.InputFileError`), :func:`open_product`.

Writing a product-like directory (``product.json`` + ``panorama.zarr``) from six-band arrays or tile
functions, as the relit panorama of :mod:`omnispectral.apps.relight` and the tests do, so that every
tool that reads a product (``export``, ``spectrum``, ``view``, ``render``) reads it too:
:func:`create_band_product`, :func:`write_level0` (chunk by chunk), :func:`fill_pyramid` (levels ≥ 1 are
the store's 2 × 2 box averages, ``PanoramaStore.downsample_chunk``), and :func:`write_band_product` for a
whole in-memory panorama.  Chunks are written whole and marked done.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from omnispectral.errors import InputFileError
from omnispectral.io import atomic_write_json
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.estimator import estimator_from_params
from omnispectral.progress import ProgressCallback, report_progress
from omnispectral.threads import kernel_threads

__all__ = ["INDEX", "MERGED", "PANORAMA", "PRODUCT_FORMAT", "RIG_CALIBRATION", "create_band_product",
           "fill_pyramid", "open_product", "product_paths", "read_index", "write_band_product", "write_level0"]

PRODUCT_FORMAT = "omnispectral-product"
#: The index file of a product.
INDEX = "product.json"
PANORAMA = "panorama.zarr"
MERGED = "merged"
#: The rig calibration a product was made with (reusable: ``process --rig-calibration``).
RIG_CALIBRATION = "rig-calibration.json"


def product_paths(product: str | Path) -> dict[str, Path]:
    """The paths of a product directory's parts.

    Parameters
    ----------
    product
        The product directory.

    Returns
    -------
    dict
        ``root``, ``index``, ``panorama``, ``merged``, ``report`` and ``rig_calibration`` paths.
    """
    root = Path(product)
    return {"root": root, "index": root / INDEX, "panorama": root / PANORAMA, "merged": root / MERGED,
            "report": root / "report", "rig_calibration": root / RIG_CALIBRATION}


def read_index(product: str | Path) -> dict:
    """A product's ``product.json``.

    Parameters
    ----------
    product
        The product directory.

    Returns
    -------
    dict
        The index.

    Raises
    ------
    InputFileError
        When the directory or its index is missing, or the index is unreadable.
    """
    paths = product_paths(product)
    try:
        return json.loads(paths["index"].read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputFileError(paths["root"], "not found" if not paths["root"].exists() else
                             "not a processed product (no product.json)") from None
    except (OSError, ValueError) as exc:
        raise InputFileError(paths["index"], f"unreadable ({exc})") from None


def open_product(product: str | Path):
    """Open a processed product directory.

    Parameters
    ----------
    product
        The product directory.

    Returns
    -------
    tuple
        ``(index, PanoramaStore, estimator)``.

    Raises
    ------
    InputFileError
        When the index is missing or unreadable (:func:`read_index`).
    """
    index = read_index(product)
    store = PanoramaStore.open(product_paths(product)["panorama"])
    estimator, _ = estimator_from_params(index["estimator"]["params"])
    return index, store, estimator


def create_band_product(root: str | Path, height: int, width: int, index: dict, attrs: dict, tile: int = 512,
                        overwrite: bool = True, n_bands: int = 6) -> PanoramaStore:
    """An empty product-like directory: the store with its pyramid, and ``product.json``.

    Parameters
    ----------
    root
        The directory (created if needed).
    height, width
        Level-0 size (pixels).
    index
        Entries of ``product.json`` besides ``format``, ``panorama``, ``width`` and ``height``.
    attrs
        The store's metadata.
    tile
        Chunk size (pixels).
    overwrite
        Replace an existing store.
    n_bands
        Bands per pixel: six, or three for a one-camera rig.

    Returns
    -------
    PanoramaStore
        The new, empty store (``(height, width, n_bands)`` and its pyramid).
    """
    paths = product_paths(root)
    paths["root"].mkdir(parents=True, exist_ok=True)
    store = PanoramaStore.create(paths["panorama"], height, width, n_bands, tile, attrs,
                                 fingerprint={"written_by": "apps"}, overwrite=overwrite)
    atomic_write_json(paths["index"], {"format": PRODUCT_FORMAT, "panorama": str(paths["panorama"].resolve()),
                                       "width": width, "height": height, **index})
    return store


def fill_pyramid(store: PanoramaStore) -> None:
    """Write every level ≥ 1 from the level below (2 × 2 box averages, NaN ignored).

    Parameters
    ----------
    store
        A store whose level 0 is written.
    """
    for k in range(1, len(store.shapes)):
        arr = store.array(k, mode="r+")
        ny, nx = store.n_chunks(k)
        for ty in range(ny):
            for tx in range(nx):
                store.write_chunk(k, ty, tx, store.downsample_chunk(k, ty, tx), array=arr)
    store.set_display_windows()


def write_band_product(root: str | Path, bands: np.ndarray, index: dict, attrs: dict | None = None,
                       tile: int = 512) -> PanoramaStore:
    """A whole product-like directory from an in-memory panorama (tests, small results).

    Parameters
    ----------
    root
        The directory.
    bands
        The panorama ``(H, W, bands)``.
    index
        Entries of ``product.json`` (:func:`create_band_product`).
    attrs
        The store's metadata (default ``{"bands": index["bands"]}``).
    tile
        Chunk size (pixels).

    Returns
    -------
    PanoramaStore
        The written store, pyramid included.
    """
    h, w = bands.shape[:2]
    store = create_band_product(root, h, w, index, attrs or {"bands": index.get("bands")}, tile,
                                n_bands=bands.shape[2])
    write_level0(store, lambda r0, r1, c0, c1: bands[r0:r1, c0:c1])
    fill_pyramid(store)
    return store


def write_level0(store: PanoramaStore, tile_fn: Callable[[int, int, int, int], np.ndarray],
                 workers: int | None = None, progress: ProgressCallback | None = None) -> list:
    """Write level 0 chunk by chunk, as Dask tasks on threads.

    Each task holds one tile: memory is bounded by the tile size times the workers.

    Parameters
    ----------
    store
        The store to write.
    tile_fn
        ``tile_fn(r0, r1, c0, c1) → (r1-r0, c1-c0, bands)`` values, or ``(values, stats)``.
    workers
        Threads (default up to 4, at most :func:`omnispectral.threads.kernel_threads`).
    progress
        ``progress("tiles", done, total)`` after each tile.

    Returns
    -------
    list
        Each tile's ``stats`` (``None`` where ``tile_fn`` returns values only).
    """
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
        report_progress(progress or None, "tiles", done[0], ny * nx)
        return stats

    tasks = [dask.delayed(task)(ty, tx) for ty in range(ny) for tx in range(nx)]
    return list(dask.compute(*tasks, scheduler="threads", num_workers=workers or max(1, min(4, kernel_threads()))))
