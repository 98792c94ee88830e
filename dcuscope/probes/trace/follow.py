"""Read a trace file while it is being written (by the GStreamer tracer or ``dcuscope run``).

    follower = TraceFollower("dcu1.trace.jsonl")
    while True:
        update = follower.poll()            # what was added since the last poll
        ... update.header, update.events, update.ended ...

Only complete lines are read (a line being written waits for its newline). The header is read
again whenever the file says it changed: the GStreamer tracer rewrites its padded first line in
place when a stage, a source or a lineage note appears (probes/capture/c/writer.c); an events line
that uses a stage the header does not name yet makes the follower read it again too.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dcuscope.probes.trace.errors import TraceError
from dcuscope.probes.trace.tracefile import MAGIC, _parse_end, _parse_header, _parse_rows, rows_to_events
from dcuscope.protocol.events import EVENT_DTYPE, TraceHeader


@dataclass
class Update:
    header: TraceHeader | None
    """The header as it stands now (None until the file has one)."""
    header_changed: bool
    events: np.ndarray
    ended: bool
    """The end line was read: the traced process closed its trace."""
    dropped: int = 0
    """With ``ended``: events the traced process lost in its ring."""


class TraceFollower:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.header: TraceHeader | None = None
        self._header_raw = b""
        self._offset = 0
        self._lineno = 1
        self._count = 0
        self.ended = False

    def poll(self) -> Update:
        empty = np.empty(0, EVENT_DTYPE)
        try:
            with open(self.path, "rb") as f:
                first = f.readline()
                changed = self._read_header(first)
                if self.header is None:
                    return Update(None, False, empty, False)
                if self._offset == 0:
                    self._offset = len(first)
                f.seek(self._offset)
                data = f.read()
        except FileNotFoundError:
            return Update(None, False, empty, False)
        except OSError as exc:
            raise TraceError(f"{self.path}: cannot read trace file: {exc.strerror or exc}") from exc
        complete = data[:data.rfind(b"\n") + 1]
        self._offset += len(complete)
        chunks, dropped = [], 0
        for line in complete.split(b"\n")[:-1]:
            self._lineno += 1
            if not line.strip():
                continue
            obj = json.loads(line)
            if "events" in obj:
                rows = np.asarray(obj["events"], np.int64)
                if rows.ndim == 2 and len(rows) and rows[:, 1].max() >= len(self.header.stages):
                    changed |= self._reread_header()
                chunks.append(_parse_rows(self.path, self._lineno, rows, self.header))
                self._count += len(chunks[-1])
            elif "end" in obj:
                dropped = _parse_end(self.path, self._lineno, obj["end"], self._count)
                self.ended = True
        events = rows_to_events(np.concatenate(chunks)) if chunks else empty
        return Update(self.header, changed, events, self.ended, dropped)

    def _read_header(self, first: bytes) -> bool:
        if not first.endswith(b"\n") or first == self._header_raw:
            return False
        obj = json.loads(first)
        if not isinstance(obj, dict) or MAGIC not in obj:
            raise TraceError(f"{self.path}: not a dcuscope trace (line 1 has no '{MAGIC}' key)")
        if not obj["header"].get("stages"):
            return False  # the tracer has not seen a frame yet
        self.header = _parse_header(self.path, first)
        self._header_raw = first
        return True

    def _reread_header(self) -> bool:
        with open(self.path, "rb") as f:
            return self._read_header(f.readline())
