"""Simulated photographs "made elsewhere": bracketed JPEGs (with EXIF) or 16-bit TIFFs, a Hugin ``.pto``, a
Papywizard XML and a ``file,pan_deg,tilt_deg`` CSV, rendered by the simulated rig (:class:`RigRenderer`).

This is how ``omnispectral import`` is tested with ground truth: a camera of the rig photographs a scene
(procedural, or an HDR panorama through :class:`~omnispectral.sim.scenes.PanoramaScene`) the way a
DSLR on a panoramic head would, the files are written as such a camera and such software write them, and
the import must rebuild a session that ``process`` turns into the same panorama.

JPEGs hold the sensor's codes scaled to full scale and encoded with the sRGB curve (IEC 61966-2-1), 8 bit,
with the EXIF ``ExposureTime`` (in the Exif sub-IFD, as cameras write it), quality 95 without chroma
subsampling; TIFFs hold the 16-bit raw codes
(exposure times in ``exposures.csv``).  The ``.pto`` has one ``i`` line per image with ``y`` (pan), ``p``
(tilt), ``r`` (the camera's mounting roll), ``v`` (the lens's field of view across the image width) and Hugin's
distortion terms at 0 (the rig file holds the OpenCV lens model the import uses).
"""

from __future__ import annotations

import datetime as _dt
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import tifffile
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from omnispectral.capture.plan import make_plan
from omnispectral.errors import ConfigurationError
from omnispectral.imaging.bracket import EXIF_EXPOSURE_TIME, EXIF_IFD_POINTER
from omnispectral.io import atomic_path, atomic_write_text
from omnispectral.rig import Rig
from omnispectral.sim.devices import frame_rng
from omnispectral.sim.simulate import RigRenderer, true_mounting_error_deg
from omnispectral.spectral.colour import srgb_encode

__all__ = ["FORMATS", "write_papywizard", "write_photographs", "write_pto"]

FORMATS = ("jpeg", "tiff")


def _exposure_rational(t: float) -> IFDRational:
    if t >= 1:
        return IFDRational(round(t * 10), 10)
    return IFDRational(1, round(1 / t)) if abs(1 / t - round(1 / t)) < 1e-6 * (1 / t) else IFDRational(
        round(t * 1_000_000), 1_000_000)


def write_photographs(output: str | Path, rig: Rig, scene, camera: str = "A", *, fmt: str = "jpeg", seed: int = 0,
                      noise: bool = True, quality: int = 95, renderer: RigRenderer | None = None) -> dict:
    """Render camera ``camera``'s brackets of every planned direction into ``output`` (module docstring).

    Returns the files written: ``images`` (in capture order), ``pto``, ``papywizard``, ``csv`` and, for TIFF,
    ``exposures``.
    """
    if fmt not in FORMATS:
        raise ConfigurationError(f"format must be one of {FORMATS}, got {fmt!r}")
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    plan = make_plan(rig)
    renderer = renderer or RigRenderer(rig, scene, noise=noise, b_mounting_error_deg=true_mounting_error_deg(seed))
    cam = rig.cameras[camera]
    top = cam.max_dn
    files, rows = [], []
    for d in plan.directions:
        for k, t in enumerate(plan.exposures_s):
            frame = renderer(camera, d.pan_deg, d.tilt_deg, t, frame_rng(seed, camera, d.pan_deg, d.tilt_deg, t))
            if frame.ndim != 3:
                raise ConfigurationError(f"camera {camera} gives Bayer mosaics; photographs need RGB frames")
            name = f"{camera}_d{d.index:04d}_e{k:02d}." + ("jpg" if fmt == "jpeg" else "tif")
            path = out / name
            with atomic_path(path) as tmp:
                if fmt == "jpeg":
                    codes = np.rint(srgb_encode(frame.astype(np.float64) / top) * 255).astype(np.uint8)
                    exif = Image.Exif()
                    exif.get_ifd(EXIF_IFD_POINTER)[EXIF_EXPOSURE_TIME] = _exposure_rational(t)
                    Image.fromarray(codes, "RGB").save(tmp, format="JPEG", quality=quality, subsampling=0, exif=exif)
                else:
                    tifffile.imwrite(tmp, frame, photometric="rgb", metadata=None)
            files.append(path)
            rows.append((name, d.pan_deg, d.tilt_deg, t))
    result = {"images": [str(p) for p in files], "n_directions": plan.n_directions,
              "exposures_s": list(plan.exposures_s)}
    result["pto"] = str(write_pto(out / f"{camera}.pto", rows, cam))
    result["papywizard"] = str(write_papywizard(out / f"{camera}.xml", rows, len(plan.exposures_s), cam))
    lines = ["file,pan_deg,tilt_deg"] + [f"{n},{p:.6f},{ti:.6f}" for n, p, ti, _ in rows]
    result["csv"] = str(atomic_write_text(out / f"{camera}_directions.csv", "\n".join(lines) + "\n"))
    if fmt == "tiff":
        lines = ["file,exposure_s"] + [f"{n},{t!r}" for n, _, _, t in rows]
        result["exposures"] = str(atomic_write_text(out / f"{camera}_exposures.csv", "\n".join(lines) + "\n"))
    return result


def write_pto(path: Path, rows: list[tuple[str, float, float, float]], cam) -> Path:
    """A Hugin project without control points: one ``i`` line per image (yaw, pitch, roll, field of view)."""
    head = ["# hugin project written by omnispectral (simulated photographs)",
            "p f2 w3600 h1800 v360 E0 R0 n\"TIFF c:NONE\"", "m i2"]
    images = [f"i w{cam.width_px} h{cam.height_px} f0 v{cam.lens.hfov_deg:.6f} Ra0 Rb0 Rc0 Rd0 Re0 "
              f"Eev{-np.log2(t):.6f} Er1 Eb1 r{cam.roll_deg:.6f} p{tilt:.6f} y{pan:.6f} TrX0 TrY0 TrZ0 j0 "
              f"a0 b0 c0 d0 e0 g0 t0 Va1 Vb0 Vc0 Vd0 Vx0 Vy0 Vm5 n\"{name}\"" for name, pan, tilt, t in rows]
    return atomic_write_text(path, "\n".join(head + images) + "\n")


def write_papywizard(path: Path, rows: list[tuple[str, float, float, float]], n_bracket: int, cam) -> Path:
    """Papywizard's shoot file: header (camera, bracketing) and one ``<pict>`` per image in shooting order."""
    root = ET.Element("papywizard", version="c")
    header = ET.SubElement(root, "header")
    shooting = ET.SubElement(header, "shooting", mode="mosaic")
    ET.SubElement(shooting, "headOrientation").text = "up"
    ET.SubElement(shooting, "cameraOrientation").text = cam.orientation
    camera = ET.SubElement(header, "camera")
    ET.SubElement(camera, "bracketing", nbPicts=str(n_bracket))
    shoot = ET.SubElement(root, "shoot")
    start = _dt.datetime(2026, 1, 1, 12, tzinfo=_dt.UTC)
    for i, (_, pan, tilt, _) in enumerate(rows):
        pict = ET.SubElement(shoot, "pict", id=str(i + 1), bracket=str(i % n_bracket + 1))
        ET.SubElement(pict, "time").text = (start + _dt.timedelta(seconds=2 * i)).isoformat()
        ET.SubElement(pict, "position", yaw=f"{pan:.6f}", pitch=f"{tilt:.6f}", roll="0.0")
    ET.indent(root)
    return atomic_write_text(path, '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, "unicode") + "\n")
