"""What determines a product's ``merged/`` directory: the session's identity and content, the rig, the
settings (see :mod:`omnispectral.fingerprint` for how fingerprints are compared and enforced)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from omnispectral.capture.session import Session, read_journal
from omnispectral.checksums import file_sha256
from omnispectral.errors import ConfigurationError
from omnispectral.fingerprint import FINGERPRINT_VERSION
from omnispectral.mosaic.sources import FORMAT_VERSION

__all__ = ["REGISTRATION_IDENTITY", "product_fingerprint", "session_identity"]


def session_identity(session_path: str | Path) -> dict:
    """Identity and content of a session: creation time, kind, rig, and a hash of all its frame records."""
    s = Session.open(session_path)
    meta = s.metadata()
    records = read_journal(s.journal_path).records
    h = hashlib.sha256()
    for key in sorted(records):
        rec = records[key]
        h.update(json.dumps([list(key), rec.get("sha256"), rec.get("bytes"), rec.get("exposure_s")]).encode())
    return {"created_utc": meta.get("created_utc"), "kind": meta.get("kind"), "rig": meta.get("rig"),
            "n_frames": len(records), "frames_sha256": h.hexdigest()}


def _paper_identity(min_confidence: float | None, rig_calibration, calibration_views_sha256) -> dict:
    """The paper's registration: its POC confidence threshold."""
    return {"min_confidence": None if min_confidence is None else float(min_confidence)}


def _parallax_identity(min_confidence: float | None, rig_calibration, calibration_views_sha256) -> dict:
    """The parallax registration: camera B's calibration file and the chessboard views it was fitted from."""
    reg = {"rig_calibration_sha256": None if rig_calibration is None else file_sha256(rig_calibration)}
    if calibration_views_sha256 is not None:  # absent otherwise: products made without views keep their key
        reg["calibration_views_sha256"] = calibration_views_sha256
    return reg


#: What identifies each registration method's result (the method names of
#: :data:`omnispectral.product.process.REGISTRATIONS`): ``identity(min_confidence, rig_calibration,
#: calibration_views_sha256) -> dict`` recorded beside ``"method"``.
REGISTRATION_IDENTITY = {"paper": _paper_identity, "parallax": _parallax_identity}


def product_fingerprint(session_path: str | Path, *, hdr_weight: str, registration: str,
                        min_confidence: float | None = None, rig_calibration: str | Path | None = None,
                        skipped_directions=(), merged_format_version: int | None = None,
                        calibration_views_sha256: str | None = None) -> dict:
    """Everything that determines a product's ``merged/`` directory (module docstring).

    ``calibration_views_sha256``: the chessboard views camera B's mounting was fitted from
    (:func:`omnispectral.product.rigsource.views_sha256`), when it was: other views make another product."""
    session = Path(session_path)
    rig_file = session / "rig.toml"
    plan = json.loads((session / "plan.json").read_text(encoding="utf-8"))
    identity = REGISTRATION_IDENTITY.get(registration)
    if identity is None:
        raise ConfigurationError(f"registration must be one of {', '.join(REGISTRATION_IDENTITY)}, "
                                 f"got {registration!r}")
    reg: dict = {"method": registration, **identity(min_confidence, rig_calibration, calibration_views_sha256)}
    return {"fingerprint_version": FINGERPRINT_VERSION,
            "merged_format_version": merged_format_version if merged_format_version is not None else FORMAT_VERSION,
            "session": session_identity(session), "rig_sha256": file_sha256(rig_file),
            "exposures_s": [float(t) for t in plan.get("exposures_s", [])],
            "hdr_weight": hdr_weight, "registration": reg,
            "skipped_directions": sorted(int(d) for d in skipped_directions),
            **_darks(session)}


def _darks(session: Path) -> dict:
    """The dark frames' index (``capture darks``), when the session has one: recording darks changes every merge."""
    index = session / "darks" / "darks.json"
    return {"darks_sha256": file_sha256(index)} if index.exists() else {}
