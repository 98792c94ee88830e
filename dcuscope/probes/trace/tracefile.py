"""Trace files: the events of one run of one node, as JSON Lines (format v2).

    {"dcuscope_trace": 2, "header": {...TraceHeader.to_dict()...}}
    {"events": [[ts, stage, point, source, frame, code], ...]}   one line per shipped batch
    ...
    {"end": {"events": TOTAL, "dropped": DROPPED}}               absent if the run crashed

Format 1 files (points origin, enter and exit only; events of five columns, no code) still
read: their frames have no service/wait split (:mod:`dcuscope.protocol.events`).

Every line is flushed as it is written, so a run that dies leaves a readable file: the reader
accepts a missing end line and a truncated last line, and says so in ``Trace.complete``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dcuscope.probes.trace.errors import TraceError
from dcuscope.protocol.events import EVENT_DTYPE, FORMAT_VERSION, POINT_NAMES, READABLE_FORMATS, TraceHeader, codes_valid

MAGIC = "dcuscope_trace"

# Column order of an event on an "events" line (format 1 had the first five).
COLUMNS = ("ts", "stage", "point", "source", "frame", "code")
V1_COLUMNS = 5


@dataclass
class Trace:
    """What :func:`read_trace` found in one file."""

    header: TraceHeader
    events: np.ndarray
    """Structured array of EVENT_DTYPE, in file order."""
    dropped: int
    """Events the node lost in its buffer (0 when the end line is missing)."""
    complete: bool
    """True when the file ends with its end line, i.e. the run closed the trace cleanly."""
    path: str = ""


def events_to_rows(events: np.ndarray) -> list[list[int]]:
    """EVENT_DTYPE array -> ``[[ts, stage, point, source, frame, code], ...]`` of Python ints."""
    return np.stack([events[c].astype(np.int64) for c in COLUMNS], axis=1).tolist()


def rows_to_events(rows: np.ndarray) -> np.ndarray:
    """An (n, 6) (or, format 1, (n, 5)) integer array in :data:`COLUMNS` order -> EVENT_DTYPE."""
    events = np.zeros(len(rows), dtype=EVENT_DTYPE)
    for i, column in enumerate(COLUMNS[:rows.shape[1]]):
        events[column] = rows[:, i]
    return events


class TraceFileWriter:
    """Writes a trace file; an :class:`dcuscope.protocol.events.Exporter` for the probe shipping thread."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file = None
        self.total = 0

    def start(self, header: TraceHeader) -> None:
        try:
            self._file = open(self.path, "w", encoding="utf-8", newline="\n")
        except OSError as exc:
            raise TraceError(f"{self.path}: cannot write trace file: {exc.strerror or exc}") from exc
        self.total = 0
        self._line({MAGIC: FORMAT_VERSION, "header": header.to_dict()})

    def write(self, events: np.ndarray) -> None:
        if self._file is None:
            raise TraceError(f"{self.path}: write() before start() or after close()")
        if len(events) == 0:
            return
        self._line({"events": events_to_rows(events)})
        self.total += len(events)

    def close(self, dropped: int) -> None:
        if self._file is None:
            return
        self._line({"end": {"events": self.total, "dropped": int(dropped)}})
        self._file.close()
        self._file = None

    def _line(self, obj: dict) -> None:
        # One flushed line per call: a crash can only ever cut the last line.
        self._file.write(json.dumps(obj, separators=(",", ":")) + "\n")
        self._file.flush()


def write_trace(path: str | Path, header: TraceHeader, events: np.ndarray, dropped: int = 0) -> None:
    """Write a whole trace at once (tests, conversions)."""
    writer = TraceFileWriter(path)
    writer.start(header)
    writer.write(events)
    writer.close(dropped)


def read_trace(path: str | Path) -> Trace:
    """Read a trace file; raise :class:`TraceError` naming the file (and line) if it is not one."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise TraceError(f"{path}: cannot read trace file: {exc.strerror or exc}") from exc
    lines = data.split(b"\n")
    # A file written to the end finishes with "\n"; anything after the last one is a cut line.
    truncated_tail = lines.pop() if lines else b""

    if not lines and not truncated_tail.strip():
        raise TraceError(f"{path}: not a dcuscope trace (empty file)")
    first = lines[0] if lines else truncated_tail
    header = _parse_header(path, first)

    chunks: list[np.ndarray] = []
    count = 0
    end = None
    for lineno, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        if end is not None:
            raise TraceError(f"{path}:{lineno}: data after the end line")
        obj = _loads(path, lineno, line)
        if "events" in obj:
            rows = _parse_rows(path, lineno, obj["events"], header)
            chunks.append(rows)
            count += len(rows)
        elif "end" in obj:
            end = _parse_end(path, lineno, obj["end"], count)
        else:
            raise TraceError(f"{path}:{lineno}: expected an 'events' or 'end' line, got keys {sorted(obj)}")

    rows = np.concatenate(chunks) if chunks else np.zeros((0, _width(header)), np.int64)
    # A non-empty tail is a line cut short by a crash (or a lost final newline): keep it when it
    # still parses, never fail because of it.
    if truncated_tail.strip() and end is None and lines:
        rows, end = _salvage_tail(path, len(lines) + 1, truncated_tail, rows, header)
    dropped = end if end is not None else 0
    return Trace(header, rows_to_events(rows), dropped=dropped, complete=end is not None, path=str(path))


def _loads(path: Path, lineno: int, line: bytes) -> dict:
    try:
        obj = json.loads(line)
    except ValueError as exc:  # includes UnicodeDecodeError: a binary file
        raise TraceError(f"{path}:{lineno}: not valid JSON ({_short(exc)})") from exc
    if not isinstance(obj, dict):
        raise TraceError(f"{path}:{lineno}: expected a JSON object, got {type(obj).__name__}")
    return obj


def _short(exc: Exception) -> str:
    return str(exc).splitlines()[0][:80]


def _parse_header(path: Path, line: bytes) -> TraceHeader:
    try:
        obj = json.loads(line)
    except ValueError as exc:
        raise TraceError(f"{path}: not a dcuscope trace (line 1 is not JSON)") from exc
    if not isinstance(obj, dict) or MAGIC not in obj:
        raise TraceError(f"{path}: not a dcuscope trace (line 1 has no '{MAGIC}' key)")
    version = obj[MAGIC]
    if version not in READABLE_FORMATS:
        raise TraceError(f"{path}: trace format version {version!r} is not supported (this dcuscope reads "
                         f"{', '.join(map(str, READABLE_FORMATS))})")
    try:
        header = TraceHeader.from_dict(obj["header"])
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise TraceError(f"{path}:1: malformed trace header ({type(exc).__name__}: {exc})") from exc
    if not header.stages:
        raise TraceError(f"{path}:1: trace header lists no stages")
    header.format = version
    return header


def _width(header: TraceHeader) -> int:
    """Columns of an event row in this header's format."""
    return V1_COLUMNS if header.format == 1 else len(COLUMNS)


def _parse_rows(path: Path, lineno: int, rows: object, header: TraceHeader) -> np.ndarray:
    width, n_stages = _width(header), len(header.stages)
    columns = list(COLUMNS[:width])
    try:
        arr = np.asarray(rows, dtype=np.int64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise TraceError(f"{path}:{lineno}: events must be lists of {width} integers ({_short(exc)})") from exc
    if arr.size == 0:
        return np.zeros((0, width), np.int64)
    if arr.ndim != 2 or arr.shape[1] != width:
        raise TraceError(f"{path}:{lineno}: events must be lists of {width} integers {columns}")
    stage, point = arr[:, 1], arr[:, 2]
    if stage.min() < 0 or stage.max() >= n_stages:
        raise TraceError(f"{path}:{lineno}: event stage index out of range 0..{n_stages - 1}")
    points = POINT_NAMES[:3] if width == V1_COLUMNS else POINT_NAMES
    if point.min() < 0 or point.max() >= len(points):
        raise TraceError(f"{path}:{lineno}: event point must be one of "
                         f"{', '.join(f'{i} {name}' for i, name in enumerate(points))}")
    if width > V1_COLUMNS and not codes_valid(point, arr[:, 5]).all():
        raise TraceError(f"{path}:{lineno}: an event's code does not fit its point (see dcuscope/protocol/events.py)")
    return arr


def _parse_end(path: Path, lineno: int, end: object, count: int) -> int:
    if not isinstance(end, dict) or not isinstance(end.get("events"), int) or not isinstance(end.get("dropped"), int):
        raise TraceError(f"{path}:{lineno}: end line must be {{\"events\": int, \"dropped\": int}}")
    if end["events"] != count:
        raise TraceError(f"{path}:{lineno}: end line counts {end['events']} events but the file holds {count}")
    return end["dropped"]


def _salvage_tail(path: Path, lineno: int, tail: bytes, rows: np.ndarray, header: TraceHeader):
    try:
        obj = json.loads(tail)
    except ValueError:
        return rows, None
    if isinstance(obj, dict) and "events" in obj:
        more = _parse_rows(path, lineno, obj["events"], header)
        return np.concatenate([rows, more]), None
    if isinstance(obj, dict) and "end" in obj:
        return rows, _parse_end(path, lineno, obj["end"], len(rows))
    return rows, None
