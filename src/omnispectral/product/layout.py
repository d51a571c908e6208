"""Where a product's parts live and how to open one: paths, format name, :func:`open_product`.

A product directory (docs/product.md) holds ``product.json`` (the index), ``panorama.zarr`` (the
six-band panorama, :class:`~omnispectral.mosaic.store.PanoramaStore`), ``merged/`` (the merged
directions), ``rig-calibration.json`` and ``report/``.  Every module of ``product`` that reads or
writes a product takes the paths from here.
"""

from __future__ import annotations

import json
from pathlib import Path

from omnispectral.errors import InputFileError
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.estimator import estimator_from_params

PRODUCT_FORMAT = "omnispectral-product"
PANORAMA = "panorama.zarr"
MERGED = "merged"
#: The rig calibration a product was made with (reusable: ``process --rig-calibration``).
RIG_CALIBRATION = "rig-calibration.json"


def product_paths(product: str | Path) -> dict[str, Path]:
    """The paths of a product directory's parts: root, index, panorama, merged, report, rig_calibration."""
    root = Path(product)
    return {"root": root, "index": root / "product.json", "panorama": root / PANORAMA, "merged": root / MERGED,
            "report": root / "report", "rig_calibration": root / RIG_CALIBRATION}


def read_index(product: str | Path) -> dict:
    """A product's ``product.json``; a missing or unreadable index is an :class:`InputFileError`."""
    paths = product_paths(product)
    try:
        return json.loads(paths["index"].read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputFileError(paths["root"], "not found" if not paths["root"].exists() else
                             "not a processed product (no product.json)") from None
    except (OSError, ValueError) as exc:
        raise InputFileError(paths["index"], f"unreadable ({exc})") from None


def open_product(product: str | Path):
    """``(index, PanoramaStore, estimator)`` of a processed product directory."""
    index = read_index(product)
    store = PanoramaStore.open(product_paths(product)["panorama"])
    estimator, _ = estimator_from_params(index["estimator"]["params"])
    return index, store, estimator
