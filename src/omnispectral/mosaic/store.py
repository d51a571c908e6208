"""The panorama store: an OME-Zarr 0.5 image (Zarr v3 group) with a multiscale pyramid, per-chunk atomic writes
and resume.

Layout (format version 2, docs/product.md)::

    PANO.zarr/
      zarr.json          group; attributes "ome" (OME-NGFF 0.5: version, multiscales with axes c, y, x and each
                         level's scale/translation in degrees) and "omnispectral" (a small summary: format,
                         bands, units, tile, levels, the name of the metadata file)
      omnispectral/zarr.json  a child group without arrays; its attributes hold everything else: sensitivities,
                         wavelengths, estimator, rig, session, cameras, geometry, how it was made, and the run's
                         fingerprint (kept out of the image's zarr.json: it is ~250 kB)
      0/                 (6, H, W) float32, dimension names (c, y, x), chunks (6, tile, tile): DN/s, NaN uncovered
      1/ 2/ …            levels halved by 2 × 2 box averages (ceil sizes) until the long side ≤ tile
      quality/           (2, H, W) float32, (c, y, x): camera B's registration quality (level 0 only, optional)
      k/.done/TY_TX.json a chunk's completion marker, with the statistics of the tile and the chunk file's
                         checksum ("chunk": {"crc32", "bytes"}; level 0 also "quality_chunk" for the quality
                         layer's chunk)

Checksums.  Every array's codecs end with Zarr v3's standard ``crc32c`` codec (stores written before it have
none and still open and resume): every Zarr reader — this package's, xarray's, napari's — refuses a chunk whose
bytes changed instead of decoding wrong numbers.  The markers' CRC-32 records cover the chunk files as they are
on disk (:mod:`omnispectral.checksums`): a resume checks them (:meth:`PanoramaStore.unmark_damaged`) and
recomputes a damaged or missing chunk; ``omnispectral product verify`` checks them all.  Reads through
:class:`ChannelLast` refuse a chunk that is marked done but whose file is gone, or that fails its checksum, with
one line naming the chunk file (:class:`~omnispectral.errors.InputFileError`).

In memory nothing changed: :meth:`PanoramaStore.read` and :meth:`PanoramaStore.array` give ``(H, W, C)``
(:class:`ChannelLast` transposes per request).  Stores of format version 1 (``(H, W, 6)`` on disk, metadata in
``zarr.json``) are still read; resuming one is refused with a message (rerun with ``--overwrite``).

Writes.  A chunk is computed whole and written with one Zarr store call (the local store writes a
temporary file and renames it), then the chunk file is fsynced and its CRC-32 taken, then its marker is
written atomically (temporary name, fsync, rename).  A chunk without a marker is therefore recomputed on
resume, whatever state its file is in, and a marker never exists for a chunk not fully on disk.
``state.json``-like parameters of the run (``fingerprint``) are kept in ``omnispectral/zarr.json``; a
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

from omnispectral.checksums import checksum_problem, file_checksum
from omnispectral.errors import InputFileError, OmnispectralError, os_errno, os_problem
from omnispectral.io import TEMP_MARK, atomic_write_json, follow_umask, jsonable
from omnispectral.mosaic.kernels import compiled_kernels
from omnispectral.ownership import STORE_NAMES, remove_owned_tree

__all__ = [
    "BAND_COLOURS",
    "CHECKSUM_KEYS",
    "DIMENSIONS",
    "DONE_DIR",
    "FORMAT",
    "FORMAT_VERSION",
    "MARKER_NAME",
    "METADATA",
    "OME_VERSION",
    "QUALITY",
    "QUALITY_LAYERS",
    "SUMMARY_KEYS",
    "WINDOW_PERCENTILE",
    "ChannelLast",
    "PanoramaStore",
    "box_average_2x2",
    "chunk_file",
    "multiscales_attr",
    "omero_attr",
    "pyramid_shapes",
]

FORMAT = "omnispectral-panorama"
#: 2: OME-Zarr 0.5, arrays (c, y, x), metadata in ``omnispectral.json``; 1: arrays (y, x, band), all in zarr.json.
FORMAT_VERSION = 2
#: The store's own metadata: a child Zarr group (no arrays) whose attributes hold everything too large for the
#: image group's attributes.  A Zarr node, so that Zarr readers listing the store meet nothing foreign.
METADATA = "omnispectral"
#: OME-NGFF version written under ``attributes.ome``.
OME_VERSION = "0.5"
#: Dimension names of every array (OME-NGFF: channel before space).
DIMENSIONS = ("c", "y", "x")
DONE_DIR = ".done"
MARKER_NAME = re.compile(r"^(\d+)_(\d+)\.json$")
#: Entries of a completion marker that are checksums, not statistics of the tile.
CHECKSUM_KEYS = ("chunk", "quality_chunk")
#: What a damaged chunk's error says to do.
REPAIR_HINT = "'omnispectral process' on the product repairs it"


def chunk_file(array_dir: Path, ty: int, tx: int, channel_first: bool = True) -> Path:
    """The file of chunk ``(ty, tx)`` of an array (format 2: ``c/0/TY/TX``; format 1: ``c/TY/TX/0``)."""
    if channel_first:
        return Path(array_dir) / "c" / "0" / str(ty) / str(tx)
    return Path(array_dir) / "c" / str(ty) / str(tx) / "0"


def pyramid_shapes(height: int, width: int, tile: int) -> list[tuple[int, int]]:
    """Level sizes: level 0 is ``(height, width)``, each next one ``ceil(/2)``, until the long side ≤ ``tile``."""
    shapes = [(height, width)]
    while max(shapes[-1]) > tile:
        h, w = shapes[-1]
        shapes.append((math.ceil(h / 2), math.ceil(w / 2)))
    return shapes


#: Display colour of a band by its channel letter (``A:R`` …): what OME-Zarr viewers (napari) tint it with.
BAND_COLOURS = {"R": "FF0000", "G": "00FF00", "B": "0000FF"}


#: Percentile of a band's finite values that ends its display window (:meth:`PanoramaStore.set_display_windows`).
WINDOW_PERCENTILE = 99.5


def omero_attr(band_names: list[str]) -> dict:
    """OME-NGFF ``omero`` channel metadata: each band's name as its ``label`` (napari and ome-zarr show it), a
    colour from its channel letter, and a display window (0 to 1e6 DN/s until the panorama is written: then
    :meth:`PanoramaStore.set_display_windows` sets it from the data)."""
    return {"channels": [{"label": name, "color": BAND_COLOURS.get(name.rsplit(":", 1)[-1], "FFFFFF"),
                          "active": True, "window": {"min": 0.0, "max": 1e6, "start": 0.0, "end": 1e6}}
                         for name in band_names]}


def multiscales_attr(shapes: list[tuple[int, int]], name: str) -> list[dict]:
    """OME-NGFF 0.5 ``multiscales`` for axes (c, y, x).

    Space is angular: ``x`` is longitude and ``y`` the polar angle from the zenith (90° − latitude), both in
    degrees (a UDUNITS-2 unit; the spec's list of recommended units holds lengths only).  Level ``k``'s pixel is
    ``s_k = 180·2^k / H_0`` degrees on both axes and its pixel 0 is centred at ``(s_k/2, −180 + s_k/2)``: pixel
    ``(col, row)`` of level ``k`` is at ``lon = −180 + (col + ½) s_k``, ``lat = 90 − (row + ½) s_k``.
    """
    h0, _ = shapes[0]
    datasets = []
    for k in range(len(shapes)):
        step = 180.0 * 2 ** k / h0
        datasets.append({"path": str(k), "coordinateTransformations": [
            {"type": "scale", "scale": [1.0, step, step]},
            {"type": "translation", "translation": [0.0, step / 2, -180.0 + step / 2]}]})
    return [{"name": name, "type": "2x2 box average (NaN ignored)",
             "axes": [{"name": "c", "type": "channel"},
                      {"name": "y", "type": "space", "unit": "degree", "longName": "polar angle from the zenith"},
                      {"name": "x", "type": "space", "unit": "degree", "longName": "longitude"}],
             "datasets": datasets,
             "metadata": {"description": "equirectangular; y = 90 - latitude, x = longitude (Mitsuba's envmap "
                                         "orientation); values DN/s per band, NaN where uncovered"}}]


class ChannelLast:
    """A Zarr array seen as ``(H, W, C)`` whatever its order on disk (``(C, H, W)`` in format 2).

    Supports what the package does with arrays: ``shape``, ``dtype``, basic slicing ``a[rows, cols, bands]``
    for reading and ``a[rows, cols, :] = data`` for writing (integer indices keep their axis out, as NumPy).
    """

    def __init__(self, array, path: Path | str | None = None, markers: Path | None = None,
                 record_key: str = "chunk"):
        self.zarr = array
        self.path = path  # the array's directory: named by a write's operating-system error
        names = tuple(getattr(array.metadata, "dimension_names", None) or ())
        self.channel_first = bool(names) and names[0] == DIMENSIONS[0]
        # where the completion markers of this array's chunks are, and which of their records is this array's
        self.markers = Path(markers) if markers is not None and path is not None and self.channel_first else None
        self.record_key = record_key

    @property
    def shape(self) -> tuple[int, int, int]:
        s = self.zarr.shape
        return (s[1], s[2], s[0]) if self.channel_first else tuple(s)

    @property
    def dtype(self):
        return self.zarr.dtype

    @staticmethod
    def _key(key) -> tuple:
        key = key if isinstance(key, tuple) else (key,)
        if any(k is Ellipsis for k in key):
            raise IndexError("ChannelLast takes explicit (rows, cols[, bands]) indices")
        return key + (slice(None),) * (3 - len(key))

    def __getitem__(self, key):
        if not self.channel_first:
            return self.zarr[key]
        rows, cols, bands = self._key(key)
        chunks = self._chunks_of(rows, cols)
        self._check_present(chunks)
        try:
            data = np.asarray(self.zarr[bands, rows, cols])
        except OmnispectralError:
            raise
        except (ValueError, RuntimeError) as exc:  # zarr's crc32c codec (ValueError), a codec fed damaged bytes
            bad = self._damaged_chunk(chunks)
            if bad is None:
                raise
            raise InputFileError(bad, f"damaged: checksum does not match the chunk's bytes ({type(exc).__name__}); "
                                      f"{REPAIR_HINT}") from None
        return data if isinstance(bands, (int, np.integer)) else np.moveaxis(data, 0, -1)

    def _chunks_of(self, rows, cols) -> list[tuple[int, int]]:
        """The chunks ``(ty, tx)`` a read of ``rows × cols`` meets (all of them for indices other than slices)."""
        _, h, w = self.zarr.shape
        _, th, tw = self.zarr.chunks
        spans = []
        for index, size, side in ((rows, h, th), (cols, w, tw)):
            if isinstance(index, (int, np.integer)):
                start = int(index) % size if size else 0
                spans.append(range(start // side, start // side + 1))
            elif isinstance(index, slice) and (index.step or 1) > 0:
                start, stop, _ = index.indices(size)
                spans.append(range(start // side, (stop - 1) // side + 1) if stop > start else range(0))
            else:
                spans.append(range(math.ceil(size / side)))
        return [(ty, tx) for ty in spans[0] for tx in spans[1]]

    def _record(self, ty: int, tx: int) -> dict | None:
        """The checksum record of chunk ``(ty, tx)`` in its completion marker (``None``: not marked, or marked
        before checksums were recorded)."""
        if self.markers is None:
            return None
        try:
            marker = json.loads((self.markers / f"{ty}_{tx}.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        record = marker.get(self.record_key) if isinstance(marker, dict) else None
        return record if isinstance(record, dict) else None

    def _check_present(self, chunks: list[tuple[int, int]]) -> None:
        """Refuse a read meeting a chunk that is marked done (with a checksum) but whose file is gone."""
        if self.markers is None or not self.markers.is_dir():
            return
        for ty, tx in chunks:
            path = chunk_file(Path(self.path), ty, tx)
            if not path.exists() and self._record(ty, tx) is not None:
                raise InputFileError(path, f"missing: the chunk is marked done but its file is gone; {REPAIR_HINT}")

    def _damaged_chunk(self, chunks: list[tuple[int, int]]) -> Path | None:
        """The first of ``chunks`` that cannot be decoded, or ``None``."""
        _, th, tw = self.zarr.chunks
        for ty, tx in chunks:
            try:
                self.zarr[:, ty * th:(ty + 1) * th, tx * tw:(tx + 1) * tw]
            except Exception:
                return chunk_file(Path(self.path), ty, tx) if self.path is not None else Path(f"chunk {ty}/{tx}")
        return None

    def __setitem__(self, key, value) -> None:
        try:
            if not self.channel_first:
                self.zarr[key] = value
                return
            rows, cols, bands = self._key(key)
            value = np.asarray(value)
            if not isinstance(bands, (int, np.integer)):
                value = np.moveaxis(value, -1, 0) if value.ndim == 3 else value
            self.zarr[bands, rows, cols] = np.ascontiguousarray(value)
        except OSError as exc:  # a failed chunk write (disk full) names no file: name the array
            if exc.filename is not None or self.path is None:
                raise
            code = os_errno(exc)
            raise OSError(code, exc.strerror or os_problem(exc), str(self.path)) from exc


def _compressors(name: str) -> tuple:
    """The bytes-to-bytes codecs of every array: the compression, then Zarr's standard ``crc32c`` checksum (4
    bytes per chunk: every Zarr reader refuses a chunk whose bytes changed)."""
    from zarr.codecs import BloscCodec, Crc32cCodec, ZstdCodec

    if name == "none":
        return (Crc32cCodec(),)
    if name == "zstd":
        return (ZstdCodec(level=1), Crc32cCodec())
    if name == "blosc-zstd":
        return (BloscCodec(cname="zstd", clevel=1, shuffle="shuffle", typesize=4), Crc32cCodec())
    raise ValueError(f"unknown compression {name!r}")


#: Name of the registration-quality array (level 0 only).
QUALITY = "quality"
#: The quality array's layers, in order (``mosaic.tile.N_QUALITY``; older products hold a prefix).
QUALITY_LAYERS = ("registration_confidence", "occluded", "sun", "b_predicted", "b_unmixed")
#: Entries of the metadata also kept in the (small) group attributes, for readers that look only there.
SUMMARY_KEYS = ("bands", "units", "camera_bands")


@dataclass
class PanoramaStore:
    """An open panorama store (:meth:`create` or :meth:`open`)."""

    path: Path
    tile: int
    shapes: list[tuple[int, int]]
    n_bands: int
    format_version: int = FORMAT_VERSION

    # ------------------------------------------------------------------ create / open
    @classmethod
    def create(cls, path: str | Path, height: int, width: int, n_bands: int, tile: int, attrs: dict,
               fingerprint: dict, overwrite: bool = False, compression: str = "blosc-zstd",
               quality_bands: int = 0) -> PanoramaStore:
        """Create the store, or reopen it for resuming if it was made with the same ``fingerprint``.

        ``quality_bands > 0`` adds the array ``quality`` (level 0 only, ``(y, x, quality_bands)``
        float32): the registration-quality layer (see ``mosaic.tile.N_QUALITY``).
        """
        import zarr

        path = Path(path)
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()  # an empty directory (a creation killed before its first file) is no store yet
        if path.exists():
            existing = None
            try:
                existing = cls.open(path)
            except InputFileError:  # never deleted, --overwrite or not: only what omnispectral wrote is replaced
                raise InputFileError(path, "exists and is not a panorama store; omnispectral replaces only a store "
                                           "it wrote: choose another output or remove it yourself") from None
            if existing is not None and not overwrite:
                if existing.format_version < FORMAT_VERSION:
                    raise InputFileError(path, f"was written by an older omnispectral (panorama format "
                                               f"{existing.format_version}: channel-last, not OME-Zarr); it can "
                                               f"still be read, but to resume or rebuild it rerun with --overwrite")
                if existing.attrs().get("fingerprint") != jsonable(fingerprint):
                    raise InputFileError(path, "holds a panorama made with other inputs or parameters; rerun with "
                                               "--overwrite or choose another output")
                return existing
            remove_owned_tree(path, STORE_NAMES, "panorama store")  # a user's file inside: refused, nothing removed
        # built under a temporary name and renamed into place: a run killed while creating the store
        # leaves only a ".NAME.omnitmp-…" directory (removed here next time), never a half-made store
        for stale in path.parent.glob(f".{path.name}{TEMP_MARK}*"):
            shutil.rmtree(stale, ignore_errors=True)
        path.parent.mkdir(parents=True, exist_ok=True)
        final, path = path, Path(tempfile.mkdtemp(prefix=f".{path.name}{TEMP_MARK}", dir=path.parent))
        follow_umask(path, directory=True)  # mkdtemp makes it 0o700 whatever the umask
        shapes = pyramid_shapes(height, width, tile)
        group = zarr.open_group(str(path), mode="w", zarr_format=3)
        for k, (h, w) in enumerate(shapes):
            group.create_array(str(k), shape=(n_bands, h, w), chunks=(n_bands, tile, tile), dtype="float32",
                               fill_value=np.nan, compressors=_compressors(compression),
                               dimension_names=DIMENSIONS, config={"write_empty_chunks": True})
        if quality_bands:
            group.create_array(QUALITY, shape=(quality_bands, *shapes[0]), chunks=(quality_bands, tile, tile),
                               dtype="float32", fill_value=np.nan, compressors=_compressors(compression),
                               dimension_names=DIMENSIONS, config={"write_empty_chunks": True})
            layers = list(QUALITY_LAYERS[:quality_bands])
            attrs = {**attrs, "quality": {"array": QUALITY, "layers": layers,
                                          "description": "camera B's registration confidence (0..1, feather-"
                                          "weighted over directions), 1 where B's view of the pixel is "
                                          "hidden by a nearer surface in every direction that sees it, 1 "
                                          "where the pixel holds the recovered sun, the relative error of "
                                          "B's bands where they are predicted from A's (B saw nothing; 0 "
                                          "where B measured them), and the relative error of B's bands where "
                                          "an edge between two surfaces mixes B's two surfaces in A's share "
                                          "(0 where B's own value stands)"}}
        summary = {"format": FORMAT, "format_version": FORMAT_VERSION, "metadata": METADATA, "tile": tile,
                   "levels": [list(s) for s in shapes], "compression": compression,
                   **{k: attrs[k] for k in SUMMARY_KEYS if k in attrs}}
        ome = {"version": OME_VERSION, "multiscales": multiscales_attr(shapes, final.name)}
        if attrs.get("bands"):
            ome["omero"] = omero_attr(list(attrs["bands"]))
        group.attrs.update(jsonable({"ome": ome, "omnispectral": summary}))
        _write_metadata(path, {"omnispectral": {**attrs, **summary}, "fingerprint": fingerprint})
        os.replace(path, final)
        return cls(final, tile, shapes, n_bands, FORMAT_VERSION)

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
        version = int(meta.get("format_version", 1))
        if version > FORMAT_VERSION:
            raise InputFileError(path, f"panorama format {version} is newer than this omnispectral reads "
                                       f"({FORMAT_VERSION}); update omnispectral")
        n_bands = ChannelLast(group["0"]).shape[2]
        return cls(path, int(meta["tile"]), [tuple(s) for s in meta["levels"]], n_bands, version)

    def attrs(self) -> dict:
        """All metadata as one dict: ``omnispectral`` (full), ``fingerprint``, and the group's ``ome``.

        Format 2 keeps the large part in ``omnispectral/zarr.json``; format 1 had everything in ``zarr.json``.
        """
        import zarr

        root = zarr.open_group(str(self.path), mode="r", zarr_format=3).attrs.asdict()
        if self.format_version < 2:
            return root
        extra = _read_metadata(self.path)
        return {**root, **extra, "omnispectral": {**root.get("omnispectral", {}), **extra.get("omnispectral", {})}}

    def set_display_windows(self, percentile: float = WINDOW_PERCENTILE) -> list[tuple[float, float]]:
        """Each band's OME ``omero`` display window from the data: ``start`` 0, ``end`` the band's ``percentile``
        of the finite values of the coarsest level, ``min``/``max`` their range — so that napari and other
        OME-Zarr viewers open the panorama exposed for its sky rather than for 1e6 DN/s (the sun's few pixels
        stay above the window).  Returns ``(end, max)`` per band; a store without ``omero`` is left alone."""
        root = self.path / "zarr.json"
        meta = json.loads(root.read_text(encoding="utf-8"))
        channels = meta.get("attributes", {}).get("ome", {}).get("omero", {}).get("channels")
        if not channels:
            return []
        coarse = self.read(len(self.shapes) - 1)
        windows = []
        for k, channel in enumerate(channels[: coarse.shape[2]]):
            values = coarse[..., k][np.isfinite(coarse[..., k])]
            top = float(values.max()) if values.size else 1e6
            end = float(np.percentile(values, percentile)) if values.size else 1e6
            low = min(0.0, float(values.min())) if values.size else 0.0
            channel["window"] = {"min": low, "max": max(top, end, 1e-30), "start": 0.0, "end": max(end, 1e-30)}
            windows.append((end, top))
        atomic_write_json(root, meta)
        return windows

    def update_attrs(self, values: dict) -> None:
        """Replace top-level metadata entries (``omnispectral``, ``fingerprint``, …) atomically."""
        import zarr

        if self.format_version < 2:
            zarr.open_group(str(self.path), mode="r+", zarr_format=3).attrs.update(jsonable(values))
            return
        _write_metadata(self.path, {**_read_metadata(self.path), **values})

    def array(self, level: int = 0, mode: str = "r") -> ChannelLast:
        """Level ``level`` as an ``(H, W, C)`` array (:class:`ChannelLast`; ``.zarr`` is the array on disk)."""
        import zarr

        where = self.path / str(level)
        return ChannelLast(zarr.open_array(str(where), mode=mode, zarr_format=3), where, where / DONE_DIR)

    def to_xarray(self, level: int = 0):
        """Level ``level`` as a lazy (Dask) ``xarray.DataArray`` with dimensions ``(band, lat, lon)``.

        Read by xarray's own Zarr backend (dimension names from the arrays' ``dimension_names``); the
        coordinates are the pixel centres of docs/product.md (``lat`` descending from the zenith, ``lon``
        from −180°) and the band names; attributes: ``units``.  Format-1 stores come back in the same shape.
        """
        import xarray as xr  # lazy: xarray is only needed by this reader

        others = [str(k) for k in range(len(self.shapes)) if k != level]
        if (self.path / QUALITY / "zarr.json").is_file():
            others.append(QUALITY)
        ds = xr.open_dataset(self.path, engine="zarr", drop_variables=others, chunks={}, consolidated=False,
                             zarr_format=3)
        da = ds[str(level)]
        if self.format_version < 2:
            da = da.rename({"band": "c"}).transpose("c", "y", "x")
        h, w = self.shapes[level]
        step = 180.0 * 2 ** level / self.shapes[0][0]
        meta = self.attrs().get("omnispectral", {})
        bands = list(meta.get("bands") or [f"band{i}" for i in range(self.n_bands)])
        da = da.rename({"c": "band", "y": "lat", "x": "lon"}).assign_coords(
            band=bands, lat=90.0 - (np.arange(h) + 0.5) * step, lon=-180.0 + (np.arange(w) + 0.5) * step)
        da.lat.attrs["units"] = da.lon.attrs["units"] = "degree"
        da.attrs = {"units": meta.get("units", "")}
        return da.rename(f"level{level}")

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
        return chunk_file(self.path / str(level), ty, tx, self.format_version >= 2)

    def _quality_file(self, ty: int, tx: int) -> Path | None:
        """The quality layer's chunk file beside level 0's chunk ``(ty, tx)`` (``None`` without the layer)."""
        return chunk_file(self.path / QUALITY, ty, tx) if self.format_version >= 2 and self.has_quality() else None

    def unmark(self, level: int, ty: int, tx: int) -> None:
        """Forget that a chunk is finished (it will be recomputed)."""
        self._marker(level, ty, tx).unlink(missing_ok=True)

    def done_markers(self, level: int) -> dict[tuple[int, int], dict]:
        """Statistics recorded with every finished chunk of ``level`` (its checksums left out:
        :meth:`chunk_records`)."""
        return {key: {k: v for k, v in marker.items() if k not in CHECKSUM_KEYS}
                for key, marker in self.chunk_records(level).items()}

    def chunk_records(self, level: int) -> dict[tuple[int, int], dict]:
        """Every completion marker of ``level`` as written: statistics and checksums (:data:`CHECKSUM_KEYS`)."""
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
        stats = {k: v for k, v in (stats or {}).items() if k not in CHECKSUM_KEYS}
        atomic_write_json(self._marker(level, ty, tx), {"level": level, "ty": ty, "tx": tx, **stats,
                                                        **self._checksums(level, ty, tx)})

    def _checksums(self, level: int, ty: int, tx: int) -> dict:
        """The chunk's file (and at level 0 the quality layer's chunk), fsynced, as checksum records."""
        out = {}
        files = {"chunk": self._chunk_file(level, ty, tx), "quality_chunk": self._quality_file(ty, tx) if level == 0
                 else None}
        for key, path in files.items():
            if path is None or not path.exists():
                continue
            fd = os.open(path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            out[key] = file_checksum(path)
        return out

    def refresh_checksums(self, level: int, chunks) -> None:
        """Record the current checksums in the markers of ``chunks`` (those marked done) of ``level``, after
        something rewrote them in place (the sun painted into level 0 and its quality layer)."""
        records = self.chunk_records(level)
        for ty, tx in chunks:
            marker = records.get((int(ty), int(tx)))
            if marker is not None:
                atomic_write_json(self._marker(level, ty, tx), {**{k: v for k, v in marker.items()
                                                                   if k not in CHECKSUM_KEYS},
                                                                **self._checksums(level, int(ty), int(tx))})

    def chunks_meeting(self, level: int, rows: tuple[int, int], cols: tuple[int, int]) -> list[tuple[int, int]]:
        """Chunks ``(ty, tx)`` of ``level`` meeting the window ``[row0, row1) × [col0, col1)``."""
        t = self.tile
        return [(ty, tx) for ty in range(rows[0] // t, (rows[1] - 1) // t + 1)
                for tx in range(cols[0] // t, (cols[1] - 1) // t + 1)]

    def chunk_problems(self, level: int) -> list[dict]:
        """The finished chunks of ``level`` whose files are missing or do not match the checksums in their
        markers (level 0: the quality layer's chunk too).

        Markers written before checksums were recorded are not checked.

        Returns
        -------
        list of dict
            ``{"level", "ty", "tx", "path", "problem"}`` per problem (``problem`` from
            :func:`omnispectral.checksums.checksum_problem`).
        """
        out = []
        for (ty, tx), marker in sorted(self.chunk_records(level).items()):
            files = {"chunk": self._chunk_file(level, ty, tx),
                     "quality_chunk": chunk_file(self.path / QUALITY, ty, tx) if level == 0 else None}
            for key, path in files.items():
                record = marker.get(key)
                if path is None or not isinstance(record, dict):
                    continue
                problem = checksum_problem(path, record)
                if problem is not None:
                    out.append({"level": level, "ty": ty, "tx": tx, "path": path, "problem": problem})
        return out

    def unmark_damaged(self) -> list[dict]:
        """Forget the finished chunks of every level that :meth:`chunk_problems` finds (a resume recomputes
        them); returns the problems."""
        problems = [p for level in range(len(self.shapes)) for p in self.chunk_problems(level)]
        for p in problems:
            self.unmark(p["level"], p["ty"], p["tx"])
        return problems

    def write_quality(self, ty: int, tx: int, data: np.ndarray) -> None:
        """Write one chunk of the quality layer (before the chunk of bands and its marker)."""
        r0, r1, c0, c1 = self.chunk_rect(0, ty, tx)
        self._quality("r+")[r0:r1, c0:c1, :] = np.asarray(data, dtype=np.float32)

    def _quality(self, mode: str = "r") -> ChannelLast:
        import zarr

        return ChannelLast(zarr.open_array(str(self.path / QUALITY), mode=mode, zarr_format=3), self.path / QUALITY,
                           self.path / "0" / DONE_DIR, "quality_chunk")

    def has_quality(self) -> bool:
        return (self.path / QUALITY / "zarr.json").is_file()

    def write_quality_layer(self, layer: int, r0: int, cols: np.ndarray, values: np.ndarray) -> bool:
        """Set one layer of the quality array in a window (rows from ``r0``, the given level-0 columns);
        False when the store has no such layer."""
        if not self.has_quality():
            return False
        q = self._quality("r+")
        if q.shape[2] <= layer:
            return False
        for c, col in zip(np.asarray(cols), np.asarray(values, np.float32).T, strict=True):
            q[r0:r0 + len(col), int(c):int(c) + 1, layer:layer + 1] = col[:, None, None]
        return True

    def read_quality(self, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
        """The quality layer ``(h, w, k)``, :data:`QUALITY_LAYERS` (older products hold the first two or
        three); NaN where not computed."""
        return np.asarray(self._quality()[rows, cols, :])

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
    kernels = compiled_kernels()
    if kernels is not None and src.shape[0] <= 2 * h and src.shape[1] <= 2 * w:
        out = np.empty((h, w, c), np.float32)
        kernels.box_average(np.ascontiguousarray(src, np.float32), out)
        return out
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


def _read_metadata(store: Path) -> dict:
    """The attributes of the store's metadata group (format 2)."""
    path = store / METADATA / "zarr.json"
    try:
        return dict(json.loads(path.read_text(encoding="utf-8")).get("attributes") or {})
    except (OSError, ValueError, AttributeError) as exc:
        raise InputFileError(path, f"unreadable ({exc})") from None


def _write_metadata(store: Path, attributes: dict) -> None:
    """Write the metadata group's ``zarr.json`` (a Zarr v3 group, no arrays) atomically."""
    (store / METADATA).mkdir(exist_ok=True)
    atomic_write_json(store / METADATA / "zarr.json", {"zarr_format": 3, "node_type": "group",
                                                       "attributes": jsonable(attributes)})
