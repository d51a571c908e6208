"""Dark frames: what each camera records with no light, per exposure of the bracket (``capture darks``).

A dark frame holds the camera's black level (its offset code) plus the sensor's dark signal, which grows
with the exposure time and differs from pixel to pixel (hot pixels; EMVA 1288 calls the spread DSNU).
``record_darks`` averages ``n_frames`` frames per camera and exposure (the lens capped, or the simulated
rig with no light) into ``SESSION/darks/``; ``process`` subtracts the exposure's mean dark frame from
every raw frame instead of the black level alone (:class:`omnispectral.product.merge.RawSettings`).

Layout::

    SESSION/darks/darks.json        index: one entry per camera and exposure index (exposure_s, n_frames, file,
                                    mean and spread of the dark frame in DN), created time
    SESSION/darks/{A,B}_eKK.tif     float32 mean dark frame, the shape of the session's raw frames
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
import tifffile

from omnispectral.capture.devices import Camera
from omnispectral.capture.run import exposure_differs
from omnispectral.capture.session import Session, utc_now_iso
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.io import atomic_path, atomic_write_json
from omnispectral.limits import check_image_header
from omnispectral.locking import directory_lock
from omnispectral.progress import ProgressCallback
from omnispectral.rig import DARK_EXPOSURE_BASE

__all__ = ["DARKS_DIR", "DARKS_INDEX", "DARK_EXPOSURE_TOLERANCE", "DarkFrame", "check_dark_exposure", "dark_frames",
           "dark_relpath", "load_darks", "record_darks"]

DARKS_DIR = "darks"
DARKS_INDEX = "darks.json"
#: Relative difference between a dark frame's exposure and a frame's above which the dark frame does not apply.
DARK_EXPOSURE_TOLERANCE = 0.01


def dark_relpath(camera: str, exposure_index: int) -> str:
    return f"{DARKS_DIR}/{camera}_e{exposure_index:02d}.tif"


def record_darks(session: Session | str | Path, cameras: dict[str, Camera], n_frames: int = 8,
                 timeout_s: float = 30.0, progress: ProgressCallback | None = None) -> dict:
    """Record and average ``n_frames`` dark frames per camera and exposure of the session's plan (its bracket, and
    the exposures of its dark extension at their exposure indices from
    :data:`~omnispectral.rig.DARK_EXPOSURE_BASE`).

    The exposure the camera reports it set is recorded (``exposure_s``; the plan's as ``exposure_s_requested``
    when the camera set another, as the capture records its frames: a camera clamps to its range).  Processing
    subtracts a dark frame only from frames of the same exposure (:func:`check_dark_exposure`), since the dark
    signal grows with it.  Returns the index written to ``darks/darks.json``.
    """
    session = session if isinstance(session, Session) else Session.open(session)
    if n_frames < 1:
        raise ConfigurationError(f"n_frames must be at least 1, got {n_frames}")
    plan = session.plan()
    exposures = dict(enumerate(plan.exposures_s))
    exposures.update({DARK_EXPOSURE_BASE + j: t
                      for j, t in enumerate((plan.dark_extension or {}).get("exposures_s", ()))})
    total = len(exposures) * len(cameras)
    entries = []
    with directory_lock(session.path, "capture darks"):
        (session.path / DARKS_DIR).mkdir(exist_ok=True)
        for i, (k, c) in enumerate((k, c) for k in exposures for c in sorted(cameras)):
            cam = cameras[c]
            actual = float(cam.set_exposure(exposures[k]))
            total_dn = None
            for _ in range(n_frames):
                cam.trigger()
                frame, _meta = cam.read_frame(timeout_s)
                f = frame.astype(np.float64)
                total_dn = f if total_dn is None else total_dn + f
            mean = (total_dn / n_frames).astype(np.float32)
            rel = dark_relpath(c, k)
            with atomic_path(session.path / rel) as tmp:
                tifffile.imwrite(tmp, mean, photometric="rgb" if mean.ndim == 3 else "minisblack", metadata=None)
            entries.append({"camera": c, "exposure_index": k, "exposure_s": actual, "n_frames": n_frames,
                            "file": rel, "shape": list(mean.shape), "mean_dn": float(mean.mean()),
                            "p99_dn": float(np.percentile(mean, 99)), "max_dn": float(mean.max()),
                            **({"exposure_s_requested": exposures[k]} if exposure_differs(exposures[k], actual)
                               else {})})
            if progress is not None:
                progress("darks", i + 1, total)
        index = {"format": "omnispectral-darks", "format_version": 1, "created_utc": utc_now_iso(),
                 "frames": entries}
        atomic_write_json(session.path / DARKS_DIR / DARKS_INDEX, index)
        session.log_event("darks", n_frames=n_frames, n_darks=len(entries))
    return index


class DarkFrame(NamedTuple):
    """A mean dark frame (float32 DN), the exposure it was recorded at (as the camera set it) and its file."""

    data: np.ndarray
    exposure_s: float
    path: Path


def check_dark_exposure(dark: DarkFrame, frame_exposure_s: float, frame_name: str) -> None:
    """Refuse a dark frame recorded at another exposure than the frame it would correct (beyond
    :data:`DARK_EXPOSURE_TOLERANCE`): its dark signal would be scaled wrongly in every pixel."""
    if abs(dark.exposure_s - frame_exposure_s) > DARK_EXPOSURE_TOLERANCE * frame_exposure_s:
        raise InputFileError(dark.path, f"dark frame recorded at {dark.exposure_s:.6g} s, but {frame_name} was "
                                        f"exposed {frame_exposure_s:.6g} s (record the dark frames again: "
                                        "'omnispectral capture darks')")


def load_darks(session_path: str | Path) -> dict[tuple[str, int], np.ndarray]:
    """The session's mean dark frames by (camera, exposure index); empty when none were recorded
    (:func:`dark_frames` without their exposures)."""
    return {k: v.data for k, v in dark_frames(session_path).items()}


def dark_frames(session_path: str | Path) -> dict[tuple[str, int], DarkFrame]:
    """The session's mean dark frames by (camera, exposure index), with the exposure each was recorded at;
    empty when none were recorded.

    A damaged or inconsistent dark frame stops processing with its name (a wrong dark frame would bias
    every pixel silently).
    """
    root = Path(session_path)
    index_path = root / DARKS_DIR / DARKS_INDEX
    if not index_path.exists():
        return {}
    try:
        index = json.loads(index_path.read_text(encoding="utf-8"))
        entries = index["frames"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputFileError(index_path, f"not a dark-frame index ({exc})") from None
    out = {}
    for e in entries:
        p = root / e["file"]
        if not p.is_file():
            raise InputFileError(p, "dark frame missing (listed in darks.json)")
        try:
            check_image_header(p)  # a damaged header claiming gigapixels is refused before decoding
        except InputFileError as exc:
            raise InputFileError(p, f"damaged dark frame ({exc.problem})") from None
        try:
            data = tifffile.imread(p)
        except FileNotFoundError:
            raise InputFileError(p, "dark frame missing (listed in darks.json)") from None
        except Exception as exc:  # tifffile raises several types for damaged files
            raise InputFileError(p, f"damaged dark frame ({type(exc).__name__}: {exc})") from None
        if list(data.shape) != list(e["shape"]):
            raise InputFileError(p, f"shape {list(data.shape)}, darks.json recorded {e['shape']}")
        try:
            exposure_s = float(e["exposure_s"])
        except (KeyError, TypeError, ValueError):
            raise InputFileError(index_path, f"entry for {e['file']} has no exposure_s") from None
        out[(str(e["camera"]), int(e["exposure_index"]))] = DarkFrame(data.astype(np.float32), exposure_s, p)
    return out
