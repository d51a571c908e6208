"""Stage 2 of processing: a raw capture session into merged directions, one direction at a time.

Each direction's brackets are merged per camera (Eqs. (1)-(2), :func:`omnispectral.imaging.merge_exposures`)
and written to a merged-directions directory (:mod:`omnispectral.mosaic.sources`, the mosaic's input)
together with what the mosaic needs and must never re-read from a rig or a session: the two camera
models, the six bands' spectral sensitivities (``system``), the rig's name and TOML snapshot and a
summary of the session.  Camera B's registration to A for the paper's method plugs in as ``register``
(:func:`omnispectral.product.process.merge_and_register`); the parallax method runs afterwards on the
merged directions (:func:`omnispectral.product.process.register_parallax`).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from pathlib import Path

import numpy as np

from omnispectral.capture.session import Session
from omnispectral.errors import OmnispectralError
from omnispectral.imaging import merge_exposures
from omnispectral.imaging.geometry import CameraModel
from omnispectral.mosaic.sources import CAMERAS, MergedDirections, MergedDirectionsWriter
from omnispectral.rig import rig_toml

#: ``register(direction, image_a, image_b) -> (dx, dy)``: camera B's offset for one direction; it may also
#: return ``(dx, dy, extra)`` with a dict recorded in the direction's entry of ``merged.json``.
RegisterFn = Callable[[int, np.ndarray, np.ndarray], tuple]


def calibrated_offset(offset_px: tuple[float, float] = (0.0, 0.0)) -> RegisterFn:
    """A :data:`RegisterFn` that returns the rig's calibrated offset for every direction."""
    dx, dy = float(offset_px[0]), float(offset_px[1])
    return lambda direction, image_a, image_b: (dx, dy)


def merge_direction(session, direction: int, camera: str, n_exposures: int,
                    **merge_options) -> tuple[np.ndarray, tuple[float, float]]:
    """HDR merge (Eqs. (1)-(2)) of one camera's bracket; returns radiance (H, W, 3) and the reported pan/tilt."""
    frames, times, pans, tilts, bit_depth = [], [], [], [], 12
    for k in range(n_exposures):
        frame, meta = session.read_frame(direction, camera, k)
        frames.append(frame)
        times.append(float(meta["exposure_s"]))
        pans.append(float(meta.get("pan_deg_reported", meta.get("pan_deg_commanded"))))
        tilts.append(float(meta.get("tilt_deg_reported", meta.get("tilt_deg_commanded"))))
        bit_depth = int(meta.get("bit_depth", bit_depth))
    result = merge_exposures(frames, times, bit_depth, **merge_options)
    radiance = result.radiance if result.radiance.ndim == 3 else result.radiance[..., None]
    return radiance, (float(np.mean(pans)), float(np.mean(tilts)))


def merge_session(session: Session | str | Path, output: str | Path, *, register: RegisterFn | None = None,
                  dtype: str = "float16", progress: Callable[[int, int], None] | None = None,
                  skip: Collection[int] = (), cameras: dict[str, CameraModel] | None = None,
                  **merge_options) -> MergedDirections:
    """Stream a raw capture session into a merged-directions directory, one direction at a time.

    Each direction's brackets are merged (:func:`omnispectral.imaging.merge_exposures`, options passed
    through), camera B's offset comes from ``register`` (default: the calibrated offset 0 — the
    end-to-end pipeline plugs phase-only correlation in here), the pan/tilt recorded is the mean
    position the head reported during the bracket, and the images are written before the next
    direction is read, so memory holds one direction.  Directions already written are skipped, and
    so are the planned directions in ``skip`` (e.g. ones with damaged frames), which are not planned here.
    ``session`` is an open :class:`Session` or its directory; ``cameras`` the rig's camera models when the
    caller has them already (default: built from the session's rig).
    """
    session = session if isinstance(session, Session) else Session.open(session)
    rig = session.rig()
    plan = session.plan()
    register = register or calibrated_offset()
    cameras = cameras or {c: rig.camera_model(c) for c in CAMERAS}
    directions = [d for d in plan.directions if d.index not in set(skip)]
    writer = MergedDirectionsWriter.create(
        output, cameras, [d.to_dict() for d in directions], rig_name=rig.name, rig_toml=rig_toml(rig),
        session={"path": str(session.path.resolve()), **_session_summary(session)}, dtype=dtype,
        system=_system_or_none(rig))
    done = writer.done()
    n = len(directions)
    for i, d in enumerate(directions):
        if d.index not in done:
            img_a, (pan, tilt) = merge_direction(session, d.index, "A", len(plan.exposures_s), **merge_options)
            img_b, _ = merge_direction(session, d.index, "B", len(plan.exposures_s), **merge_options)
            dx, dy, *rest = register(d.index, img_a, img_b)
            writer.add(d.index, pan, tilt, {"A": img_a, "B": img_b}, {"B": (dx, dy)},
                       {"pan_deg_commanded": d.pan_deg, "tilt_deg_commanded": d.tilt_deg, **(rest[0] if rest else {})})
            del img_a, img_b
        if progress is not None:
            progress(i + 1, n)
    return MergedDirections.open(output)


def _system_or_none(rig) -> dict | None:
    """The six bands' sensitivities for ``merged.json`` (``None`` when the rig names curves this package
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
