"""Compaction: a run's old batches moved into segments (:mod:`dcuscope.relay.store.segment`), from 24 bytes an
event (zlib barely helps a paced batch of a few hundred) to about 3.5.

**Which batches.** Those stored more than ``after_s`` ago (``--compact-after``, default
COMPACT_AFTER_S): long acknowledged, and past what a node may still send again. They go by ranges
of contiguous seqs of one run (a batch missing, still to come or lost, ends a range: a segment is
always every seq from its first to its last), at most MAX_SEGMENT_EVENTS events a segment. A run
that ended or went quiet for ``after_s`` has every due batch compacted. A run still being written
waits until a range holds MIN_SEGMENT_EVENTS (larger segments compress better) or until its oldest
due batch was stored LIVE_WAIT_S ago, whichever comes first: its rollups (below) lag it by at most
max(``after_s``, LIVE_WAIT_S) and a pass, however slowly it goes. The cost, for a slow run: with
the default ``--compact-after`` each pass compacts it, a segment holding a pass's 30 s of its
events; at the demo's DCU-1 pace (155 events/s) 4,700 events at 3.14 bytes an event, where
segments of 100,000 take 2.86 (+10 %: a 20-minute run in SQLite, 40 segments against 2); waiting
for 100,000, it would keep its batches (24 bytes an event) and have no rollups for 11 minutes. A run
at the paper's pace (4,300 events/s) fills MIN_SEGMENT_EVENTS within a pass: compacted as before.

**Crash-safe.** A range moves in one transaction: its batches deleted, only if every one is still
there, and the segment inserted. A relay killed mid-compaction leaves the batches as they were,
one whose transaction committed leaves the segment: nothing is lost and nothing stored twice.
Readers read a run's batches and segments in one statement (one snapshot). A batch sent again
after its range was compacted is recognised as stored (``stored_seqs``, and the insert itself
looks for a segment holding its seq).

**Rollups.** The same transaction merges the rollups of the frames whose origin is in the range
(:mod:`dcuscope.relay.rollup.compute`): each frame is counted once, whatever is killed when.

**Who.** The relay compacts in a process of its own with its own store connection
(:class:`dcuscope.relay.store.compactor.Compactor`), so that reading and encoding never hold up the writer
thread's commits. A relay that stops (SIGINT, SIGTERM) compacts what its runs still hold raw, within
:data:`dcuscope.relay.store.compactor.STOP_ROLLUP_S`; one that starts compacts first what a relay killed outright
left raw (runs not heard from since); readers of rollups count what is still raw from the batches
(:mod:`dcuscope.relay.store.unrolled`). ``dcuscope db compact`` compacts a store no relay is compacting (one written
with ``--compact-after 0``, or by a relay before schema 5). On a shared store any relay may compact
any run, one at a time (an advisory lock per run: two relays never encode the same range), and a
relay that lost the race finds its range gone and leaves it.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np

from dcuscope.protocol.errors import ProtocolError
from dcuscope.protocol.events import EVENT_DTYPE, TraceHeader
from dcuscope.protocol.wire import decode_payload
from dcuscope.relay.rollup.compute import LOOKAHEAD_NS, rollups_of
from dcuscope.relay.store.base import Database
from dcuscope.relay.store.segment import encode

COMPACT_AFTER_S = 60.0
"""Batches are compacted once stored this long (a node keeps at most 64 unacknowledged batches,
resent within seconds)."""
MIN_SEGMENT_EVENTS = 100_000
"""A run still being written is compacted by segments of at least this many events (23 s at the
paper's 4,300 events/s): 3.52 bytes an event, where segments of 43,000 take 3.56."""
LIVE_WAIT_S = 60.0
"""A run still being written has its due batches compacted however few they are once the oldest was
stored this long ago: with ``--compact-after`` 60 s or more, at every pass."""
MAX_SEGMENT_EVENTS = 262_144
"""At most this many events a segment (6 MB to decode at once; a minute at the paper's pace)."""
FOLLOWING_READ = 16
FOLLOWING_BATCHES = 4096
"""Batches read after a range for its frames' ends (rollups: LOOKAHEAD_NS), at most."""

log = logging.getLogger(__name__)


@dataclass
class Compacted:
    """What compaction did: counts and the bytes of the payloads before and of the segments after."""

    segments: int = 0
    batches: int = 0
    events: int = 0
    bytes_before: int = 0
    bytes_after: int = 0
    skipped: int = 0
    """Ranges left as they were: another compactor moved them first, or a batch could not be read."""

    def add(self, other: "Compacted") -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def compact(db: Database, before_ns: int, min_events: int = MIN_SEGMENT_EVENTS,
            say: Callable[[str], None] | None = None, stop: Callable[[], bool] = lambda: False,
            max_events: int = MAX_SEGMENT_EVENTS, waited_ns: int | None = None,
            skip: set[str] = frozenset()) -> Compacted:
    """Compact every batch of ``db`` stored before ``before_ns`` (a live run's: by ``min_events`` at
    least, unless its oldest due batch was stored before ``waited_ns``), segments of ``max_events``
    at most, but those of the runs in ``skip``; ``say`` hears a line per run compacted, ``stop`` is
    asked between ranges."""
    done = Compacted()
    for run, whole in db.compaction_due(before_ns, min_events, waited_ns):
        if stop():
            break
        if run in skip:
            continue
        if not db.claim_compaction(run):
            continue
        try:
            this = compact_run(db, run, before_ns, 1 if whole else min_events, stop, max_events)
        finally:
            db.release_compaction(run)
        done.add(this)
        if say and this.segments:
            say(f"run {run}: {this.batches} batches, {this.events} events -> {this.segments} segments, "
                f"{this.bytes_before / 1e6:.1f} -> {this.bytes_after / 1e6:.2f} MB")
    return done


def compact_run(db: Database, run: str, before_ns: int, min_events: int,
                stop: Callable[[], bool] = lambda: False, max_events: int = MAX_SEGMENT_EVENTS) -> Compacted:
    """Compact the batches of ``run`` stored before ``before_ns``, by contiguous ranges of at least ``min_events``."""
    done = Compacted()
    stored = db.run_node(run)
    if stored is None:
        return done
    node, header = stored[0], TraceHeader.from_dict(json.loads(stored[1]))
    due = db.due_batches(run, before_ns)
    for first, last, events in ranges(due, max_events):
        if events < min_events:
            continue
        if stop():
            break
        done.add(move_range(db, run, first, last, node, header))
    return done


def ranges(due: list[tuple[int, int]], most: int = MAX_SEGMENT_EVENTS) -> list[tuple[int, int, int]]:
    """``(first seq, last seq, events)`` of the contiguous ranges of ``due`` ((seq, count) by seq),
    each of at most ``most`` events (or one batch)."""
    out: list[list[int]] = []
    for seq, count in due:
        if out and seq == out[-1][1] + 1 and out[-1][2] + count <= most:
            out[-1][1] = seq
            out[-1][2] += count
        else:
            out.append([seq, seq, count])
    return [tuple(r) for r in out]


def move_range(db: Database, run: str, first: int, last: int, node: str, header: TraceHeader) -> Compacted:
    """Batches ``first..last`` of ``run`` (of ``node``) into one segment, with the rollups of the frames
    they start, in one transaction (see the module)."""
    rows = db.batch_rows(run, first, last)
    if [seq for seq, _, _, _ in rows] != list(range(first, last + 1)):
        return Compacted(skipped=1)  # another compactor took them, or retention
    parts, counts, size = [], [], 0
    for seq, count, compressed, data in rows:
        try:
            events = decode_payload(data, compressed)
        except ProtocolError as exc:
            log.warning("run %s: stored batch %d cannot be read (%s); its range is left uncompacted", run, seq, exc)
            return Compacted(skipped=1)
        if len(events) != count:
            log.warning("run %s: stored batch %d holds %d events, not %d; its range is left uncompacted",
                        run, seq, len(events), count)
            return Compacted(skipped=1)
        parts.append(events)
        counts.append(count)
        size += len(data)
    events = np.concatenate(parts)
    data = encode(counts, events)
    first_ns, last_ns = (int(events["ts"].min()), int(events["ts"].max())) if len(events) else (0, 0)
    following = _following(db, run, last, last_ns + LOOKAHEAD_NS)
    owned = np.zeros(len(events) + len(following), bool)
    owned[:len(events)] = True
    rollups = rollups_of(header, np.concatenate([events, following]), owned)
    if not db.replace_batches(run, first, last, len(events), first_ns, last_ns, data, node, rollups):
        return Compacted(skipped=1)
    return Compacted(segments=1, batches=len(rows), events=len(events), bytes_before=size, bytes_after=len(data))


def _following(db: Database, run: str, seq: int, until_ns: int) -> np.ndarray:
    """The run's stored events after batch ``seq``, up to the first batch reaching ``until_ns``."""
    parts: list[np.ndarray] = []
    while len(parts) < FOLLOWING_BATCHES:
        batches = db.batches_after(run, seq, FOLLOWING_READ)
        for seq, events in batches:
            parts.append(events)
            if len(events) and int(events["ts"].max()) >= until_ns:
                return np.concatenate(parts)
        if not batches:
            break
    return np.concatenate(parts) if parts else np.zeros(0, EVENT_DTYPE)
