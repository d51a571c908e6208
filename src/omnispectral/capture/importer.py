"""``omnispectral import``: a capture session from images made elsewhere (a DSLR on a Merlin head, Papywizard, Hugin).

Inputs, per camera of the rig (run once for camera A and once for camera B into the same session):

* **images**: TIFF (8/16 bit), PNG, JPEG, read unchanged (:func:`omnispectral.imaging.bracket.read_frame`);
  their size must be the rig camera's sensor size;
* **directions**: where each image looked, from
  - a CSV with a header ``file,pan_deg,tilt_deg`` (optional ``exposure_s``, ``roll_deg``);
  - a Papywizard XML (``<shoot><pict id=… bracket=…><position yaw= pitch= roll=/>``): picture ``id`` *n* is the
    *n*-th image of the image list in name order; ``roll`` is the head's and must be 0;
  - a Hugin project ``.pto``: the ``i`` lines' ``y`` (yaw), ``p`` (pitch), ``r`` (roll) and ``n"file"`` (relative to
    the project); yaw is pan (positive right), pitch is tilt (positive up), roll must be the rig camera's mounting
    roll with the same sign (90 for a portrait camera), as Hugin's ``nona`` remaps such an image onto our model's
    pixels (``tests/capture/test_import.py::test_pto_yaw_pitch_roll_follow_hugin``);
* **exposure times**: the CSV's ``exposure_s`` column, else a table (``file,exposure_s`` CSV or Debevec's
  ``name seconds`` list), else the EXIF ``ExposureTime`` of each file.

Images that looked the same way (pan and tilt within 0.05°) form one direction's bracket, ordered longest
exposure first as in a capture.  Every direction must hold the same number of exposures.  The first camera
imported fixes the plan; the second camera's brackets are assigned to the nearest planned direction.

The session is written as a capture would write it (:class:`~omnispectral.capture.session.Session`: rig snapshot,
plan, fsynced journal, frames copied into ``frames/`` as uint16 TIFFs, or with ``reference`` left where they are:
the journal records each file's absolute path, size, modification time and SHA-256, ``session verify`` names a
moved or changed one and ``process`` decodes them in place), with ``kind = "import"``; each journal
record's ``camera_metadata`` names the source file, its SHA-256, where the exposure time came from, and the
``response`` of the values: ``linear`` (raw/16-bit) or ``srgb`` (8-bit JPEG/PNG, decoded by ``process`` through
the sRGB curve, IEC 61966-2-1, with the largest code at the rig camera's full scale ``full_scale_dn``, so that
radiance is in the rig's DN/s).  ``process`` then works on it unchanged.

Camera raw files (DNG, NEF, CR2, ARW, …) are read through rawpy (LibRaw): the Bayer mosaic as recorded, with
its CFA layout and black level in ``camera_metadata`` (``process`` subtracts and demosaics as for a raw camera,
:mod:`omnispectral.imaging.bayer`); their exposure times come from the table or the CSV.

One camera: a rig with camera A only (or ``--one-camera``) makes a three-band session, processed into a
three-band product.  Not supported: per-image roll or lens parameters from the ``.pto`` (the rig file's lens
model is used).
"""

from __future__ import annotations

import csv
import datetime as _dt
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnispectral.capture.plan import Direction, Plan
from omnispectral.capture.session import Session
from omnispectral.capture.sourcefiles import IMAGE_SUFFIXES, RAW_SUFFIXES, decode_source_image
from omnispectral.checksums import file_sha256
from omnispectral.choices import RESPONSES
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.bracket import exif_exposure_s, parse_exposure_s, read_times_list
from omnispectral.limits import image_header
from omnispectral.locking import directory_lock
from omnispectral.progress import ProgressCallback
from omnispectral.rig import Rig

__all__ = ["RESPONSES", "SAME_DIRECTION_DEG", "ImageEntry", "group_brackets", "import_images", "list_images",
           "read_directions", "read_directions_csv", "read_exposure_table", "read_papywizard", "read_pto"]

#: images whose pan and tilt agree within this belong to one direction's bracket
SAME_DIRECTION_DEG = 0.05


@dataclass(frozen=True)
class ImageEntry:
    """One image and where it looked (``where``: the line or element it came from, for error messages)."""

    path: Path
    pan_deg: float
    tilt_deg: float
    where: str
    exposure_s: float | None = None
    roll_deg: float | None = None


def list_images(directory: str | Path) -> list[Path]:
    """Image files of a directory in name order."""
    d = Path(directory)
    if not d.is_dir():
        raise InputFileError(d, "not a directory of images")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not files:
        raise InputFileError(d, f"holds no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


def read_directions(path: str | Path, images: list[Path] | None = None) -> list[ImageEntry]:
    """Directions of images from a CSV, a Papywizard XML or a Hugin ``.pto`` (module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return read_directions_csv(path, images)
    if suffix == ".xml":
        if images is None:
            raise ConfigurationError(f"{path}: a Papywizard XML lists no file names; give the images (--images DIR)")
        return read_papywizard(path, images)
    if suffix == ".pto":
        return read_pto(path)
    raise InputFileError(path, "unknown directions format; expected .csv (file,pan_deg,tilt_deg), a Papywizard "
                               ".xml or a Hugin .pto")


def _number(path: Path, text, what: str, line: int | None = None) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise InputFileError(path, f"{what} {text!r} is not a number", line=line) from None
    if not np.isfinite(v):
        raise InputFileError(path, f"{what} {text!r} is not finite", line=line)
    return v


def _check_angles(path: Path, pan: float, tilt: float, where: str, line: int | None = None) -> None:
    if abs(tilt) > 90 + 1e-9:
        raise InputFileError(path, f"{where}: tilt {tilt} deg is beyond ±90", line=line)
    if abs(pan) > 720:
        raise InputFileError(path, f"{where}: pan {pan} deg is beyond ±720", line=line)


def read_directions_csv(path: Path, images: list[Path] | None = None) -> list[ImageEntry]:
    """``file,pan_deg,tilt_deg[,exposure_s][,roll_deg]`` with a header; files relative to the CSV (or to the images)."""
    by_name = {p.name: p for p in images or []}
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"unreadable ({exc})") from None
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        raise InputFileError(path, "empty; expected a header file,pan_deg,tilt_deg")
    header = [h.strip() for h in rows[0]]
    for need in ("file", "pan_deg", "tilt_deg"):
        if need not in header:
            raise InputFileError(path, f"header {','.join(header)!r} has no column {need!r} "
                                       "(expected file,pan_deg,tilt_deg[,exposure_s][,roll_deg])", line=1)
    col = {h: i for i, h in enumerate(header)}
    out = []
    for n, row in enumerate(rows[1:], 2):
        if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
            continue
        if len(row) != len(header):
            raise InputFileError(path, f"{len(row)} fields, the header has {len(header)}", line=n)
        name = row[col["file"]].strip()
        file = by_name.get(name) or by_name.get(Path(name).name) or (path.parent / name)
        pan = _number(path, row[col["pan_deg"]], "pan_deg", n)
        tilt = _number(path, row[col["tilt_deg"]], "tilt_deg", n)
        _check_angles(path, pan, tilt, name, n)
        exposure = None
        if "exposure_s" in col and row[col["exposure_s"]].strip():
            try:
                exposure = parse_exposure_s(row[col["exposure_s"]])
            except ConfigurationError as exc:
                raise InputFileError(path, str(exc), line=n) from None
        roll = _number(path, row[col["roll_deg"]], "roll_deg", n) if "roll_deg" in col else None
        out.append(ImageEntry(Path(file), pan, tilt, f"line {n}", exposure, roll))
    if not out:
        raise InputFileError(path, "lists no images")
    return out


def read_papywizard(path: Path, images: list[Path]) -> list[ImageEntry]:
    """Papywizard's XML: ``<pict id="n">`` ↔ the n-th image in name order; ``<position yaw pitch roll/>``."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise InputFileError(path, f"not valid XML ({exc})") from None
    if root.tag != "papywizard":
        raise InputFileError(path, f"root element is <{root.tag}>, expected <papywizard>")
    picts = root.findall("./shoot/pict")
    if not picts:
        raise InputFileError(path, "no <shoot><pict> elements")
    entries = []
    for pict in picts:
        pid = pict.get("id")
        try:
            index = int(pid)
        except (TypeError, ValueError):
            raise InputFileError(path, f"<pict id={pid!r}>: id is not an integer") from None
        pos = pict.find("position")
        if pos is None:
            raise InputFileError(path, f"<pict id={pid}> has no <position>")
        pan = _number(path, pos.get("yaw"), f"<pict id={pid}> yaw")
        tilt = _number(path, pos.get("pitch"), f"<pict id={pid}> pitch")
        roll = _number(path, pos.get("roll", "0"), f"<pict id={pid}> roll")
        _check_angles(path, pan, tilt, f"<pict id={pid}>")
        if abs(roll) > 1e-6:
            raise InputFileError(path, f"<pict id={pid}>: head roll {roll} deg; heads with a roll axis are not "
                                       "supported (the camera's own roll is the rig's orientation)")
        entries.append((index, pan, tilt, pid))
    entries.sort()
    if [e[0] for e in entries] != list(range(entries[0][0], entries[0][0] + len(entries))):
        raise InputFileError(path, "<pict> ids are not consecutive")
    if len(entries) != len(images):
        raise InputFileError(path, f"lists {len(entries)} pictures but {len(images)} images were given; picture id n "
                                   "is the n-th image in name order")
    return [ImageEntry(img, pan, tilt, f"<pict id={pid}>") for img, (_, pan, tilt, pid) in zip(images, entries,
                                                                                               strict=True)]


_PTO_TOKEN = re.compile(r'(\w)("[^"]*"|\S*)')


def read_pto(path: Path) -> list[ImageEntry]:
    """The ``i`` (image) lines of a Hugin project: ``y`` yaw, ``p`` pitch, ``r`` roll, ``n"file"``."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise InputFileError(path, f"unreadable ({exc.strerror})") from None
    out = []
    for n, line in enumerate(lines, 1):
        if not line.startswith("i "):
            continue
        fields = {k: v for k, v in _PTO_TOKEN.findall(line[2:])}
        for key in ("y", "p", "r", "n"):
            if key not in fields:
                raise InputFileError(path, f"image line without '{key}'", line=n)
        if "=" in (fields["y"] + fields["p"] + fields["r"]):
            raise InputFileError(path, "image angles linked to another image ('y=0'); write the values", line=n)
        name = fields["n"].strip('"')
        pan = _number(path, fields["y"], "yaw", n)
        tilt = _number(path, fields["p"], "pitch", n)
        roll = _number(path, fields["r"], "roll", n)
        _check_angles(path, pan, tilt, name, n)
        out.append(ImageEntry(path.parent / name, pan, tilt, f"line {n}", None, roll))
    if not out:
        raise InputFileError(path, "no image lines ('i …') in the project")
    return out


def read_exposure_table(path: str | Path) -> dict[str, float]:
    """Exposure times by file stem: a CSV with ``file,exposure_s`` columns or a ``name seconds`` list."""
    path = Path(path)
    if path.suffix.lower() != ".csv":
        return read_times_list(path)
    try:
        rows = list(csv.reader(path.read_text(encoding="utf-8-sig").splitlines()))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"unreadable ({exc})") from None
    header = [h.strip() for h in rows[0]] if rows else []
    if "file" not in header or "exposure_s" not in header:
        raise InputFileError(path, "expected a header with columns file and exposure_s", line=1)
    i, j = header.index("file"), header.index("exposure_s")
    out = {}
    for n, row in enumerate(rows[1:], 2):
        if not row or not "".join(row).strip():
            continue
        try:
            out[Path(row[i].strip()).stem] = parse_exposure_s(row[j])
        except (ConfigurationError, IndexError) as exc:
            raise InputFileError(path, str(exc), line=n) from None
    return out


def _angle_close(a: float, b: float, tol: float) -> bool:
    return abs((a - b + 180.0) % 360.0 - 180.0) <= tol


def group_brackets(entries: list[ImageEntry]) -> list[list[ImageEntry]]:
    """Images per direction (pan and tilt within :data:`SAME_DIRECTION_DEG`), in order of first appearance."""
    groups: list[list[ImageEntry]] = []
    for e in entries:
        for g in groups:
            if _angle_close(g[0].pan_deg, e.pan_deg, SAME_DIRECTION_DEG) and \
                    abs(g[0].tilt_deg - e.tilt_deg) <= SAME_DIRECTION_DEG:
                g.append(e)
                break
        else:
            groups.append([e])
    return groups


def _timestamp(path: Path) -> str:
    return _dt.datetime.fromtimestamp(path.stat().st_mtime, _dt.UTC).isoformat(timespec="milliseconds")


def import_images(output: str | Path, rig: Rig, camera: str, entries: list[ImageEntry], *,
                  exposure_table: dict[str, float] | None = None, response: str = "auto", reference: bool = False,
                  progress: ProgressCallback | None = None) -> dict:
    """Write camera ``camera``'s images into the session at ``output`` (created for the first camera); with
    ``reference`` the journal points at the files where they are instead of copying them (module docstring)."""
    if camera not in rig.cameras:
        raise ConfigurationError(f"camera must be one of {', '.join(rig.cameras)}, got {camera!r}")
    if response not in RESPONSES:
        raise ConfigurationError(f"response must be one of {', '.join(RESPONSES)}, got {response!r}")
    cam = rig.cameras[camera]
    groups = group_brackets(entries)
    sizes = {len(g) for g in groups}
    if len(sizes) != 1:
        small = min(groups, key=len)
        raise InputFileError(small[0].path, f"its direction (pan {small[0].pan_deg}, tilt {small[0].tilt_deg}) has "
                                            f"{len(small)} images, others have {max(sizes)}: every direction needs "
                                            "the same bracket")
    # read exposure times first: a missing one stops the import before anything is written
    times = {}
    for e in entries:
        t = e.exposure_s if e.exposure_s is not None else (exposure_table or {}).get(e.path.stem)
        source = "directions" if e.exposure_s is not None else "table"
        if t is None:
            if not e.path.is_file():
                raise InputFileError(e.path, f"file not found (listed at {e.where})")
            t, source = exif_exposure_s(e.path), "exif"
        if t is None:
            raise InputFileError(e.path, "no exposure time: no EXIF ExposureTime and not in the exposure table")
        if e.roll_deg is not None and not _angle_close(e.roll_deg, cam.roll_deg, 1.0):
            raise InputFileError(e.path, f"roll {e.roll_deg} deg ({e.where}) is not camera {camera}'s mounting roll "
                                         f"{cam.roll_deg} deg ({cam.orientation}); per-image roll is not supported")
        times[e.path] = (float(t), source)
    for g in groups:
        g.sort(key=lambda e: -times[e.path][0])
    exposures = tuple(float(np.median([times[g[k].path][0] for g in groups])) for k in range(len(groups[0])))
    with directory_lock(output, "import"):
        if (Path(output) / "session.json").exists():
            session = Session.open(output)
            plan = session.plan()
            assignment = _assign_to_plan(plan, groups)
        else:
            plan = _plan_of(rig, groups, exposures)
            session = Session.create(output, rig, plan, kind="import")
            assignment = {d.index: g for d, g in zip(plan.directions, groups, strict=True)}
        done = session.completed()
        n_total, n = sum(len(g) for g in groups), 0
        for index, group in assignment.items():
            for k, e in enumerate(group):
                n += 1
                if (index, camera, k) not in done:
                    _write_one(session, cam, camera, index, k, e, times[e.path], response, reference)
                if progress is not None:
                    progress("import", n, n_total)
    return {"session": str(Path(output)), "camera": camera, "referenced": reference, "n_directions": len(groups),
            "n_exposures": len(groups[0]), "n_images": n_total, "exposures_s": list(exposures),
            "cameras_imported": sorted({c for _, c, _ in Session.open(output).completed()})}


def _size_problem(shape: tuple[int, ...], cam, camera: str) -> str:
    channels = '' if len(shape) == 2 or shape[2] == 1 else f' x {shape[2]}'
    return (f"image of {shape[1]}x{shape[0]} px{channels}; camera {camera} of the rig is "
            f"{cam.width_px}x{cam.height_px} (RGB, or a Bayer mosaic)")


def _write_one(session: Session, cam, camera: str, index: int, k: int, e: ImageEntry, time_and_source, response,
               reference: bool = False):
    if e.path.suffix.lower() not in RAW_SUFFIXES:  # the size from the header, before anything is decoded
        header = image_header(e.path)  # a size other than the sensor's (a sensor is within the limits) is refused
        if header is not None and tuple(header[0][:2]) != (cam.height_px, cam.width_px):
            raise InputFileError(e.path, _size_problem(tuple(header[0]), cam, camera))
    sensor = (cam.height_px, cam.width_px)  # a camera raw file's sizes are checked from its metadata, undecoded
    frame, raw_meta = decode_source_image(e.path, sensor if e.path.suffix.lower() in RAW_SUFFIXES else None)
    if raw_meta:
        response = "linear"
    if frame.shape[:2] != (cam.height_px, cam.width_px) or (frame.ndim == 3 and frame.shape[2] != 3):
        raise InputFileError(e.path, _size_problem(frame.shape, cam, camera))
    bit_depth = 8 if frame.dtype == np.uint8 else cam.bit_depth
    if int(frame.max()) >= 1 << bit_depth:
        raise InputFileError(e.path, f"holds values up to {int(frame.max())}, more than camera {camera}'s "
                                     f"{bit_depth} bits")
    if response == "auto":
        response = "srgb" if bit_depth == 8 else "linear"
    meta = {"source_file": str(e.path.resolve()), "source_sha256": file_sha256(e.path),
            "exposure_source": time_and_source[1], "response": response, "direction_source": e.where, **raw_meta}
    if response == "srgb":  # the largest code means the camera's full scale: radiance in the rig's DN/s
        meta["full_scale_dn"] = cam.max_dn
    fields = {"direction": index, "camera": camera, "exposure_index": k, "exposure_s": time_and_source[0],
              "pan_deg_commanded": e.pan_deg, "tilt_deg_commanded": e.tilt_deg, "pan_deg_reported": e.pan_deg,
              "tilt_deg_reported": e.tilt_deg, "timestamp": _timestamp(e.path), "bit_depth": bit_depth,
              "extra": {"camera_metadata": meta}}
    if reference:
        session.write_reference(e.path, frame.shape, **fields)
    else:
        session.write_frame(frame.astype(np.uint16), **fields)


def _plan_of(rig: Rig, groups: list[list[ImageEntry]], exposures: tuple[float, ...]) -> Plan:
    directions = tuple(Direction(i, 0, i, float(g[0].pan_deg), float(g[0].tilt_deg)) for i, g in enumerate(groups))
    n_tilt = len({round(d.tilt_deg, 1) for d in directions})
    return Plan(rig.name, max(1, len(directions) // n_tilt), n_tilt, 0.0, 0.0, 0.0, directions, exposures,
                {"total": 0.0, "note": "imported: the directions and exposures of the images, no timing model"})


def _assign_to_plan(plan: Plan, groups: list[list[ImageEntry]]) -> dict[int, list[ImageEntry]]:
    """Brackets of the second camera → the planned direction nearest to each (within 2°), one to one."""
    out: dict[int, list[ImageEntry]] = {}
    for g in groups:
        best = min(plan.directions, key=lambda d: abs((d.pan_deg - g[0].pan_deg + 180) % 360 - 180)
                   + abs(d.tilt_deg - g[0].tilt_deg))
        far = abs((best.pan_deg - g[0].pan_deg + 180) % 360 - 180) + abs(best.tilt_deg - g[0].tilt_deg)
        if far > 2.0 or best.index in out:
            raise InputFileError(g[0].path, f"pan {g[0].pan_deg}, tilt {g[0].tilt_deg} ({g[0].where}) matches no "
                                            "direction of the session's plan one to one (nearest "
                                            f"{best.pan_deg}, {best.tilt_deg})")
        if len(g) != len(plan.exposures_s):
            raise InputFileError(g[0].path, f"{len(g)} exposures per direction; the session has "
                                            f"{len(plan.exposures_s)}")
        out[best.index] = g
    return out
