"""Stage 2 of processing: a raw capture session into merged directions, one direction at a time.

Each direction's brackets are merged per camera (Eqs. (1)-(2), :func:`omnispectral.imaging.merge_exposures`)
and written to a merged-directions directory (:mod:`omnispectral.mosaic.sources`, the mosaic's input)
together with what the mosaic needs and must never re-read from a rig or a session: the camera
models, the bands' spectral sensitivities (``system``, three bands per camera), the rig's name and TOML snapshot and a
summary of the session.  A one-camera rig (camera A alone) gives three-band directions and nothing to
register.  Camera B's registration to A for the paper's method plugs in as ``register``
(:func:`omnispectral.product.process.merge_and_register`); the parallax method runs afterwards on the
merged directions (:func:`omnispectral.product.process.register_parallax`).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from omnispectral.capture.darks import check_dark_exposure, dark_frames
from omnispectral.capture.session import Session, bracket_indices, dark_extensions, frame_relpath
from omnispectral.errors import OmnispectralError
from omnispectral.imaging import merge_exposures
from omnispectral.imaging.bayer import correct_raw, demosaic
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.response import CameraResponse
from omnispectral.mosaic.sources import MergedDirections, MergedDirectionsWriter
from omnispectral.progress import ProgressCallback, report_progress
from omnispectral.rig import RawSpec, rig_toml
from omnispectral.spectral.colour import srgb_decode

__all__ = ["RAW_ORDERS", "READ_THREADS", "Bracket", "RawSettings", "RegisterFn", "calibrated_offset",
           "merge_direction", "merge_session", "read_bracket", "read_direction", "srgb_response"]

#: ``register(direction, image_a, image_b) -> (dx, dy)``: camera B's offset for one direction; it may also
#: return ``(dx, dy, extra)`` with a dict recorded in the direction's entry of ``merged.json``.
RegisterFn = Callable[[int, np.ndarray, np.ndarray], tuple]


def calibrated_offset(offset_px: tuple[float, float] = (0.0, 0.0)) -> RegisterFn:
    """A :data:`RegisterFn` that returns the rig's calibrated offset for every direction."""
    dx, dy = float(offset_px[0]), float(offset_px[1])
    return lambda direction, image_a, image_b: (dx, dy)


@dataclass(frozen=True)
class RawSettings:
    """How one camera's raw frames are corrected and demosaiced before/after the HDR merge.

    ``black_level_dn`` is the rig file's (a frame's own ``camera_metadata.black_level`` wins); ``darks`` maps
    an exposure index to its mean dark frame (:class:`~omnispectral.capture.darks.DarkFrame`), which replaces the
    black level in frames of the exposure it was recorded at (another exposure is refused); ``raw`` is the rig's
    :class:`~omnispectral.rig.RawSpec` (None: RGB frames, unless a frame's metadata names a CFA layout, which is
    then demosaiced with the defaults).
    """

    black_level_dn: float = 0.0
    darks: dict = field(default_factory=dict)
    raw: RawSpec | None = None

    @classmethod
    def of(cls, session: Session, rig, camera: str) -> RawSettings:
        cam = rig.cameras[camera]
        darks = {k: dark for (c, k), dark in dark_frames(session.path).items() if c == camera}
        return cls(cam.black_level_dn, darks, cam.raw)


def srgb_response(bit_depth: int = 8, full_scale_dn: float | None = None) -> CameraResponse:
    """The response of sRGB-encoded images (IEC 61966-2-1): code ``z`` → linear ``decode(z / top) · full_scale``.

    ``full_scale_dn``: the linear value of the largest code, in the rig camera's DN (the import records the
    rig camera's full scale, so an imported JPEG's radiance is in the same DN/s as the camera's raw frames);
    default ``top``."""
    top = (1 << bit_depth) - 1
    scale = float(full_scale_dn) if full_scale_dn else float(top)
    return CameraResponse((srgb_decode(np.arange(top + 1) / top) * scale).astype(np.float32)[:, None], "srgb")


def _demosaic_frames(frames: list[np.ndarray], times: list[float], pattern: str, spec: RawSpec,
                     bit_depth: int) -> list[np.ndarray]:
    """Demosaic every corrected frame (``order = "demosaic-first"``) back to integer codes for the merge.

    Pixels within 2 px of a clipped photosite are set to full scale in all channels (an interpolated value
    next to a clipped one is not trustworthy: the merge then takes them from shorter exposures), except in
    the shortest exposure, which has nothing shorter to fall back on.
    """
    top = (1 << bit_depth) - 1
    shortest = int(np.argmin(times))
    out = []
    for k, f in enumerate(frames):
        rgb = demosaic(f if spec.demosaic == "opencv-ea" else f.astype(np.float32), pattern, spec.demosaic)
        codes = np.clip(np.rint(rgb), 0, top).astype(np.uint16)
        if k != shortest:
            codes[ndimage.maximum_filter(f >= 0.99 * top, size=5)] = top
        out.append(codes)
    return out


@dataclass
class Bracket:
    """One camera's frames of a bracket as read from a session, corrected, ready for the HDR merge."""

    frames: list
    times: list
    pose: tuple[float, float]  # the head's mean reported pan/tilt over the bracket
    bit_depth: int
    pattern: str | None  # the CFA layout of raw mosaics, else None
    merge_options: dict
    filter_name: str | None  # the filter in front of the lens (the sun bracket), else None


def read_bracket(session, direction: int, camera: str, indices, raw: RawSettings | None = None,
                 read: dict | None = None, **merge_options) -> Bracket:
    """Read the frames ``indices`` of one camera in one direction: raw frames corrected
    (:func:`omnispectral.imaging.bayer.correct_raw`: the exposure's dark frame, else the black level), the
    response of imported 8-bit images added to ``merge_options``.  ``read``: frames already read, by exposure
    index (``(pixels, record)`` as ``session.read_frame`` returns them; :func:`read_direction`)."""
    raw = raw or RawSettings()
    frames, times, pans, tilts, bit_depth, pattern, filt = [], [], [], [], 12, None, None
    for k in indices:
        frame, meta = read[k] if read is not None and k in read else session.read_frame(direction, camera, k)
        camera_meta = meta.get("camera_metadata") or {}
        if camera_meta.get("response") == "srgb":  # imported 8-bit images (omnispectral.capture.importer)
            merge_options = {**merge_options, "response": srgb_response(int(meta.get("bit_depth", 8)),
                                                                        camera_meta.get("full_scale_dn"))}
        bit_depth = int(meta.get("bit_depth", bit_depth))
        black = float(camera_meta.get("black_level", raw.black_level_dn))
        dark = raw.darks.get(k)
        if dark is not None:
            check_dark_exposure(dark, float(meta["exposure_s"]), f"frame {frame_relpath(direction, camera, k)}")
        if dark is not None or black:
            frame = correct_raw(frame, bit_depth, black, None if dark is None else dark.data)
        if frame.ndim == 2 and (camera_meta.get("cfa_pattern") or raw.raw is not None):
            pattern = camera_meta.get("cfa_pattern") or raw.raw.cfa_pattern
        frames.append(frame)
        times.append(float(meta["exposure_s"]))
        pans.append(float(meta.get("pan_deg_reported", meta.get("pan_deg_commanded"))))
        tilts.append(float(meta.get("tilt_deg_reported", meta.get("tilt_deg_commanded"))))
        filt = meta.get("filter", filt)
    return Bracket(frames, times, (float(np.mean(pans)), float(np.mean(tilts))), bit_depth, pattern,
                   merge_options, filt)


def _merged_radiance(b: Bracket, frames: list[np.ndarray]) -> np.ndarray:
    """Eq. (1) over ``frames`` of the bracket ``b``: radiance ``(H, W, C)`` (C = 1 for a mosaic)."""
    result = merge_exposures(frames, b.times, b.bit_depth, **b.merge_options)
    return result.radiance if result.radiance.ndim == 3 else result.radiance[..., None]


def _merge_then_demosaic(b: Bracket, spec: RawSpec) -> np.ndarray:
    """``order = "merge-first"``: the mosaics merged, then the merged mosaic demosaiced once."""
    return demosaic(_merged_radiance(b, b.frames)[..., 0], b.pattern, spec.demosaic)


def _demosaic_then_merge(b: Bracket, spec: RawSpec) -> np.ndarray:
    """``order = "demosaic-first"``: every frame demosaiced (:func:`_demosaic_frames`), then merged."""
    return _merged_radiance(b, _demosaic_frames(b.frames, b.times, b.pattern, spec, b.bit_depth))


#: How a raw Bayer bracket is merged, by the rig's ``[cameras.X.raw] order`` (its valid values are the keys,
#: as :data:`omnispectral.imaging.bayer.ORDERS`): ``merge(bracket, spec) -> radiance (H, W, 3)``.
RAW_ORDERS: dict[str, Callable[[Bracket, RawSpec], np.ndarray]] = {
    "merge-first": _merge_then_demosaic,
    "demosaic-first": _demosaic_then_merge,
}


#: Threads reading (and checking) the next direction's frames: file reads, SHA-256 and TIFF decoding release the GIL.
READ_THREADS = 2


def _exposure_indices(exposures: int | Sequence[int]) -> list[int]:
    return list(range(exposures)) if isinstance(exposures, int) else [int(k) for k in exposures]


def read_direction(session, direction: int, cameras, exposures: int | Sequence[int]) -> dict[str, dict]:
    """Every frame of one direction's brackets, ``{camera: {exposure index: (pixels, record)}}``, read (and checked,
    :meth:`~omnispectral.capture.session.Session.check_frames_on_read`) as ``session.read_frame`` does, on
    :data:`READ_THREADS` threads: what :func:`merge_session` reads for the next direction while the current one
    merges.  ``exposures``: the bracket's exposure indices (:func:`~omnispectral.capture.session.bracket_indices`),
    or their count ``n`` (indices ``0 .. n - 1``)."""
    keys = [(c, k) for c in cameras for k in _exposure_indices(exposures)]
    with ThreadPoolExecutor(max_workers=READ_THREADS, thread_name_prefix="frame") as pool:
        frames = list(pool.map(lambda key: session.read_frame(direction, *key), keys))
    out: dict[str, dict] = {c: {} for c in cameras}
    for (c, k), frame in zip(keys, frames, strict=True):
        out[c][k] = frame
    return out


def merge_direction(session, direction: int, camera: str, exposures: int | Sequence[int],
                    raw: RawSettings | None = None,
                    read: dict | None = None, **merge_options) -> tuple[np.ndarray, tuple[float, float]]:
    """HDR merge (Eqs. (1)-(2)) of one camera's bracket; returns radiance (H, W, 3) and the reported pan/tilt.

    Frames are read and corrected by :func:`read_bracket`; Bayer mosaics are merged and then demosaiced once,
    or demosaiced frame by frame and then merged, as the rig's ``[cameras.X.raw] order`` says
    (:data:`RAW_ORDERS`, :mod:`omnispectral.imaging.bayer`).

    Parameters
    ----------
    session : Session
        The open capture session.
    direction : int
        The direction's index in the plan.
    camera : str
        ``"A"`` or ``"B"``.
    exposures : int or sequence of int
        Exposure indices of the bracket (with a dark extension, its frames too:
        :func:`~omnispectral.capture.session.bracket_indices`), or their count ``n`` (indices ``0 .. n - 1``).
    raw : RawSettings, optional
        The camera's black level (DN), dark frames and raw layout (default: no correction, RGB frames).
    read : dict, optional
        The bracket's frames already read, by exposure index (:func:`read_direction`); others are read here.
    **merge_options
        Keyword arguments of :func:`~omnispectral.imaging.hdr.merge_exposures` (``weight``, ``noise``,
        ``deghost``, ...); imported sRGB images add their ``response``.

    Returns
    -------
    radiance : numpy.ndarray
        ``(H, W, 3)`` float32 HDR radiance in DN/s (Eq. (1)).
    pose : tuple of float
        The head's mean reported ``(pan, tilt)`` over the bracket (degrees).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.1, Eqs. (1)-(2) (the HDR merge of each direction's bracket).
    .. [2] D. Menon, S. Andriani, G. Calvagno, "Demosaicing with directional filtering and a posteriori
       decision", IEEE TIP 16(1), 2007 (the default demosaicing of raw mosaics).
    """
    raw = raw or RawSettings()
    b = read_bracket(session, direction, camera, _exposure_indices(exposures), raw, read, **merge_options)
    if b.pattern is None:  # RGB frames
        return _merged_radiance(b, b.frames), b.pose
    spec = raw.raw or RawSpec()
    return RAW_ORDERS[spec.order](b, spec), b.pose


def merge_session(session: Session | str | Path, output: str | Path, *, register: RegisterFn | None = None,
                  dtype: str = "float16", progress: ProgressCallback | None = None,
                  skip: Collection[int] = (), cameras: dict[str, CameraModel] | None = None,
                  written: Callable[[dict], None] | None = None, **merge_options) -> MergedDirections:
    """Stream a raw capture session into a merged-directions directory, one direction at a time.

    Each direction's brackets are merged (:func:`omnispectral.imaging.merge_exposures`, options passed
    through), camera B's offset comes from ``register`` (default: the calibrated offset 0 — the
    end-to-end pipeline plugs phase-only correlation in here), the pan/tilt recorded is the mean
    position the head reported during the bracket, and the images are written before the next
    direction is read, so memory holds one direction.  Directions already written are skipped, and
    so are the planned directions in ``skip`` (e.g. ones with damaged frames), which are not planned here.
    ``session`` is an open :class:`Session` or its directory; ``cameras`` the rig's camera models when the
    caller has them already (default: built from the session's rig).  ``progress("merge", done, total)`` after
    each direction.

    Parameters
    ----------
    session : Session or str or pathlib.Path
        The capture session, open or its directory.
    output : str or pathlib.Path
        The merged-directions directory (``merged.json`` and the images); a partial one is resumed.
    register : RegisterFn, optional
        ``register(direction, image_a, image_b) -> (dx, dy[, extra])``: camera B's sensor offset (px) per
        direction; default :func:`calibrated_offset` (0, 0).
    dtype : str
        Storage type of the merged images (``"float16"`` or ``"float32"``).
    progress : ProgressCallback, optional
        ``progress("merge", done, total)`` after each direction.
    skip : collection of int
        Direction indices left out (not planned in the output).
    cameras : dict of str to CameraModel, optional
        The rig's camera models (default: built from the session's rig).
    written : callable, optional
        ``written(entry)`` after each direction is written, with its ``merged.json`` entry (e.g. to start the
        next stage's work on it while the merge goes on).
    **merge_options
        Keyword arguments of :func:`~omnispectral.imaging.hdr.merge_exposures`, for every bracket.

    Returns
    -------
    MergedDirections
        The merged directions, open: per direction and camera the HDR radiance (DN/s), the reported pan and
        tilt, camera B's offset, plus the camera models, the bands' sensitivities and the rig snapshot.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.1, Eqs. (1)-(2) (HDR synthesis), Sec. 4.3 (camera B's
       registration, plugged in as ``register``), Fig. 5 (the processing flow).
    """
    session = session if isinstance(session, Session) else Session.open(session)
    rig = session.rig()
    plan = session.plan()
    register = register or calibrated_offset()
    names = rig.camera_names
    cameras = {c: m for c, m in cameras.items() if c in names} if cameras else \
        {c: rig.camera_model(c) for c in names}
    directions = [d for d in plan.directions if d.index not in set(skip)]
    raw = {c: RawSettings.of(session, rig, c) for c in names}
    writer = MergedDirectionsWriter.create(
        output, cameras, [d.to_dict() for d in directions], rig_name=rig.name, rig_toml=rig_toml(rig),
        session={"path": str(session.path.resolve()), **_session_summary(session)}, dtype=dtype,
        system=_system_or_none(rig))
    done = writer.done()
    n = len(directions)
    extensions = dark_extensions(session, plan)
    indices = {d.index: bracket_indices(plan, extensions.get(d.index, 0)) for d in directions}
    todo = [d for d in directions if d.index not in done]
    # the next direction's frames are read (decoded, checked) on a worker thread while this one merges: file
    # reads, SHA-256 and TIFF decoding release the GIL; memory holds one direction's frames more
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="frames") as reader:
        ahead = reader.submit(read_direction, session, todo[0].index, names, indices[todo[0].index]) if todo else None
        for i, d in enumerate(directions):
            if d.index not in done:
                frames = ahead.result()
                later = todo.index(d) + 1
                ahead = reader.submit(read_direction, session, todo[later].index, names, indices[todo[later].index]) \
                    if later < len(todo) else None
                images, (pan, tilt) = {}, (0.0, 0.0)
                for c in names:
                    images[c], pose = merge_direction(session, d.index, c, indices[d.index], raw[c], frames[c],
                                                      **merge_options)
                    if c == "A":
                        pan, tilt = pose
                del frames
                dx, dy, *rest = register(d.index, images["A"], images["B"]) if "B" in images else (0.0, 0.0)
                entry = writer.add(d.index, pan, tilt, images, {"B": (dx, dy)} if "B" in images else {},
                                   {"pan_deg_commanded": d.pan_deg, "tilt_deg_commanded": d.tilt_deg,
                                    **(rest[0] if rest else {})})
                del images
                if written is not None:
                    written(entry)
            report_progress(progress, "merge", i + 1, n)
    return MergedDirections.open(output)


def _system_or_none(rig) -> dict | None:
    """The rig's bands' sensitivities for ``merged.json`` (``None`` when the rig names curves this package
    does not know: the mosaic then records no sensitivities, as before)."""
    try:
        return rig.system().to_dict()
    except (OmnispectralError, KeyError, ValueError):
        return None


def _session_summary(session) -> dict:
    meta = session.metadata()
    keep = ("kind", "rig", "created_utc", "format_version")
    out = {k: meta[k] for k in keep if k in meta}
    if "simulation" in meta:
        out["simulation"] = meta["simulation"]
    return out
