"""Capture sessions on disk: crash-safe frames, an append-only journal, resume and verification.

Layout of a session directory::

    SESSION/
      session.json      format version, kind (capture | simulation), rig name, created (UTC)
      rig.toml          snapshot of the rig description used
      plan.json         the plan (directions, exposures, timing estimate)
      journal.jsonl     one JSON line per frame, appended, flushed and fsynced; it holds the frame file's
                        ``bytes``, ``sha256`` and ``xxh3_128`` (the fast checksum ``process`` verifies,
                        :mod:`omnispectral.checksums`; older frames lack it)
      events.jsonl      start / resume / stop / complete events with reasons
      frames/dNNNN/{A,B}_eKK.tif   16-bit raw frames (tifffile), metadata as JSON in the description
                        (camera B only in sessions of two-camera rigs); the description's record holds
                        ``pixels_sha256``, the SHA-256 of the decoded pixels (:func:`pixels_sha256`; frames
                        written before it existed lack it)
      quarantine/frames/dNNNN/{A,B}_eKK.tif   frames ``session repair --apply`` refused as damaged, moved
                        aside (never deleted) and out of the journal, so that a resume shoots them again
      ground_truth/     simulated sessions only (see omnispectral.sim.simulate)
      calibration/      chessboard views for camera B's mounting, once per mounting of the cameras
                        (omnispectral.capture.calviews; not part of the plan: verify and repair leave it alone)

A frame is first written to a temporary name, fsynced and renamed; only then is its journal line
appended.  A process killed at any moment therefore leaves (a) complete frames with journal lines,
(b) at most one frame file without a line (rewritten on resume), and (c) at most one partial last
journal line (ignored and cut on resume).  Nothing already written is modified.

**Referenced frames** (``omnispectral import --reference``): a frame may stay where it was made instead of
being copied into ``frames/``.  Its journal record then has ``"referenced": true``, ``"file"`` the absolute
path of the original, and the original's ``bytes``, ``mtime_ns`` and ``sha256``; the frame's metadata is the
journal record itself.  :meth:`Session.read_frame` decodes the original
(:func:`omnispectral.capture.sourcefiles.decode_source_image`) after checking its size and modification time,
and :func:`verify_session` names a referenced file that was moved, deleted or changed.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import io
import json
import math
import mmap
import os
import re
import shutil
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from omnispectral.capture.plan import Plan
from omnispectral.capture.sourcefiles import decode_source_image
from omnispectral.checksums import FRAME_FAST_ALGORITHM, bytes_xxh3, file_sha256
from omnispectral.errors import DamagedFrameError, InputFileError
from omnispectral.filebytes import file_bytes
from omnispectral.fingerprint import differences
from omnispectral.io import atomic_path, atomic_write_json, atomic_write_text, is_temp_name, jsonable
from omnispectral.limits import check_image_shape
from omnispectral.locking import LOCK_NAME, directory_lock
from omnispectral.rig import CAMERA_NAMES, DARK_EXPOSURE_BASE, SUN_EXPOSURE_BASE, Rig, rig_from_dict, rig_toml
from omnispectral.threads import ordered_thread_map

__all__ = ["CALIBRATION_DIR", "CAMERAS", "FORMAT_VERSION", "FRAME_NAME", "QUARANTINE_DIR", "JournalReadout", "Session",
           "bracket_indices", "content_matches", "dark_extensions", "decode_frame",
           "file_record_checksums", "frame_relpath", "half_created_leftovers", "pixel_problem", "pixels_sha256",
           "read_journal", "record_key", "referenced_problem", "sun_bracket_keys", "sun_directions", "utc_now_iso",
           "verify_session"]

FORMAT_VERSION = 1
#: The folder of a session's calibration views (:mod:`omnispectral.capture.calviews`).
CALIBRATION_DIR = "calibration"
#: The folder of the frames ``session repair --apply`` refused as damaged (``quarantine/frames/dNNNN/…``).
QUARANTINE_DIR = "quarantine"
#: Every camera a session may hold; a session's own are its rig's (:meth:`Session.cameras`: A, or A and B).
CAMERAS = CAMERA_NAMES


def frame_relpath(direction: int, camera: str, exposure_index: int) -> str:
    """Path of a frame relative to the session directory."""
    return f"frames/d{direction:04d}/{camera}_e{exposure_index:02d}.tif"


#: A final frame name inside ``frames/`` (temporary files never match it).
FRAME_NAME = re.compile(r"^d(\d{4,})/([AB])_e(\d{2,3})\.tif$")


def half_created_leftovers(path: Path) -> list[Path] | None:
    """The entries of a session directory a killed :meth:`Session.create` left (``None``: something else is there).

    Only ``rig.toml``, ``plan.json``, an empty ``frames/``, the lock file and temporary files qualify; calibration
    views recorded before the capture (``calibration/``, :mod:`omnispectral.capture.calviews`) are kept.
    """
    out = []
    for p in path.iterdir():
        if p.name in (LOCK_NAME, CALIBRATION_DIR):
            continue
        if p.name in ("rig.toml", "plan.json") or is_temp_name(p.name):
            out.append(p)
        elif p.name == "frames" and p.is_dir() and not any(p.rglob("*.tif")):
            out.append(p)
        else:
            return None
    return out



def file_record_checksums(content: bytes) -> dict:
    """The journal's checksums of a frame file's bytes: ``sha256``, ``xxh3_128`` (the fast one ``process``
    verifies, :mod:`omnispectral.checksums`) and ``bytes``."""
    return {"sha256": hashlib.sha256(content).hexdigest(), FRAME_FAST_ALGORITHM: bytes_xxh3(content),
            "bytes": len(content)}


def content_matches(content, rec: dict, cryptographic: bool = True) -> bool:
    """Whether a frame file's bytes match its journal record: its SHA-256, or with ``cryptographic=False`` its
    XXH3-128 where the record holds one (records written before it existed: the SHA-256)."""
    fast = rec.get(FRAME_FAST_ALGORITHM)
    if not cryptographic and isinstance(fast, str):
        return bytes_xxh3(content) == fast
    return hashlib.sha256(content).hexdigest() == rec.get("sha256")


def pixels_sha256(pixels: np.ndarray) -> str:
    """SHA-256 (hex) of a frame's decoded pixels: their values as little-endian uint16 in C order.

    Embedded as ``pixels_sha256`` in the record a frame's TIFF description holds (:meth:`Session.write_frame`), it
    says whether the pixels are still those the camera delivered even when the frame's journal line is lost.
    """
    return hashlib.sha256(np.ascontiguousarray(pixels, dtype="<u2").tobytes()).hexdigest()


def pixel_problem(pixels: np.ndarray, record: dict, max_dn: int | None = None) -> str | None:
    """What is wrong with a frame's decoded pixels against the record its TIFF embeds (``None``: nothing).

    Parameters
    ----------
    pixels
        The decoded frame (16-bit codes; any other type is damage).
    record
        The frame record from its TIFF description: its ``shape`` and, when present, its ``pixels_sha256``
        (frames written before that field existed are checked for shape and full scale only).
    max_dn
        The camera's full scale (``2**bit_depth - 1`` of the session's rig); a larger value is damage.
        ``None``: not checked.
    """
    if pixels.dtype.kind != "u" or pixels.dtype.itemsize != 2:
        return f"decodes to {pixels.dtype} pixels, not 16-bit raw codes"
    if "shape" in record and list(pixels.shape) != list(record["shape"]):
        return f"shape {list(pixels.shape)}, the frame's record says {record['shape']}"
    expected = record.get("pixels_sha256")
    if expected is not None and pixels_sha256(pixels) != expected:
        return "pixel checksum mismatch (the pixels changed after the capture)"
    top_dn = int(pixels.max()) if max_dn is not None and pixels.size else 0
    if max_dn is not None and top_dn > max_dn:
        return f"holds {top_dn} DN, above the camera's full scale of {max_dn} DN (damaged pixels)"
    return None


def utc_now_iso() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


@dataclass
class JournalReadout:
    """What a journal holds: the complete frame records by key, and any damage found."""

    records: dict[tuple[int, str, int], dict]
    bad_lines: list[tuple[int, str]]
    partial_tail: bool
    valid_bytes: int


def record_key(rec) -> tuple[int, str, int]:
    """``(direction, camera, exposure index)`` of a frame record; ``ValueError`` unless exactly that."""
    if not isinstance(rec, dict):
        raise ValueError("not an object")
    d, c, k = rec["direction"], rec["camera"], rec["exposure_index"]
    if any(isinstance(v, bool) or not isinstance(v, int) for v in (d, k)) or c not in CAMERAS \
            or not 0 <= d < 1 << 31 or not 0 <= k < 1 << 16:
        raise ValueError("not a frame key")
    return d, c, k


def read_journal(path: Path) -> JournalReadout:
    """Parse ``journal.jsonl``; a last line without newline or unparsable is a cut write (``partial_tail``)."""
    records: dict[tuple[int, str, int], dict] = {}
    bad: list[tuple[int, str]] = []
    if not path.exists():
        return JournalReadout(records, bad, False, 0)
    data = path.read_bytes()
    lines = data.split(b"\n")
    partial = False
    valid = 0
    offset = 0
    for n, raw in enumerate(lines, 1):
        is_last = n == len(lines)
        if is_last and raw == b"":
            break
        end = offset + len(raw) + (0 if is_last else 1)
        try:
            rec = json.loads(raw.decode("utf-8"))
            key = record_key(rec)
        except (ValueError, KeyError, TypeError, UnicodeDecodeError):
            if is_last:
                partial = True
            else:
                bad.append((n, "not a frame record"))
            offset = end
            continue
        if is_last:  # a complete JSON object without its newline: the write was cut after the object
            partial = True
        else:
            records[key] = rec
            valid = end
        offset = end
    return JournalReadout(records, bad, partial, valid)


class Session:
    """A session directory (create with :meth:`create`, open with :meth:`open`)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._records: dict | None = None  # journal records, read when a frame is not under frames/
        self._checked_reads: dict | None = None  # full scale by camera once check_frames_on_read() is called
        self._cryptographic_reads = False  # check_frames_on_read(): SHA-256 even where a fast checksum is recorded

    # ------------------------------------------------------------------ create / open
    @classmethod
    def create(cls, path: str | Path, rig: Rig, plan: Plan, kind: str = "capture", extra: dict | None = None,
               identity: dict | None = None):
        """Start a new session, or return the existing one at ``path`` if it was made by the same parameters.

        ``identity``: parameters besides the rig and the plan that determine the frames (a simulation's
        scene, seed, noise); recorded in ``session.json`` and compared on resume.  A resume with another
        rig, plan or identity is refused naming the difference.  A directory left by a run killed while
        creating the session (only our own files, no ``session.json`` yet) is created again.
        """
        with directory_lock(path, "create session"):
            return cls._create_locked(Path(path), rig, plan, kind, extra, identity)

    @classmethod
    def _create_locked(cls, path: Path, rig: Rig, plan: Plan, kind: str, extra: dict | None,
                       identity: dict | None) -> Session:
        s = cls(path)
        if (s.path / "session.json").exists():
            s.check_same_parameters(rig, plan, identity)
            return s
        if s.path.exists():
            leftovers = half_created_leftovers(s.path)
            if leftovers is None:
                raise InputFileError(s.path, "exists and is not an omnispectral session; choose an empty directory")
            for p in leftovers:  # a creation killed before session.json: start it again
                shutil.rmtree(p) if p.is_dir() else p.unlink()
        (s.path / "frames").mkdir(parents=True, exist_ok=True)
        atomic_write_text(s.path / "rig.toml", rig_toml(rig))
        atomic_write_json(s.path / "plan.json", plan.to_dict())
        meta = {"format": "omnispectral-session", "format_version": FORMAT_VERSION, "kind": kind, "rig": rig.name,
                "created_utc": utc_now_iso(), "n_frames_planned": s.n_planned(plan, rig.camera_names)}
        if identity is not None:
            meta["identity"] = jsonable(identity)
        meta.update(extra or {})
        atomic_write_json(s.path / "session.json", meta)  # written last: its presence marks a session
        return s

    def check_same_parameters(self, rig: Rig, plan: Plan, identity: dict | None = None) -> None:
        """Refuse to resume this session with another plan, rig or identity; the error names the differences."""

        existing = self.plan()
        if existing.to_dict()["directions"] != plan.to_dict()["directions"] or \
                list(existing.exposures_s) != list(plan.exposures_s):
            raise InputFileError(self.path, "holds a session with a different plan; choose another output directory")
        diffs = []
        try:
            old_rig = tomllib.loads((self.path / "rig.toml").read_text(encoding="utf-8"))
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise InputFileError(self.path / "rig.toml", f"cannot read the rig snapshot ({exc})") from None
        new_rig = tomllib.loads(rig_toml(rig))
        diffs += [f"rig {d}" for d in differences(old_rig, new_rig)]
        recorded = self.metadata().get("identity")
        if identity is not None and recorded is not None:
            diffs += differences(recorded, jsonable(identity))
        if diffs:
            raise InputFileError(self.path, "was captured with other parameters, resuming would mix frames: "
                                            + "; ".join(diffs[:4]) + (" …" if len(diffs) > 4 else "")
                                            + ". Use the original parameters or another output directory")

    @classmethod
    def open(cls, path: str | Path) -> Session:
        s = cls(path)
        if not (s.path / "session.json").is_file():
            raise InputFileError(s.path, "not found" if not s.path.exists() else
                                 "not a session directory (no session.json)")
        return s

    def metadata(self) -> dict:
        return self._json("session.json")

    def plan(self) -> Plan:
        data = self._json("plan.json")
        try:
            return Plan.from_dict(data)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputFileError(self.path / "plan.json", f"not a valid plan ({exc})") from None

    def cameras(self) -> tuple[str, ...]:
        """The cameras of the session's rig, in band order: ``("A", "B")``, or ``("A",)`` for one RGB camera."""
        return self.rig().camera_names

    def full_scale_dn(self) -> dict[str, int]:
        """The largest code each camera of the session's rig can deliver (``2**bit_depth - 1``), by camera."""
        rig = self.rig()
        return {c: rig.cameras[c].max_dn for c in rig.camera_names}

    def rig(self) -> Rig:
        p = self.path / "rig.toml"
        try:
            text = p.read_text(encoding="utf-8")
            return rig_from_dict(tomllib.loads(text), str(p), text)
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise InputFileError(p, f"cannot read the rig snapshot ({exc})") from None

    def _json(self, name: str) -> dict:
        p = self.path / name
        try:
            return json.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputFileError(p, "missing from the session") from None
        except (OSError, ValueError) as exc:
            raise InputFileError(p, f"unreadable ({exc})") from None

    @staticmethod
    def n_planned(plan: Plan, cameras: tuple[str, ...] = CAMERAS) -> int:
        return plan.n_directions * len(cameras) * len(plan.exposures_s)

    # ------------------------------------------------------------------ journal
    @property
    def journal_path(self) -> Path:
        return self.path / "journal.jsonl"

    def repair_journal(self) -> bool:
        """Cut a partial last journal line left by a killed process; True if something was cut."""
        j = read_journal(self.journal_path)
        if j.partial_tail:
            with open(self.journal_path, "r+b") as fh:
                fh.truncate(j.valid_bytes)
                fh.flush()
                os.fsync(fh.fileno())
            return True
        return False

    def completed(self) -> dict[tuple[int, str, int], dict]:
        """Frames recorded in the journal, by (direction, camera, exposure index)."""
        return read_journal(self.journal_path).records

    def _append_line(self, path: Path, record: dict) -> None:
        line = json.dumps(record, separators=(",", ":")) + "\n"
        with open(path, "a", encoding="utf-8") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())

    def log_event(self, event: str, **fields) -> None:
        self._append_line(self.path / "events.jsonl", {"event": event, "time_utc": utc_now_iso(), **fields})

    def events(self) -> list[dict]:
        p = self.path / "events.jsonl"
        if not p.exists():
            return []
        out = []
        for line in p.read_text(encoding="utf-8").splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                continue
        return out

    # ------------------------------------------------------------------ frames
    def write_frame(self, frame: np.ndarray, *, direction: int, camera: str, exposure_index: int, exposure_s: float,
                    pan_deg_commanded: float, tilt_deg_commanded: float, pan_deg_reported: float,
                    tilt_deg_reported: float, timestamp: str, bit_depth: int, extra: dict | None = None) -> dict:
        """Write one raw frame (atomic) and then its journal line (fsynced); returns the record.

        The record (embedded in the TIFF description, and the journal line with the file's ``sha256`` and
        ``bytes``) holds ``pixels_sha256``, the checksum of ``frame``'s pixels (:func:`pixels_sha256`).
        """

        if frame.dtype != np.uint16 or frame.ndim not in (2, 3):
            raise ValueError(f"raw frames are (H, W[, C]) uint16, got {frame.shape} {frame.dtype}")
        rel = frame_relpath(direction, camera, exposure_index)
        record = {"direction": direction, "camera": camera, "exposure_index": exposure_index,
                  "exposure_s": exposure_s, "pan_deg_commanded": pan_deg_commanded,
                  "tilt_deg_commanded": tilt_deg_commanded, "pan_deg_reported": pan_deg_reported,
                  "tilt_deg_reported": tilt_deg_reported, "timestamp": timestamp, "bit_depth": bit_depth,
                  "shape": list(frame.shape), "file": rel, **(extra or {})}
        record["pixels_sha256"] = pixels_sha256(frame)
        target = self.path / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            tifffile.imwrite(tmp, frame, photometric="rgb" if frame.ndim == 3 else "minisblack",
                             description=json.dumps(record), metadata=None)
        record.update(file_record_checksums(target.read_bytes()))
        self._append_line(self.journal_path, record)
        return record

    def write_reference(self, source: str | Path, shape: tuple[int, ...], *, direction: int, camera: str,
                        exposure_index: int, exposure_s: float, pan_deg_commanded: float, tilt_deg_commanded: float,
                        pan_deg_reported: float, tilt_deg_reported: float, timestamp: str, bit_depth: int,
                        extra: dict | None = None) -> dict:
        """Record a frame that stays in the file ``source`` (module docstring: referenced frames); returns the
        record.  ``shape`` is the decoded frame's."""
        src = Path(source).resolve()
        st = src.stat()
        record = {"direction": direction, "camera": camera, "exposure_index": exposure_index,
                  "exposure_s": exposure_s, "pan_deg_commanded": pan_deg_commanded,
                  "tilt_deg_commanded": tilt_deg_commanded, "pan_deg_reported": pan_deg_reported,
                  "tilt_deg_reported": tilt_deg_reported, "timestamp": timestamp, "bit_depth": bit_depth,
                  "shape": list(shape), "file": str(src), "referenced": True, **(extra or {}),
                  "sha256": file_sha256(src), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns}
        self._append_line(self.journal_path, record)
        if self._records is not None:
            self._records[(direction, camera, exposure_index)] = record
        return record

    def reference_record(self, direction: int, camera: str, exposure_index: int) -> dict | None:
        """The journal record of a referenced frame (``None`` if the frame is not a referenced one)."""
        key = (direction, camera, exposure_index)
        if self._records is None or key not in self._records:
            self._records = read_journal(self.journal_path).records
        rec = self._records.get(key)
        return rec if rec is not None and rec.get("referenced") else None

    def read_frame(self, direction: int, camera: str, exposure_index: int) -> tuple[np.ndarray, dict]:
        """A raw frame and the metadata stored inside it; a damaged file is named in the error."""

        if self._checked_reads is not None:  # frames under frames/ and referenced originals alike
            return self._read_checked((direction, camera, exposure_index))
        p = self.path / frame_relpath(direction, camera, exposure_index)
        if not p.exists() and (ref := self.reference_record(direction, camera, exposure_index)) is not None:
            return self._read_referenced(ref)
        if not p.exists():
            raise InputFileError(p, f"frame missing (direction {direction}, camera {camera}, "
                                    f"exposure {exposure_index})")
        return decode_frame(p)

    def check_frames_on_read(self, cryptographic: bool = False) -> Session:
        """From now on :meth:`read_frame` checks each frame as :func:`verify_session` with ``check_pixels`` does
        (the journal's checksum, decoding, shape, full scale), from the bytes it decodes: a session read once,
        by the stage that uses it, instead of once to check and once to use.  The checksum is the fast
        XXH3-128 where the journal holds one, unless ``cryptographic`` (:func:`content_matches`).  A failing
        frame raises :class:`~omnispectral.errors.DamagedFrameError` naming it.  Returns the session."""
        self._cryptographic_reads = cryptographic
        self._checked_reads = self.full_scale_dn()
        if self._records is None:
            self._records = read_journal(self.journal_path).records
        return self

    def _read_checked(self, key: tuple[int, str, int]) -> tuple[np.ndarray, dict]:
        found, data, meta = _checked_frame(self, key, self._records.get(key), True, True,
                                           self._checked_reads.get(key[1]), self._cryptographic_reads)
        if found is not None:
            _, file, problem = found
            raise DamagedFrameError(self.path / file if not Path(file).is_absolute() else Path(file), problem)
        return data, meta

    @staticmethod
    def _read_referenced(rec: dict) -> tuple[np.ndarray, dict]:
        """A referenced frame decoded from its original, refused when it is gone or no longer what was imported."""
        p = Path(rec["file"])
        problem = referenced_problem(rec, checksum=False)
        if problem:
            raise InputFileError(p, problem)
        data, _ = decode_source_image(p)
        if list(data.shape) != list(rec.get("shape", data.shape)):
            raise InputFileError(p, f"referenced frame decodes to shape {list(data.shape)}, the journal recorded "
                                    f"{rec['shape']}")
        return data.astype(np.uint16), rec


def frame_content(path: Path) -> bytes | mmap.mmap:
    """A frame file's bytes: the page cache's own pages, mapped, when it holds them, else read past it with
    direct I/O (:func:`omnispectral.filebytes.file_bytes`).  The checksum, the decoding and the merge read
    them where they are, with no further copy.  The frames of a session are written once, under a temporary
    name and renamed into place, so a mapped frame never changes under its reader."""
    return file_bytes(path)


def decode_frame(path: Path, content: bytes | mmap.mmap | None = None) -> tuple[np.ndarray, dict]:
    """Pixels and frame record of the frame TIFF at ``path`` (from ``content`` when its bytes are already
    read or mapped, :func:`frame_content`); a damaged file is named in the error."""
    stream = path if content is None else content if isinstance(content, mmap.mmap) else io.BytesIO(content)
    try:
        with tifffile.TiffFile(stream) as tf:
            page = tf.pages[0]
            check_image_shape(path, page.shape)  # before decoding: a hostile header cannot allocate GiB
            data = _plain_pixels(tf, page, content) if content is not None else None
            data = page.asarray() if data is None else data
            meta = json.loads(page.description)
    except InputFileError:
        raise
    except Exception as exc:  # tifffile raises several types for truncated files
        raise InputFileError(path, f"damaged frame ({type(exc).__name__}: {exc})") from None
    if not isinstance(meta, dict):
        raise InputFileError(path, "damaged frame (no frame record in the TIFF description)")
    return data, meta


def _plain_pixels(tf: tifffile.TiffFile, page: tifffile.TiffPage, content: bytes | mmap.mmap) -> np.ndarray | None:
    """The pixels of a TIFF stored plainly (uncompressed, in one run, native byte order) as a read-only view
    of the file's bytes ``content``, without decoding or copying them (a frame is read once, by the merge,
    which only reads its pixels); ``None`` for any other layout (decoded by tifffile)."""
    native = "<" if sys.byteorder == "little" else ">"
    if not (page.is_contiguous and page.compression == 1 and page.predictor == 1 and page.fillorder == 1
            and tf.byteorder == native and page.dtype.isnative
            and (page.planarconfig == 1 or page.samplesperpixel == 1)):
        return None
    count = math.prod(page.shape)
    offset = int(page.dataoffsets[0])
    if offset + count * page.dtype.itemsize > len(content):  # truncated: tifffile names the damage
        return None
    return np.frombuffer(content, page.dtype, count=count, offset=offset).reshape(page.shape)


def referenced_problem(rec: dict, checksum: bool = True) -> str | None:
    """What is wrong with a referenced frame's original against its journal record (``None``: nothing): gone,
    another size, another modification time (``checksum=False``) or another SHA-256 (``checksum``)."""
    p = Path(rec["file"])
    if not p.is_file():
        return "referenced frame missing: moved or deleted since the import (import again, or put it back)"
    st = p.stat()
    if "bytes" in rec and st.st_size != rec["bytes"]:
        return f"referenced frame changed since the import: {st.st_size} bytes, the journal recorded {rec['bytes']}"
    if checksum:
        if file_sha256(p) != rec.get("sha256"):
            return "referenced frame changed since the import: checksum mismatch"
    elif "mtime_ns" in rec and st.st_mtime_ns != rec["mtime_ns"]:
        return "referenced frame changed since the import: modified after it (the journal holds its mtime)"
    return None


def _frame_problem(s: Session, key: tuple[int, str, int], rec: dict | None, checksums: bool,
                   check_pixels: bool, max_dn: int | None = None,
                   cryptographic: bool = True) -> tuple[str, str, str] | None:
    """``("missing" | "damaged", file, problem)`` of one planned frame against its journal line, or None
    (``max_dn``: the camera's full scale, checked with ``check_pixels``; ``cryptographic``:
    :func:`content_matches`)."""
    return _checked_frame(s, key, rec, checksums, check_pixels, max_dn, cryptographic)[0]


def _checked_frame(s: Session, key: tuple[int, str, int], rec: dict | None, checksums: bool, check_pixels: bool,
                   max_dn: int | None = None, cryptographic: bool = True
                   ) -> tuple[tuple[str, str, str] | None, np.ndarray | None, dict | None]:
    """:func:`_frame_problem` and, when ``check_pixels`` decoded it without a problem, the frame's pixels and
    record (else ``None``): every check from one read of the file."""
    rel = frame_relpath(*key)
    if rec is None:
        return ("missing", rel, "not in the journal"), None, None
    if rec.get("referenced"):  # a file left where it was made (import --reference): named by its own path
        problem, data, meta = referenced_problem(rec, checksum=checksums), None, None
        if problem is None and check_pixels:
            try:
                data, meta = Session._read_referenced(rec)
            except InputFileError as exc:
                problem = exc.problem
        if problem:
            return (("missing" if "missing" in problem else "damaged"), rec["file"], problem), None, None
        return None, data, meta
    p = s.path / rel
    if not p.exists():  # journalled, then deleted: missing (there is nothing to be damaged)
        return ("missing", rel, "file missing"), None, None
    size = p.stat().st_size
    if "bytes" in rec and size != rec["bytes"]:  # the plainer message when sizes differ
        return ("damaged", rel, (f"size {size} bytes, the journal recorded {rec['bytes']} (truncated or changed"
                                 + ("; checksum mismatch)" if checksums else ")"))), None, None
    content = None
    if checksums or "bytes" not in rec:
        content = frame_content(p)
        if not content_matches(content, rec, cryptographic):
            return ("damaged", rel, "checksum mismatch (file changed or truncated)"), None, None
    if not check_pixels:
        return None, None, None
    try:
        data, embedded = decode_frame(p, content)
    except InputFileError as exc:
        return ("damaged", rel, exc.problem), None, None
    if "shape" in rec and list(data.shape) != list(rec["shape"]):
        return ("damaged", rel, f"shape {list(data.shape)}, the journal recorded {rec['shape']}"), None, None
    checked = embedded
    if content is not None:  # the file's checksum matched the journal: its pixels need no second hash
        checked = {k: v for k, v in embedded.items() if k != "pixels_sha256"}
    problem = pixel_problem(data, checked, max_dn)
    if problem:
        return ("damaged", rel, problem), None, None
    return None, data, embedded


def sun_directions(session: Session, records: dict) -> list[int]:
    """Directions that hold the sun: those with a ``sun`` event or any frame of a sun bracket."""
    found = {int(e["direction"]) for e in session.events() if e.get("event") == "sun" and "direction" in e}
    found |= {k[0] for k in records if k[2] >= SUN_EXPOSURE_BASE}
    return sorted(found)


def dark_extensions(session: Session, plan: Plan) -> dict[int, int]:
    """How many exposures of the dark extension each metered direction got: its last ``dark`` event, ``direction →
    n_exposures`` (0: metered, none needed), at most the plan's extension (``omnispectral.capture.run``)."""
    n_max = len((plan.dark_extension or {}).get("exposures_s", ()))
    return {int(e["direction"]): min(n_max, max(0, int(e.get("n_exposures", 0))))
            for e in session.events() if e.get("event") == "dark" and "direction" in e}


def bracket_indices(plan: Plan, n_dark: int) -> list[int]:
    """Exposure indices of one direction's frames that the HDR merge takes: the plan's bracket, then the
    direction's ``n_dark`` exposures of the dark extension."""
    return list(range(len(plan.exposures_s))) + [DARK_EXPOSURE_BASE + k for k in range(n_dark)]


def sun_bracket_keys(session: Session, plan: Plan, records: dict, cameras: tuple[str, ...]) -> list[tuple]:
    """Every frame key of the sun brackets the capture started (all of their exposures, both cameras)."""
    if not plan.sun_bracket:
        return []
    n = len(plan.sun_bracket["exposures_s"])
    return [(d, c, SUN_EXPOSURE_BASE + k) for d in sun_directions(session, records) for c in cameras for k in range(n)]


def verify_session(path: str | Path, check_pixels: bool = False, checksums: bool = True,
                   workers: int | None = None, sun_in_full: bool = False, cryptographic: bool = True) -> dict:
    """Completeness and integrity of a session against its plan; names every missing or damaged frame.

    Missing: no journal line, or a journalled file that no longer exists.  Damaged: a file whose size,
    checksum or (``check_pixels``) decoding disagrees with its journal line.

    Checks: every planned frame has a journal line, its file exists and its SHA-256 matches; journal
    lines that do not parse; a cut last line.  ``check_pixels`` also decodes each TIFF and checks its
    pixels (:func:`pixel_problem`: the ``pixels_sha256`` its description embeds, when present, and no value
    above the camera's full scale).  With
    ``checksums=False`` only the file size recorded in the journal is compared (catches truncation;
    a fast check before processing, which decodes every frame anyway).  ``sun_in_full``: the sun brackets' frames
    get every check whatever ``checksums`` and ``check_pixels`` say (``process`` reads them only after the
    mosaic).  ``workers``: threads (default :func:`~omnispectral.threads.kernel_threads`).
    ``cryptographic=False`` checks the fast XXH3-128 the journal records instead of the SHA-256
    (:func:`content_matches`; ``process`` does, ``session verify`` does not).
    """
    s = Session.open(path)
    plan = s.plan()
    j = read_journal(s.journal_path)
    cameras = s.cameras()
    extensions = dark_extensions(s, plan)
    expected = [(d.index, c, k) for d in plan.directions for c in cameras
                for k in bracket_indices(plan, extensions.get(d.index, 0))]
    expected += sun_bracket_keys(s, plan, j.records, cameras)

    full_scale = s.full_scale_dn()

    def check(key):
        full = sun_in_full and key[2] >= SUN_EXPOSURE_BASE
        return _frame_problem(s, key, j.records.get(key), checksums or full, check_pixels or full,
                              full_scale.get(key[1]), cryptographic)

    missing, damaged = [], []
    # each frame is read once (hash and decode from the same bytes); SHA-256 and the decoder release the
    # GIL, so two threads halve the wall time of a session of large frames
    for key, found in zip(expected, ordered_thread_map(check, expected, workers=workers), strict=True):
        if found is not None:
            kind, file, problem = found
            (missing if kind == "missing" else damaged).append(
                {"direction": key[0], "camera": key[1], "exposure_index": key[2], "file": file, "problem": problem})
    n_ok = len(expected) - len(missing) - len(damaged)
    return {"session": str(s.path), "n_planned": len(expected), "n_ok": n_ok, "n_missing": len(missing),
            "n_damaged": len(damaged), "complete": not missing and not damaged and not j.bad_lines,
            "journal_partial_last_line": j.partial_tail,
            "journal_bad_lines": [{"line": n, "problem": p} for n, p in j.bad_lines],
            "missing": missing, "damaged": damaged}
