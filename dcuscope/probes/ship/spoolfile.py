"""The files of a node's spool (:mod:`dcuscope.probes.ship.spool`): segments of batch records, and the run's
``run.json``.

A segment (``<first seq, 12 digits>.seg``) starts with an 8-byte magic and the time it was made
(ns, CLOCK_REALTIME, i64: the age of the oldest event it may hold), then records, each::

    length u32 | crc32 u32 | seq i64 | events u32 | payload (length bytes: the batch as sent, wire.py)

all little-endian; the CRC-32 covers seq, events and the payload. A record is appended in one
``write``; what a crash or a power loss leaves half-written at a segment's end (a torn tail), or a
record whose checksum does not match, ends the segment: :func:`scan` cuts the file there and says
how many bytes it cut, and every record before it is kept.

Files are made readable by their owner only (0600, folders 0700): a run's file holds its resume
secret, and its events say what the machine ran.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

MAGIC = b"DCUSPL01"
SEGMENT_HEAD = struct.Struct("<8sq")
RECORD = struct.Struct("<IIqI")
"""length, crc32, seq, events."""
MAX_PAYLOAD = 64 << 20
"""A record longer than this is corrupt (a batch is at most wire.MAX_MESSAGE_BYTES)."""
FILE_MODE, DIR_MODE = 0o600, 0o700
META = "run.json"


class SpoolError(Exception):
    """A spool that cannot be used: not writable, full, or not a spool."""


@dataclass(frozen=True)
class Record:
    seq: int
    events: int
    offset: int
    """Where the record's payload starts in its segment."""
    length: int
    crc: int


def _crc(seq: int, events: int, payload: bytes | memoryview) -> int:
    return zlib.crc32(payload, zlib.crc32(struct.pack("<qI", seq, events)))


def encode_record(seq: int, events: int, payload: bytes) -> bytes:
    return RECORD.pack(len(payload), _crc(seq, events, payload), seq, events) + payload


def segment_head(made_ns: int) -> bytes:
    return SEGMENT_HEAD.pack(MAGIC, made_ns)


def made_ns(path: Path) -> int | None:
    """When segment ``path`` was made, None if it is no segment."""
    try:
        with open(path, "rb") as f:
            head = f.read(SEGMENT_HEAD.size)
    except OSError:
        return None
    if len(head) != SEGMENT_HEAD.size or head[:len(MAGIC)] != MAGIC:
        return None
    return SEGMENT_HEAD.unpack(head)[1]


def scan(path: Path) -> tuple[list[Record], int]:
    """The records of segment ``path`` and the bytes after the last good one: a torn or corrupt
    tail, truncated away (a file without the segment head is cut whole)."""
    data = path.read_bytes()
    records: list[Record] = []
    good = SEGMENT_HEAD.size if len(data) >= SEGMENT_HEAD.size and data[:len(MAGIC)] == MAGIC else 0
    pos = good
    while good and pos + RECORD.size <= len(data):
        length, crc, seq, events = RECORD.unpack_from(data, pos)
        start = pos + RECORD.size
        if length > MAX_PAYLOAD or start + length > len(data):
            break
        if _crc(seq, events, memoryview(data)[start:start + length]) != crc:
            break
        records.append(Record(seq, events, start, length, crc))
        pos = good = start + length
    tail = len(data) - good
    if tail:
        with open(path, "r+b") as f:
            f.truncate(good)
            os.fsync(f.fileno())
    return records, tail


def count_records(path: Path) -> tuple[int, int]:
    """(records, events) of segment ``path`` from its record headers alone, up to the first that does
    not fit (no payload read, no checksum: a listing of a large spool stays cheap)."""
    records = events = 0
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        head = f.read(SEGMENT_HEAD.size)
        if len(head) != SEGMENT_HEAD.size or head[:len(MAGIC)] != MAGIC:
            return 0, 0
        pos = SEGMENT_HEAD.size
        while pos + RECORD.size <= size:
            f.seek(pos)
            length, _, _, n = RECORD.unpack(f.read(RECORD.size))
            if length > MAX_PAYLOAD or pos + RECORD.size + length > size:
                break
            records, events, pos = records + 1, events + n, pos + RECORD.size + length
    return records, events


def read_payload(path: Path, record: Record) -> bytes:
    """The payload of ``record``, checked again (SpoolError if the file changed under it)."""
    try:
        with open(path, "rb") as f:
            f.seek(record.offset)
            data = f.read(record.length)
    except OSError as exc:
        raise SpoolError(f"{path}: {exc.strerror or exc}") from None
    if len(data) != record.length or _crc(record.seq, record.events, data) != record.crc:
        raise SpoolError(f"{path}: the record of batch {record.seq} changed on disk")
    return data


def segment_name(first_seq: int) -> str:
    return f"{first_seq:012d}.seg"


def make_dir(path: Path) -> None:
    """Create ``path`` (and its parents) for the spool, owner only; SpoolError if it cannot be written."""
    try:
        path.mkdir(mode=DIR_MODE, parents=True, exist_ok=True)
        if not os.access(path, os.W_OK | os.X_OK):
            raise PermissionError(f"{path} is not writable")
    except OSError as exc:
        raise SpoolError(f"the spool folder {path} cannot be used: {exc.strerror or exc}") from None


def write_json(path: Path, value: dict) -> None:
    """Replace ``path`` with ``value`` atomically (a temporary file, synced, renamed), mode 0600."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(value, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_json(path: Path) -> dict:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SpoolError(f"{path}: {getattr(exc, 'strerror', None) or exc}") from None
    if not isinstance(value, dict):
        raise SpoolError(f"{path}: not a spooled run")
    return value
