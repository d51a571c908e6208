"""The panorama store: a Zarr (v3) group with a multiscale pyramid, per-chunk atomic writes and resume.

Layout::

    PANO.zarr/
      zarr.json          group; attributes "omnispectral" (bands, sensitivities, wavelengths, estimator,
                         rig, session, geometry, how it was made) and "multiscales" (the levels)
      0/                 (H, W, 6) float32, chunks (tile, tile, 6): the panorama, DN/s, NaN where uncovered
      1/ 2/ …            levels halved by 2 × 2 box averages (ceil sizes) until the long side ≤ tile
      k/.done/TY_TX.json a chunk's completion marker, with the statistics of the tile

Writes.  A chunk is computed whole and written with one Zarr store call (the local store writes a
temporary file and renames it), then the chunk file is fsynced, then its marker is written
atomically (temporary name, fsync, rename).  A chunk without a marker is therefore recomputed on
resume, whatever state its file is in, and a marker never exists for a chunk not fully on disk.
``state.json``-like parameters of the run (``fingerprint``) are kept in the group attributes; a
resume with other parameters is refused unless the store is overwritten.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnispectral.errors import InputFileError
from omnispectral.io import TEMP_MARK, atomic_write_json

FORMAT = "omnispectral-panorama"
FORMAT_VERSION = 1
DONE_DIR = ".done"
MARKER_NAME = re.compile(r"^(\d+)_(\d+)\.json$")


def pyramid_shapes(height: int, width: int, tile: int) -> list[tuple[int, int]]:
    """Level sizes: level 0 is ``(height, width)``, each next one ``ceil(/2)``, until the long side ≤ ``tile``."""
    shapes = [(height, width)]
    while max(shapes[-1]) > tile:
        h, w = shapes[-1]
        shapes.append((math.ceil(h / 2), math.ceil(w / 2)))
    return shapes


def multiscales_attr(shapes: list[tuple[int, int]], name: str) -> list[dict]:
    """OME-NGFF-style ``multiscales`` for axes (y, x, band): each level's pixel size in degrees."""
    h0, w0 = shapes[0]
    datasets = []
    for k in range(len(shapes)):
        datasets.append({"path": str(k), "coordinateTransformations": [
            {"type": "scale", "scale": [180.0 * 2 ** k / h0, 360.0 * 2 ** k / w0, 1.0]}]})
    return [{"version": "0.5-omnispectral", "name": name, "type": "2x2 box average (NaN ignored)",
             "axes": [{"name": "y", "type": "space", "unit": "degree"},
                      {"name": "x", "type": "space", "unit": "degree"},
                      {"name": "band", "type": "channel"}],
             "datasets": datasets}]


def _compressors(name: str):
    from zarr.codecs import BloscCodec, ZstdCodec

    if name == "none":
        return None
    if name == "zstd":
        return (ZstdCodec(level=1),)
    if name == "blosc-zstd":
        return (BloscCodec(cname="zstd", clevel=1, shuffle="shuffle", typesize=4),)
    raise ValueError(f"unknown compression {name!r}")


#: Name of the registration-quality array (level 0 only).
QUALITY = "quality"


@dataclass
class PanoramaStore:
    """An open panorama store (:meth:`create` or :meth:`open`)."""

    path: Path
    tile: int
    shapes: list[tuple[int, int]]
    n_bands: int

    # ------------------------------------------------------------------ create / open
    @classmethod
    def create(cls, path: str | Path, height: int, width: int, n_bands: int, tile: int, attrs: dict,
               fingerprint: dict, overwrite: bool = False, compression: str = "blosc-zstd",
               quality_bands: int = 0) -> PanoramaStore:
        """Create the store, or reopen it for resuming if it was made with the same ``fingerprint``.

        ``quality_bands > 0`` adds the array ``quality`` (level 0 only, ``(y, x, quality_bands)``
        float32): the registration-quality layer (see ``mosaic.engine.N_QUALITY``).
        """
        import zarr

        path = Path(path)
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()  # an empty directory (a creation killed before its first file) is no store yet
        if path.exists():
            existing = None
            try:
                existing = cls.open(path)
            except InputFileError:
                if not overwrite:
                    raise InputFileError(path, "exists and is not a panorama store; choose another output or "
                                               "overwrite it") from None
            if existing is not None and not overwrite:
                if existing.attrs().get("fingerprint") != _jsonable(fingerprint):
                    raise InputFileError(path, "holds a panorama made with other inputs or parameters; rerun with "
                                               "--overwrite or choose another output")
                return existing
            shutil.rmtree(path)
        # built under a temporary name and renamed into place: a run killed while creating the store
        # leaves only a ".NAME.omnitmp-…" directory (removed here next time), never a half-made store
        for stale in path.parent.glob(f".{path.name}{TEMP_MARK}*"):
            shutil.rmtree(stale, ignore_errors=True)
        path.parent.mkdir(parents=True, exist_ok=True)
        final, path = path, Path(tempfile.mkdtemp(prefix=f".{path.name}{TEMP_MARK}", dir=path.parent))
        shapes = pyramid_shapes(height, width, tile)
        group = zarr.open_group(str(path), mode="w", zarr_format=3)
        for k, (h, w) in enumerate(shapes):
            group.create_array(str(k), shape=(h, w, n_bands), chunks=(tile, tile, n_bands), dtype="float32",
                               fill_value=np.nan, compressors=_compressors(compression),
                               dimension_names=("y", "x", "band"), config={"write_empty_chunks": True})
        if quality_bands:
            group.create_array(QUALITY, shape=(*shapes[0], quality_bands), chunks=(tile, tile, quality_bands),
                               dtype="float32", fill_value=np.nan, compressors=_compressors(compression),
                               dimension_names=("y", "x", "quality"), config={"write_empty_chunks": True})
            attrs = {**attrs, "quality": {"array": QUALITY, "layers": ["registration_confidence", "occluded"],
                                          "description": "camera B's registration confidence (0..1, feather-"
                                          "weighted over directions) and 1 where B's view of the pixel is "
                                          "hidden by a nearer surface in every direction that sees it"}}
        meta = {"omnispectral": {**attrs, "format": FORMAT, "format_version": FORMAT_VERSION, "tile": tile,
                                 "levels": [list(s) for s in shapes], "compression": compression},
                "multiscales": multiscales_attr(shapes, final.name), "fingerprint": fingerprint}
        group.attrs.update(_jsonable(meta))
        os.replace(path, final)
        return cls(final, tile, shapes, n_bands)

    @classmethod
    def open(cls, path: str | Path) -> PanoramaStore:
        import zarr

        path = Path(path)
        try:
            group = zarr.open_group(str(path), mode="r", zarr_format=3)
        except Exception as exc:  # zarr raises several types for a missing or foreign store
            raise InputFileError(path, f"not a Zarr v3 group ({type(exc).__name__})") from None
        meta = group.attrs.asdict().get("omnispectral", {})
        if meta.get("format") != FORMAT:
            raise InputFileError(path, "not an omnispectral panorama store")
        return cls(path, int(meta["tile"]), [tuple(s) for s in meta["levels"]], int(group["0"].shape[2]))

    def attrs(self) -> dict:
        import zarr

        return zarr.open_group(str(self.path), mode="r", zarr_format=3).attrs.asdict()

    def update_attrs(self, values: dict) -> None:
        import zarr

        zarr.open_group(str(self.path), mode="r+", zarr_format=3).attrs.update(_jsonable(values))

    def array(self, level: int = 0, mode: str = "r"):
        import zarr

        return zarr.open_array(str(self.path / str(level)), mode=mode, zarr_format=3)

    # ------------------------------------------------------------------ chunks
    def n_chunks(self, level: int) -> tuple[int, int]:
        h, w = self.shapes[level]
        return math.ceil(h / self.tile), math.ceil(w / self.tile)

    def chunk_rect(self, level: int, ty: int, tx: int) -> tuple[int, int, int, int]:
        h, w = self.shapes[level]
        t = self.tile
        return ty * t, min(h, (ty + 1) * t), tx * t, min(w, (tx + 1) * t)

    def _marker(self, level: int, ty: int, tx: int) -> Path:
        return self.path / str(level) / DONE_DIR / f"{ty}_{tx}.json"

    def _chunk_file(self, level: int, ty: int, tx: int) -> Path:
        return self.path / str(level) / "c" / str(ty) / str(tx) / "0"

    def is_done(self, level: int, ty: int, tx: int) -> bool:
        return self._marker(level, ty, tx).is_file()

    def unmark(self, level: int, ty: int, tx: int) -> None:
        """Forget that a chunk is finished (it will be recomputed)."""
        self._marker(level, ty, tx).unlink(missing_ok=True)

    def done_markers(self, level: int) -> dict[tuple[int, int], dict]:
        """Statistics recorded with every finished chunk of ``level``."""
        out = {}
        d = self.path / str(level) / DONE_DIR
        if not d.is_dir():
            return out
        for p in d.iterdir():
            m = MARKER_NAME.match(p.name)  # temporary files (".NAME.omnitmp-…") never match
            if m is None:
                continue
            ty, tx = int(m.group(1)), int(m.group(2))
            try:
                out[(ty, tx)] = json.loads(p.read_text(encoding="utf-8"))
            except ValueError:
                continue  # cannot happen with atomic writes; a foreign file is ignored
        return out

    def write_chunk(self, level: int, ty: int, tx: int, data: np.ndarray, stats: dict | None = None,
                    array=None) -> None:
        """Write one whole chunk, make it durable, then mark it done (module docstring)."""
        r0, r1, c0, c1 = self.chunk_rect(level, ty, tx)
        if data.shape != (r1 - r0, c1 - c0, self.n_bands):
            raise ValueError(f"chunk ({ty}, {tx}) of level {level} needs shape {(r1 - r0, c1 - c0, self.n_bands)}, "
                             f"got {data.shape}")
        arr = array if array is not None else self.array(level, mode="r+")
        arr[r0:r1, c0:c1, :] = np.ascontiguousarray(data, dtype=np.float32)
        chunk = self._chunk_file(level, ty, tx)
        if chunk.exists():
            fd = os.open(chunk, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        atomic_write_json(self._marker(level, ty, tx), {"level": level, "ty": ty, "tx": tx, **(stats or {})})

    def write_quality(self, ty: int, tx: int, data: np.ndarray) -> None:
        """Write one chunk of the quality layer (before the chunk of bands and its marker)."""
        import zarr

        r0, r1, c0, c1 = self.chunk_rect(0, ty, tx)
        arr = zarr.open_array(str(self.path / QUALITY), mode="r+", zarr_format=3)
        arr[r0:r1, c0:c1, :] = np.ascontiguousarray(data, dtype=np.float32)

    def has_quality(self) -> bool:
        return (self.path / QUALITY / "zarr.json").is_file()

    def read_quality(self, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
        """The quality layer ``(h, w, 2)`` (registration confidence, occluded); NaN where not computed."""
        import zarr

        return np.asarray(zarr.open_array(str(self.path / QUALITY), mode="r", zarr_format=3)[rows, cols, :])

    def read(self, level: int = 0, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
        return np.asarray(self.array(level)[rows, cols, :])

    # ------------------------------------------------------------------ pyramid
    def downsample_chunk(self, level: int, ty: int, tx: int) -> np.ndarray:
        """Chunk ``(ty, tx)`` of ``level`` (≥ 1) as 2 × 2 box averages of ``level - 1`` (NaN ignored)."""
        r0, r1, c0, c1 = self.chunk_rect(level, ty, tx)
        h_src, w_src = self.shapes[level - 1]
        src = self.read(level - 1, slice(2 * r0, min(h_src, 2 * r1)), slice(2 * c0, min(w_src, 2 * c1)))
        return box_average_2x2(src, (r1 - r0, c1 - c0))


def box_average_2x2(src: np.ndarray, out_shape: tuple[int, int]) -> np.ndarray:
    """2 × 2 block means of ``src`` (h, w, c) onto ``out_shape`` (edge blocks may hold fewer pixels); NaN ignored."""
    h, w = out_shape
    c = src.shape[2]
    padded = np.full((2 * h, 2 * w, c), np.nan, np.float32)
    padded[:src.shape[0], :src.shape[1]] = src
    blocks = padded.reshape(h, 2, w, 2, c)
    finite = np.isfinite(blocks)
    count = finite.sum(axis=(1, 3))
    total = np.where(finite, blocks, 0.0).sum(axis=(1, 3), dtype=np.float64)
    out = np.full((h, w, c), np.nan, np.float32)
    ok = count > 0
    out[ok] = (total[ok] / count[ok]).astype(np.float32)
    return out


def _jsonable(x):
    return json.loads(json.dumps(x, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
