"""A product checked against its checksums (``omnispectral product verify``), and the repair a rerun makes.

What is checked:

* every merged image and parallax map ``merged.json`` lists (``PRODUCT/merged/dNNNN_{A,B,P}.npy``): present,
  with the size and CRC-32 recorded when it was written (:mod:`omnispectral.checksums`);
* every chunk of every level of ``panorama.zarr`` and of its quality layer: marked done
  (``k/.done/TY_TX.json``), present, with the size and CRC-32 its marker recorded (and each chunk's own
  CRC-32C, Zarr's ``crc32c`` codec, checked by every Zarr reader).

Files written before checksums were recorded are checked for presence only.  The cost is one read of every
file and its CRC-32 (0.25 ms/MB): measured on the 2-core development machine with the files in the page cache,
0.036 s for a 40 MB product (2048 × 1024 panorama in 128 px tiles: 299 chunks, 36 merged files), i.e. about
1 s per GB (3.5 s per GB on the 2 MB test product, where the per-file overhead dominates); from a disk its read
speed bounds it (a 200 MB/s disk: 5 s per GB).

A rerun of ``process`` repairs what this finds (:func:`drop_damaged_merged` before the merge, then
:meth:`omnispectral.mosaic.store.PanoramaStore.unmark_damaged` in the mosaic).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from omnispectral.errors import InputFileError
from omnispectral.io import atomic_write_json
from omnispectral.mosaic.sources import MergedDirections
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.layout import product_paths

__all__ = ["changed_files", "drop_damaged_merged", "merged_problems", "panorama_problems", "verify_product"]


def merged_problems(merged_dir: str | Path) -> tuple[list[dict], int, int]:
    """The merged files that are missing or do not match their checksums.

    Parameters
    ----------
    merged_dir
        ``PRODUCT/merged``.

    Returns
    -------
    problems : list of dict
        ``{"file", "problem", "direction", "kind"}`` (``kind``: ``"A"``, ``"B"`` or ``"P"``, B's parallax).
    n_files : int
        Files checked.
    size_bytes : int
        Their total size.
    """
    merged_dir = Path(merged_dir)
    if not (merged_dir / "merged.json").is_file():
        return [{"file": str(merged_dir / "merged.json"), "problem": "missing", "direction": None, "kind": None}], 0, 0
    merged = MergedDirections.open(merged_dir, require_complete=False)
    files = merged.files()
    problems = [{"file": str(f["path"]), "problem": f["problem"], "direction": f["direction"], "kind": f["kind"]}
                for f in merged.problems()]
    return problems, len(files), sum(_size(f["path"]) for f in files)


def panorama_problems(store_path: str | Path) -> tuple[list[dict], int, int]:
    """The chunks of the panorama (every level, and the quality layer) that are not done, missing or damaged.

    Parameters
    ----------
    store_path
        ``PRODUCT/panorama.zarr``.

    Returns
    -------
    problems : list of dict
        ``{"file", "problem", "level", "ty", "tx"}``.
    n_chunks : int
        Chunks checked.
    size_bytes : int
        Their total size.
    """
    store = PanoramaStore.open(Path(store_path).absolute())
    problems, n_chunks, size = [], 0, 0
    for level in range(len(store.shapes)):
        ny, nx = store.n_chunks(level)
        done = store.chunk_records(level)
        for ty in range(ny):
            for tx in range(nx):
                if (ty, tx) not in done:
                    problems.append({"file": str(store.path / str(level) / "c" / "0" / str(ty) / str(tx)),
                                     "problem": "not computed (no completion marker)", "level": level, "ty": ty,
                                     "tx": tx})
        for marker in done.values():
            for key in ("chunk", "quality_chunk"):
                if isinstance(marker.get(key), dict):
                    n_chunks += 1
                    size += int(marker[key].get("bytes", 0))
        problems += [{"file": str(p["path"]), "problem": p["problem"], "level": p["level"], "ty": p["ty"],
                      "tx": p["tx"]} for p in store.chunk_problems(level)]
    return problems, n_chunks, size


def verify_product(product: str | Path) -> dict:
    """Check every merged file and every panorama chunk of a product against its checksum and presence.

    Costs one read of every file (module docstring: about 1 s per GB from the page cache, the disk's read speed
    otherwise).

    Parameters
    ----------
    product
        The product directory.

    Returns
    -------
    dict
        ``product``, ``ok`` (no problem), ``problems`` (``{"file", "problem", …}``, merged files first),
        ``n_merged_files``, ``n_chunks``, ``bytes_checked``, ``seconds``.

    Raises
    ------
    InputFileError
        When ``product`` is not a product (no ``panorama.zarr``).
    """
    t0 = time.perf_counter()
    paths = product_paths(product)
    if not paths["panorama"].exists():
        raise InputFileError(paths["root"], "not a product (no panorama.zarr)")
    merged, n_merged, merged_bytes = merged_problems(paths["merged"])
    chunks, n_chunks, chunk_bytes = panorama_problems(paths["panorama"])
    problems = merged + chunks
    return {"product": str(paths["root"]), "ok": not problems, "problems": problems, "n_merged_files": n_merged,
            "n_chunks": n_chunks, "bytes_checked": merged_bytes + chunk_bytes,
            "seconds": round(time.perf_counter() - t0, 3)}


def drop_damaged_merged(merged_dir: str | Path) -> list[dict]:
    """Forget the merged files that are missing or damaged, so that a resumed run makes them again.

    A damaged image (camera A or B) drops its direction from ``merged.json`` (merged again from the session's
    frames, its parallax measured again); a damaged parallax map drops that map only.

    Parameters
    ----------
    merged_dir
        ``PRODUCT/merged`` of a run that resumes.

    Returns
    -------
    list of dict
        ``{"file", "problem", "direction", "kind", "checksum"}`` per dropped file (``checksum``: the record it had,
        to tell whether the file made again is the same, :func:`changed_files`).
    """
    merged_dir = Path(merged_dir)
    path = merged_dir / "merged.json"
    if not path.is_file():
        return []
    merged = MergedDirections.open(merged_dir, require_complete=False)
    damaged = merged.problems()
    if not damaged:
        return []
    meta = json.loads(path.read_text(encoding="utf-8"))
    redo = {int(f["direction"]) for f in damaged if f["kind"] in ("A", "B")}
    reparallax = {int(f["direction"]) for f in damaged if f["kind"] == "P"}
    meta["directions"] = [d for d in meta["directions"] if int(d["index"]) not in redo]
    for d in meta["directions"]:
        if int(d["index"]) in reparallax:
            d["images"]["B"].pop("parallax", None)
    meta["complete"] = len(meta["directions"]) == meta.get("n_planned")
    atomic_write_json(path, meta)
    return [{"file": str(f["path"]), "problem": f["problem"], "direction": f["direction"], "kind": f["kind"],
             "checksum": f["checksum"]} for f in damaged]


def changed_files(dropped: list[dict], merged: MergedDirections) -> list[str]:
    """The files :func:`drop_damaged_merged` dropped that were made again with other bytes than before (or whose
    former bytes are unknown): the panorama made from the former ones is then stale.

    Parameters
    ----------
    dropped
        What :func:`drop_damaged_merged` returned.
    merged
        The merged directions after the run made the files again.

    Returns
    -------
    list of str
        The files.
    """
    now = {str(f["path"]): f["checksum"] for f in merged.files()}
    return [d["file"] for d in dropped if not d["checksum"] or now.get(d["file"]) != d["checksum"]]


def _size(path: Path) -> int:
    try:
        return os.stat(path).st_size
    except OSError:
        return 0
