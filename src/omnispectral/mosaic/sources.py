"""Merged directions: the mosaic engine's input on disk (a raw session is merged into it by ``product.merge``).

Layout (``format = "omnispectral-merged-directions"``, version 1)::

    MERGED/
      merged.json         what is below, the rig snapshot, the camera models and every direction
      d0000_A.npy         camera A of direction 0: (H, W, 3) linear radiance, bands 0..2
      d0000_B.npy         camera B of direction 0: (H, W, 3), bands 3..5
      ...

``merged.json`` holds ``units`` (DN per second of exposure, the HDR merge's unit), ``band_names``
(``A:R … B:B``; ``A:R, A:G, A:B`` for a one-camera rig, which has no ``B`` files), ``camera_bands``
(``{"A": [0, 1, 2], "B": [3, 4, 5]}``), ``cameras`` (each
camera's :class:`~omnispectral.imaging.geometry.CameraModel` as JSON: lens, distortion, mounting),
``rig`` (name and the TOML snapshot of the rig), ``system`` (the six bands' spectral sensitivities,
:meth:`~omnispectral.spectral.system.MultibandSystem.to_dict`, or null), ``session`` (where the frames
came from, or null), ``estimator`` (optional: a spectral estimator to carry into the panorama's metadata),
``dtype`` and ``directions``: a list of ``{"index", "pan_deg", "tilt_deg", "images": {camera:
{"file", "scale", "offset_px": [dx, dy]}}}``.  ``complete`` turns true when every planned
direction is there.

Values.  A stored value times ``scale`` is radiance in DN/s.  The default dtype is float16 with a
per-image power-of-two ``scale`` that puts the image maximum near 2¹⁵: float16 then spans
2⁻¹⁴…2¹⁶ (2³⁰, beyond a 15-exposure bracket's 4 DN / 0.252 s … 4095 DN / 15 µs ≈ 2²⁶) with a
relative step of 2⁻¹¹ (0.05 %), far below a merged pixel's shot noise (~1 % at 80 % of full well).
It halves the disk: 1260 directions × 2 cameras × 2048 × 1088 × 3 are 34 GB in float16 and 67 GB in
float32.  ``.npy`` is deliberately uncompressed: float HDR data compresses poorly (~1.2×) and the
engine reads row bands of a file with ``pread`` (no decompression, no memory map that would
inflate the resident set).  ``dtype = "float32"`` (scale 1) is available for exact round trips.

Checksums.  Each image's (and parallax map's) entry records ``checksum``: the file's CRC-32 and size
(:func:`omnispectral.checksums.file_checksum`), taken when it is written.  Every read checks it first (once per
process and state of the file): a damaged file raises ``InputFileError(path, "damaged: checksum …")``, never
returns wrong radiance; :meth:`MergedDirections.problems` lists the missing and damaged files (``product
verify``, and a resumed ``process``, which merges those directions again).  Entries written before checksums
have none: their files are checked for presence only.

``offset_px`` is camera B's registration offset ``(dx, dy)`` in pixels, added to B's sensor
coordinates (``moving(x, y) ≈ reference(x - dx, y - dy)`` as :mod:`omnispectral.imaging.registration`
reports); camera A's is ``(0, 0)``.

Every file is written to a temporary name and renamed; ``merged.json`` is rewritten after each
direction, so an interrupted merge (:func:`omnispectral.product.merge.merge_session`) resumes where it stopped.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omnispectral.checksums import file_checksum, remembered_problem, verified
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.halffloat import to_float16, to_float32
from omnispectral.io import atomic_path, atomic_write_json

__all__ = ["BAND_NAMES", "CAMERAS", "CAMERA_BANDS", "DTYPES", "FLOAT16_TARGET_MAX", "FORMAT", "FORMAT_VERSION",
           "UNITS", "MergedDirections", "MergedDirectionsWriter", "SourceImage", "encode_image", "entry_sources",
           "float16_scale", "image_filename", "npy_shape", "read_npy_rows", "read_npy_window"]

FORMAT = "omnispectral-merged-directions"
FORMAT_VERSION = 1
CAMERAS = ("A", "B")
CAMERA_BANDS = {"A": (0, 1, 2), "B": (3, 4, 5)}
BAND_NAMES = ("A:R", "A:G", "A:B", "B:R", "B:G", "B:B")
UNITS = "DN per second of exposure"
DTYPES = ("float16", "float32")
#: float16 images are scaled so that their maximum lands at or below this (2¹⁵, half of float16's range).
FLOAT16_TARGET_MAX = 2.0 ** 15


def image_filename(direction: int, camera: str) -> str:
    return f"d{direction:04d}_{camera}.npy"


def float16_scale(image: np.ndarray) -> float:
    """Power-of-two ``scale`` with ``max(image) / scale <= 2¹⁵`` (1 for an image of zeros)."""
    image = np.asarray(image)
    # fmax / fmin skip NaN without a mask or a copy (9x faster than the masked |max| on a frame); an infinite
    # value (or nothing but NaN) takes the masked path, which skips it
    peak = max(float(np.fmax.reduce(image, axis=None, initial=0.0)),
               -float(np.fmin.reduce(image, axis=None, initial=0.0)))
    if not np.isfinite(peak):
        peak = float(np.max(np.abs(image), where=np.isfinite(image), initial=0.0))
    if peak <= 0:
        return 1.0
    return 2.0 ** math.ceil(math.log2(peak / FLOAT16_TARGET_MAX))


def encode_image(image: np.ndarray, dtype: str) -> tuple[np.ndarray, float]:
    """``(stored array, scale)`` with ``stored * scale`` ≈ ``image`` (exact for float32)."""
    image = np.asarray(image, dtype=np.float32)
    if dtype == "float32":
        return image, 1.0
    if dtype != "float16":
        raise ConfigurationError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    scale = float16_scale(image)
    return to_float16(image, 1.0 / scale), scale  # the float32 product rounded once


# ------------------------------------------------------------------------------------------ reading
#: NumPy parses a ``.npy`` header with ``ast.literal_eval``; CPython 3.11's AST construction is not safe while
#: another thread builds an AST (``SystemError: AST constructor recursion depth mismatch``, seen when the
#: parallax thread read a header while a Numba kernel compiled).  The headers ``np.save`` writes are parsed here
#: without the AST; any other layout goes to NumPy's parser, one at a time.
_HEADER_LOCK = threading.Lock()
_PLAIN_HEADER = re.compile(r"\{'descr': '([<>|=]?[a-zA-Z]\d*)', 'fortran_order': (True|False), "
                           r"'shape': \((\d+(?:, \d+)*,?|)\), \}")


def _npy_header(fh) -> tuple[tuple[int, ...], bool, np.dtype]:
    version = np.lib.format.read_magic(fh)
    start = fh.tell()
    n = int.from_bytes(fh.read(2 if version == (1, 0) else 4), "little")
    plain = _PLAIN_HEADER.fullmatch(fh.read(n).decode("latin1").rstrip())
    if plain is not None:
        shape = tuple(int(x) for x in plain[3].split(",") if x.strip())
        return shape, plain[2] == "True", np.dtype(plain[1])
    fh.seek(start)
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    with _HEADER_LOCK:
        shape, fortran, dtype = read(fh)
    return tuple(shape), fortran, dtype


def read_npy_rows(path: Path, row0: int, row1: int) -> np.ndarray:
    """Rows ``[row0, row1)`` of a C-ordered ``.npy`` file, read with ``pread`` (no memory map)."""
    with open(path, "rb") as fh:
        shape, fortran, dtype = _npy_header(fh)
        if fortran:
            raise InputFileError(path, "Fortran-ordered arrays are not supported")
        offset = fh.tell()
        row_items = int(np.prod(shape[1:], dtype=np.int64))
        row0, row1 = max(0, row0), min(shape[0], row1)
        n = max(0, row1 - row0) * row_items
        buf = os.pread(fh.fileno(), n * dtype.itemsize, offset + row0 * row_items * dtype.itemsize)
    if len(buf) != n * dtype.itemsize:
        raise InputFileError(path, f"truncated (rows {row0}..{row1} of {shape[0]})")
    return np.frombuffer(buf, dtype=dtype).reshape((row1 - row0, *shape[1:]))


def read_npy_window(path: Path, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """The window ``[row0, row1) × [col0, col1)`` of a C-ordered ``.npy`` image ``(H, W, …)`` as a new,
    writable, contiguous array: one ``preadv`` per row straight into it, so the kernel copies only the
    window (not whole rows) and no second copy is made."""
    with open(path, "rb") as fh:
        shape, fortran, dtype = _npy_header(fh)
        if fortran:
            raise InputFileError(path, "Fortran-ordered arrays are not supported")
        offset = fh.tell()
        row0, row1 = max(0, rows[0]), min(shape[0], rows[1])
        col0, col1 = max(0, cols[0]), min(shape[1], cols[1])
        out = np.empty((max(0, row1 - row0), max(0, col1 - col0), *shape[2:]), dtype)
        px_bytes = int(np.prod(shape[2:], dtype=np.int64)) * dtype.itemsize
        row_bytes = shape[1] * px_bytes
        if out.size and col0 == 0 and col1 == shape[1]:
            got = [os.preadv(fh.fileno(), [out], offset + row0 * row_bytes)]
        else:
            got = [os.preadv(fh.fileno(), [out[r]], offset + (row0 + r) * row_bytes + col0 * px_bytes)
                   for r in range(out.shape[0])] if out.size else []
    if sum(got) != out.nbytes:
        raise InputFileError(path, f"truncated (rows {row0}..{row1} of {shape[0]})")
    return out


def npy_shape(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    with open(path, "rb") as fh:
        shape, _, dtype = _npy_header(fh)
    return shape, dtype


@dataclass(frozen=True)
class SourceImage:
    """One camera of one direction: its file, scale, registration offset and where the head pointed."""

    direction: int
    camera: str
    pan_deg: float
    tilt_deg: float
    path: Path
    scale: float = 1.0
    offset_px: tuple[float, float] = (0.0, 0.0)
    #: camera B only: per-pixel parallax on camera A's grid of the same direction, ``(H_A, W_A, 3)``
    #: float16 (inverse depth 1/m, registration confidence 0..1, occlusion: 0 seen, 1 hidden from B by a nearer surface,
    #: 2 B shows another surface); see ``product.direction_parallax``
    parallax: Path | None = None
    #: the image file's checksum record (:func:`omnispectral.checksums.file_checksum`; ``None``: written before
    #: checksums were recorded) and the parallax file's
    checksum: dict | None = None
    parallax_checksum: dict | None = None

    @property
    def bands(self) -> tuple[int, ...]:
        return CAMERA_BANDS[self.camera]

    def read_parallax(self, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
        """The window ``rows × cols`` of camera B's parallax map, as stored (checked against its checksum first, as
        :meth:`read`)."""
        return read_npy_window(verified(self.parallax, self.parallax_checksum), rows, cols)

    def read(self, rows: tuple[int, int] | None = None, cols: tuple[int, int] | None = None) -> np.ndarray:
        """Radiance (DN/s) of a crop, float32 ``(rows, cols, 3)``; the whole image by default.

        The file is checked against its checksum first (once per process, :func:`omnispectral.checksums.verified`):
        a damaged file raises ``InputFileError(path, "damaged: checksum …")``.
        """
        verified(self.path, self.checksum)
        if rows is None or cols is None:
            shape = npy_shape(self.path)[0]
            rows, cols = rows or (0, shape[0]), cols or (0, shape[1])
        return to_float32(read_npy_window(self.path, rows, cols), self.scale)


def entry_sources(path: Path, entry: dict, cameras=CAMERAS) -> list[SourceImage]:
    """The images of one direction's ``merged.json`` entry in the directory ``path``, A before B (of ``cameras``)."""
    out = []
    for cam in cameras:
        img = entry["images"].get(cam)
        if img is None:
            continue
        par = img.get("parallax")
        out.append(SourceImage(int(entry["index"]), cam, float(entry["pan_deg"]), float(entry["tilt_deg"]),
                               path / img["file"], float(img.get("scale", 1.0)),
                               tuple(float(x) for x in img.get("offset_px", (0.0, 0.0))),
                               path / par["file"] if par else None, img.get("checksum"),
                               par.get("checksum") if par else None))
    return out


@dataclass
class MergedDirections:
    """A merged-directions directory (see the module docstring); open with :meth:`open`."""

    path: Path
    meta: dict
    cameras: dict[str, CameraModel] = field(init=False)

    def __post_init__(self):
        # absolute: the mosaic's tasks may run in Dask worker processes started in other directories
        self.path = Path(self.path).absolute()
        self.cameras = {c: CameraModel.from_dict(self.meta["cameras"][c]) for c in CAMERAS if c in self.meta["cameras"]}
        if "A" not in self.cameras:
            raise KeyError("camera A")

    @property
    def n_bands(self) -> int:
        """Bands of the panorama these directions make: three per camera (six for cameras A and B)."""
        return 3 * len(self.cameras)

    @classmethod
    def open(cls, path: str | Path, require_complete: bool = True) -> MergedDirections:
        path = Path(path)
        p = path / "merged.json"
        try:
            meta = json.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputFileError(path, "not a merged-directions directory (no merged.json)") from None
        except (OSError, ValueError) as exc:
            raise InputFileError(p, f"unreadable ({exc})") from None
        if meta.get("format") != FORMAT:
            raise InputFileError(p, f"format is {meta.get('format')!r}, expected {FORMAT!r}")
        if meta.get("format_version", 0) > FORMAT_VERSION:
            raise InputFileError(p, f"format version {meta.get('format_version')} is newer than this program's")
        if require_complete and not meta.get("complete", False):
            raise InputFileError(p, f"incomplete: {len(meta.get('directions', []))} of "
                                    f"{meta.get('n_planned', '?')} directions merged")
        try:
            return cls(path, meta)
        except (KeyError, ConfigurationError) as exc:
            raise InputFileError(p, f"bad camera models ({exc})") from None

    @property
    def directions(self) -> list[dict]:
        return self.meta["directions"]

    def sources(self) -> list[SourceImage]:
        """Every (direction, camera) image, in direction order, A before B."""
        return [s for d in self.directions for s in entry_sources(self.path, d, self.cameras)]

    def files(self) -> list[dict]:
        """Every file the directions list: ``{"direction", "kind" ("A", "B" or "P": B's parallax), "path",
        "checksum"}`` (``checksum`` ``None`` for files written before checksums were recorded)."""
        out = []
        for s in self.sources():
            out.append({"direction": s.direction, "kind": s.camera, "path": s.path, "checksum": s.checksum})
            if s.parallax is not None:
                out.append({"direction": s.direction, "kind": "P", "path": s.parallax,
                            "checksum": s.parallax_checksum})
        return out

    def problems(self) -> list[dict]:
        """The listed files that are missing or do not match their checksums: the entries of :meth:`files` with
        ``problem`` (:func:`omnispectral.checksums.remembered_problem`)."""
        out = []
        for f in self.files():
            problem = remembered_problem(f["path"], f["checksum"])  # the mosaic's check_files reads them no more
            if problem is not None:
                out.append({**f, "problem": problem})
        return out

    def check_files(self) -> None:
        """Every listed file exists with the camera's image shape and matches its checksum (camera B's parallax
        maps too); names the first one that does not (``damaged: checksum …``)."""
        for s in self.sources():
            if not s.path.is_file():
                raise InputFileError(s.path, "missing from the merged directions")
            verified(s.path, s.checksum)
            if s.parallax is not None:
                verified(s.parallax, s.parallax_checksum)
            shape, dtype = npy_shape(s.path)
            m = self.cameras[s.camera]
            if shape != (m.height, m.width, 3) or dtype.kind != "f":
                raise InputFileError(s.path, f"shape {shape} {dtype}, expected ({m.height}, {m.width}, 3) float "
                                             f"for camera {s.camera}")


class MergedDirectionsWriter:
    """Writes a merged-directions directory one direction at a time (resumable).

    ``create`` starts it (or reopens one made for the same directions); ``add`` writes one
    direction's two images and records them; ``done`` tells which directions are already there.
    """

    def __init__(self, path: Path, meta: dict):
        self.path = path
        self.meta = meta

    @classmethod
    def create(cls, path: str | Path, cameras: dict[str, CameraModel], directions: list[dict], *,
               rig_name: str = "", rig_toml: str = "", session: dict | None = None, dtype: str = "float16",
               estimator: dict | None = None, band_names=None,
               system: dict | None = None) -> MergedDirectionsWriter:
        """``directions``: the planned ``{"index", "pan_deg", "tilt_deg"}`` (pan/tilt may be updated by ``add``);
        ``cameras``: camera A's model, and camera B's for six bands (band names default to the cameras')."""
        if dtype not in DTYPES:
            raise ConfigurationError(f"dtype must be one of {DTYPES}, got {dtype!r}")
        path = Path(path)
        planned = [int(d["index"]) for d in directions]
        existing = path / "merged.json"
        if existing.exists():
            meta = json.loads(existing.read_text(encoding="utf-8"))
            if meta.get("format") != FORMAT or meta.get("planned") != planned or meta.get("dtype") != dtype:
                raise InputFileError(path, "holds merged directions of another plan or dtype; choose another directory")
            return cls(path, meta)
        names = [c for c in CAMERAS if c in cameras]
        if "A" not in names or len(names) != len(cameras):
            raise ConfigurationError(f"cameras must be A, or A and B; got {', '.join(cameras)}")
        band_names = list(band_names) if band_names is not None else [n for n in BAND_NAMES if n[0] in names]
        if len(band_names) != 3 * len(names):
            raise ConfigurationError(f"{len(band_names)} band names for {len(names)} cameras (three bands each)")
        path.mkdir(parents=True, exist_ok=True)
        meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "created_utc": _utc_now(), "units": UNITS,
                "band_names": band_names, "camera_bands": {c: list(CAMERA_BANDS[c]) for c in names},
                "dtype": dtype, "cameras": {c: cameras[c].to_dict() for c in names},
                "rig": {"name": rig_name, "toml": rig_toml}, "system": system, "session": session,
                "estimator": estimator,
                "n_planned": len(planned), "planned": planned, "complete": False, "directions": []}
        writer = cls(path, meta)
        writer._flush()
        return writer

    def done(self) -> set[int]:
        return {int(d["index"]) for d in self.meta["directions"]}

    def add(self, index: int, pan_deg: float, tilt_deg: float, images: dict[str, np.ndarray],
            offsets_px: dict[str, tuple[float, float]] | None = None, extra: dict | None = None) -> dict:
        """Write one direction: ``images[camera]`` is (H, W, 3) radiance in DN/s."""
        offsets_px = offsets_px or {}
        entry = {"index": int(index), "pan_deg": float(pan_deg), "tilt_deg": float(tilt_deg), "images": {}}
        for cam, image in images.items():
            m = CameraModel.from_dict(self.meta["cameras"][cam])
            if image.shape != (m.height, m.width, 3):
                raise ConfigurationError(f"direction {index} camera {cam}: image {image.shape}, expected "
                                         f"({m.height}, {m.width}, 3)")
            stored, scale = encode_image(image, self.meta["dtype"])
            name = image_filename(index, cam)
            with atomic_path(self.path / name) as tmp, open(tmp, "wb") as fh:
                np.save(fh, stored)
            dx, dy = offsets_px.get(cam, (0.0, 0.0))
            entry["images"][cam] = {"file": name, "scale": scale, "offset_px": [float(dx), float(dy)],
                                    "checksum": file_checksum(self.path / name)}
        entry.update(extra or {})
        self.meta["directions"] = [d for d in self.meta["directions"] if int(d["index"]) != int(index)] + [entry]
        self.meta["directions"].sort(key=lambda d: self.meta["planned"].index(int(d["index"])))
        self.meta["complete"] = len(self.meta["directions"]) == self.meta["n_planned"]
        self._flush()
        return entry

    def save_parallax(self, index: int, data: np.ndarray, info: dict,
                      offset_px: tuple[float, float] = (0.0, 0.0)) -> None:
        """Camera B's per-pixel parallax of direction ``index`` (``(H_A, W_A, 3)``: inverse depth 1/m,
        confidence, occlusion code of :meth:`omnispectral.imaging.parallax.Parallax.occlusion_code`), stored
        float16 as ``dNNNN_P.npy`` and recorded with ``info``; B's offset at
        infinity becomes ``offset_px``."""
        self.record_parallax(index, *self.write_parallax(index, data), info, offset_px)

    def write_parallax(self, index: int, data: np.ndarray) -> tuple[str, str]:
        """The file of :meth:`save_parallax` alone, not yet recorded in ``merged.json`` (safe from another thread
        while this writer adds directions): returns its name and checksum for :meth:`record_parallax`."""
        name = f"d{int(index):04d}_P.npy"
        with atomic_path(self.path / name) as tmp, open(tmp, "wb") as fh:
            np.save(fh, np.asarray(data, np.float16))
        return name, file_checksum(self.path / name)

    def record_parallax(self, index: int, name: str, checksum: str, info: dict,
                        offset_px: tuple[float, float] = (0.0, 0.0)) -> None:
        """Record a parallax file written by :meth:`write_parallax` (the rest of :meth:`save_parallax`)."""
        for d in self.meta["directions"]:
            if int(d["index"]) == int(index):
                d["images"]["B"]["parallax"] = {"file": name, **info, "checksum": checksum}
                d["images"]["B"]["offset_px"] = [float(offset_px[0]), float(offset_px[1])]
        self._flush()

    def set_meta(self, **values) -> None:
        """Update top-level entries of ``merged.json`` (e.g. camera B's calibrated model)."""
        self.meta.update(values)
        self._flush()

    def _flush(self) -> None:
        atomic_write_json(self.path / "merged.json", self.meta)

    def close(self) -> MergedDirections:
        return MergedDirections.open(self.path, require_complete=False)


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
