"""What a node's rollups do not hold yet: its batches still raw (a live run's last minute or two, what a
relay killed outright left, a store written with ``--compact-after 0``), rolled up here in memory for
a reader of rollups (:mod:`dcuscope.relay.store.history`) as compaction will roll them up, never written.

Each frame is counted once: the stored rollups hold the frames whose origin is in a segment, these
the frames whose origin is in a raw batch. The batches are listed first, the rollups read, then the
batches' payloads: a compaction that committed meanwhile shows as a listed batch gone, and the
whole read is done again (at most READS times; then the raw part is left out, and said so).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dcuscope.protocol.errors import ProtocolError
from dcuscope.protocol.events import TraceHeader
from dcuscope.protocol.wire import decode_payload
from dcuscope.relay.rollup.compute import MINUTE_NS, Key, Rollup, rollups_of
from dcuscope.relay.store.base import Database

MAX_RAW_EVENTS = 2_000_000
"""At most this many raw events are rolled up for one answer (about 2 s of CPU); past it the answer
leaves them out and says so (``dcuscope db compact`` rolls them up for good)."""
MARGIN_NS = 5 * MINUTE_NS
"""Batches stored this long before an answer's span are read too: an event is stored after it happened,
give or take the node's clock offset."""
READS = 3


@dataclass
class Raw:
    """The rollups of the frames that start in raw batches, within a span."""

    rollups: dict[Key, Rollup] = field(default_factory=dict)
    events: int = 0
    """Raw events read (or, not ``included``, left out)."""
    included: bool = True
    stored_ns: tuple[int, int] | None = None
    """When the raw batches were stored, first and last (relay clock)."""
    why: str = ""
    """Why they were left out."""
    newest_ns: int | None = None
    """The newest raw event's time (node clock)."""

    def minutes(self) -> list[int]:
        """The minutes (node clock) that hold frames read raw."""
        return sorted({t for (_, w, t) in self.rollups if w == MINUTE_NS})

    def view(self) -> dict:
        minutes = self.minutes()
        return {"events": self.events, "included": self.included, "minutes": len(minutes),
                "first_ns": minutes[0] if minutes else None, "last_ns": minutes[-1] if minutes else None,
                "stored_ns": list(self.stored_ns) if self.stored_ns else None, "said": self.said()}

    def said(self) -> str:
        """A line for the reader: which minutes were raw, and whether they are counted."""
        if not self.events:
            return ""
        if not self.included:
            first, last = self.stored_ns or (0, 0)
            return (f"{self.events:,} events stored {hhmm(first)} to {hhmm(last)} UTC are not rolled up yet and not "
                    f"counted here ({self.why}): `dcuscope db compact` rolls them up")
        minutes = self.minutes()
        if not minutes:
            return f"{self.events:,} raw events not rolled up yet: no frame of this span starts in them"
        return (f"minutes {hhmm(minutes[0])} to {hhmm(minutes[-1] + MINUTE_NS)} UTC were still raw ({self.events:,} "
                f"events not rolled up yet): counted from the stored batches")


def with_raw(database: Database, node: str, since_ns: int, until_ns: int,
             read: Callable[[], Any]) -> tuple[Any, Raw]:
    """``read()`` (the stored rollups) and the :class:`Raw` rollups of ``node``'s frames starting in
    ``since_ns..until_ns`` in raw batches, consistent with each other (see the module)."""
    received = since_ns - MARGIN_NS
    for _ in range(READS):
        listed = database.unrolled_batches(node, received)
        stored = read()
        events = sum(c for _, _, c, _ in listed)
        span = (min(t for *_, t in listed), max(t for *_, t in listed)) if listed else None
        if not listed:
            return stored, Raw()
        if events > MAX_RAW_EVENTS:
            return stored, Raw(events=events, included=False, stored_ns=span,
                               why=f"over {MAX_RAW_EVENTS:,} to read for one answer")
        payloads = database.unrolled_payloads(node, received)
        if {(r, s) for r, s, _, _ in listed} <= {(r, s) for r, s, _, _ in payloads}:
            break
    else:
        return stored, Raw(events=events, included=False, stored_ns=span, why="compaction kept moving them")
    raw = Raw(events=events, stored_ns=span)
    by_run: dict[str, list[np.ndarray]] = {}
    for run, seq, compressed, data in payloads:
        try:
            by_run.setdefault(run, []).append(decode_payload(data, compressed))
        except ProtocolError:  # compaction leaves such a batch too (and says so): not counted
            continue
    for run, parts in by_run.items():
        stored_run = database.run_node(run)
        if stored_run is None:
            continue
        header = TraceHeader.from_dict(json.loads(stored_run[1]))
        events_of = np.concatenate(parts)
        if len(events_of):
            raw.newest_ns = max(raw.newest_ns or 0, int(events_of["ts"].max()))
        found = rollups_of(header, events_of, np.ones(len(events_of), bool), database.unrolled_lost(run))
        for (stage, width, start), r in found.items():
            if since_ns // width * width <= start < until_ns:
                key = (stage, width, start)
                raw.rollups[key] = raw.rollups[key].merge(r) if key in raw.rollups else r
    return stored, raw


def hhmm(ns: int) -> str:
    """``ns`` (wall clock) as the UTC minute the raw-batch lines name: ``14:03``."""
    return time.strftime("%H:%M", time.gmtime(ns / 1e9))
