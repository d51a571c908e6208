"""Checksums of the files a product is made of (merged directions, panorama chunks): CRC-32 (zlib).

A record is ``{"crc32": "8 hex digits", "bytes": size}``.  Measured on the 2-core development machine (64 MB of
random bytes, best of 3): zlib's crc32 0.25 ms/MB (4.0 GB/s), CRC-32C (``google-crc32c``) 0.12 ms/MB, SHA-256
0.60 ms/MB, BLAKE2b 1.13 ms/MB: checking a file costs about what reading it from the page cache costs.  It
detects every burst of damage up to 32 bits and any other damage with probability 1 − 2⁻³²; it is no defence
against deliberate tampering (the frames' SHA-256 is, :mod:`omnispectral.capture`).

Raw frames carry two checksums in their journal records: the SHA-256 (``sha256``: what a product's fingerprint
names and ``omnispectral session verify`` checks, a defence against deliberate change too) and XXH3-128 (``xxh3_128``,
:func:`bytes_xxh3`, the ``xxhash`` package that Dask's hashing also uses), which ``process`` verifies when it
reads a frame: 9.8 GB/s against SHA-256's 1.1 GB/s on an Intel Xeon core with SHA extensions (64 MiB, warm), so a
full-scale session's 14.5 GiB of frames costs 1.6 CPU-s instead of 13.  A 128-bit hash misses accidental damage
with probability 2⁻¹²⁸; it is no defence against deliberate change.

Why not CRC-32C, the faster one: the panorama's chunks already end with their own CRC-32C (Zarr v3's standard
``crc32c`` codec, :mod:`omnispectral.mosaic.store`), and the CRC-32C of a message followed by its CRC-32C is
the same constant for every intact chunk; a file's CRC-32 (another polynomial) is a record of its own.

A file is checked at most once per process for each ``(size, modification time, inode)`` it has
(:func:`verified`): a reader that reads the same merged image crop by crop pays for one pass over it.
"""

from __future__ import annotations

import hashlib
import os
import threading
import zlib
from pathlib import Path

import xxhash

from omnispectral.errors import InputFileError

__all__ = ["ALGORITHM", "BLOCK_BYTES", "FRAME_FAST_ALGORITHM", "bytes_xxh3", "checksum_problem", "file_checksum",
           "file_crc32", "file_sha256", "forget_verified", "remembered_problem", "verified"]

#: The name of the checksum in every record.
ALGORITHM = "crc32"
#: The name of a raw frame's fast checksum in its journal record (module docstring).
FRAME_FAST_ALGORITHM = "xxh3_128"
#: Bytes read at a time.
BLOCK_BYTES = 1 << 22

_verified: set[tuple] = set()
_lock = threading.Lock()


def _blocks(path: str | Path):
    with open(path, "rb") as fh:
        yield from iter(lambda: fh.read(BLOCK_BYTES), b"")


def file_crc32(path: str | Path) -> str:
    """CRC-32 (zlib's) of a file's bytes, eight lower-case hex digits: the record of merged files and chunks."""
    crc = 0
    for block in _blocks(path):
        crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes: the frames' journal records and the inputs a fingerprint names, where
    a checksum must also stand against deliberate change."""
    h = hashlib.sha256()
    for block in _blocks(path):
        h.update(block)
    return h.hexdigest()


def bytes_xxh3(content) -> str:
    """XXH3-128 (hex, 32 digits) of bytes or any buffer: a raw frame's ``xxh3_128`` (module docstring)."""
    return xxhash.xxh3_128(content).hexdigest()


def file_checksum(path: str | Path) -> dict:
    """The checksum record of a file: ``{"crc32": hex, "bytes": size}``.

    Parameters
    ----------
    path
        The file.

    Returns
    -------
    dict
        The record.
    """
    st = os.stat(path)  # before the read: a change while it runs leaves the remembered state stale, not wrong
    record = {ALGORITHM: file_crc32(path), "bytes": st.st_size}
    _remember(path, st, record)  # it matches now: its first check in this process (the reader's) reads nothing
    return record


def checksum_problem(path: str | Path, record: dict | None) -> str | None:
    """What is wrong with a file against its checksum record, or ``None`` when it matches.

    Parameters
    ----------
    path
        The file.
    record
        Its record (:func:`file_checksum`); ``None`` or one without a checksum (written before checksums were
        recorded) checks presence only.

    Returns
    -------
    str or None
        ``"missing"``, ``"damaged: size …"``, ``"damaged: checksum …"`` or ``None``.
    """
    try:
        size = os.stat(path).st_size
    except FileNotFoundError:
        return "missing"
    if not record or ALGORITHM not in record:
        return None
    want = record.get("bytes")
    if want is not None and size != int(want):
        return f"damaged: size {size} bytes, {int(want)} when written"
    got = file_crc32(path)
    if got != record[ALGORITHM]:
        return f"damaged: checksum crc32 {got}, {record[ALGORITHM]} when written"
    return None


def verified(path: str | Path, record: dict | None) -> Path:
    """``path`` once it matches ``record`` (checked once per process and state of the file).

    Parameters
    ----------
    path
        The file.
    record
        Its checksum record, or ``None`` (then nothing is checked).

    Returns
    -------
    pathlib.Path
        The path.

    Raises
    ------
    InputFileError
        ``PATH: missing …`` or ``PATH: damaged: checksum …`` (one line).
    """
    path = Path(path)
    if not record or ALGORITHM not in record:
        return path
    problem = remembered_problem(path, record)
    if problem == "missing":
        raise InputFileError(path, "missing; 'omnispectral process' on the product makes it again")
    if problem is not None:
        raise InputFileError(path, f"{problem}; 'omnispectral process' on the product repairs it")
    return path


def remembered_problem(path: str | Path, record: dict | None) -> str | None:
    """:func:`checksum_problem`, remembering a file that matched (for its size, modification time and inode) so
    that the next check of it in this process, by :func:`verified` or here, reads nothing.

    Parameters
    ----------
    path
        The file.
    record
        Its checksum record, or ``None`` (presence only).

    Returns
    -------
    str or None
        As :func:`checksum_problem`.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "missing"
    if not record or ALGORITHM not in record:
        return None
    with _lock:
        if _state_key(path, st, record) in _verified:
            return None
    problem = checksum_problem(path, record)
    if problem is None:
        _remember(path, st, record)
    return problem


def _state_key(path: str | Path, st: os.stat_result, record: dict) -> tuple:
    """What :func:`remembered_problem` remembers of a file that matched: its path, state and checksum."""
    return str(Path(path).absolute()), st.st_size, st.st_mtime_ns, st.st_ino, record[ALGORITHM]


def _remember(path: str | Path, st: os.stat_result, record: dict) -> None:
    with _lock:
        _verified.add(_state_key(path, st, record))


def forget_verified() -> None:
    """Forget which files were verified (they are checked again when next read)."""
    with _lock:
        _verified.clear()
