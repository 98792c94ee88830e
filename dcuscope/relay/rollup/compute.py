"""Rollups: per DCU, stage and minute (and hour), what its frames' delays were, kept long after the events.

A rollup row holds, for the frames of one run whose origin falls in its minute (or hour) of the
node's clock: per stage the sketches (:mod:`dcuscope.relay.rollup.sketch`) of their delay, service and wait,
and the drops at the stage in that time; per frame (the row of stage :data:`FRAME_ROW`) the
end-to-end delays of complete frames, the incomplete ones, and the events the node lost. Rows are
written by compaction (:mod:`dcuscope.relay.store.compaction`), in the transaction that moves a range of
batches into a segment, so that each frame is counted once however often the relay is killed:

- a range's rollups count the frames whose origin event is in the range, paired with the events
  of the range and of the stored rows that follow it (LOOKAHEAD_NS of them: a frame started in a
  range ends in the next one);
- the rows of a minute that several ranges share are merged (sketches add, exactly).

Times are the node's (PTP-synchronised DCUs' clocks are the relay's to a microsecond; a DCU whose
clock is off files its minutes off by as much).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dcuscope.model.delays import frame_delays
from dcuscope.model.frametable import frame_table
from dcuscope.protocol.events import DROP, ORIGIN, TraceHeader
from dcuscope.relay.rollup.sketch import Sketch

FRAME_ROW = ""
"""The stage name of a rollup's per-frame row (end to end); no element is named so."""
MINUTE_NS = 60 * 10**9
HOUR_NS = 3600 * 10**9
WIDTHS_NS = (MINUTE_NS, HOUR_NS)
"""The rollups kept: a month of one DCU is 720 hour rows a stage, read within a second."""
LOOKAHEAD_NS = 10 * 10**9
"""How far past a range's last event its frames are followed (in the rows stored after it)."""

Key = tuple[str, int, int]
"""(stage, width_ns, start_ns)."""


@dataclass
class Rollup:
    delay: Sketch = field(default_factory=Sketch)
    service: Sketch = field(default_factory=Sketch)
    wait: Sketch = field(default_factory=Sketch)
    incomplete: int = 0
    drops: int = 0
    lost: int = 0

    def merge(self, other: "Rollup") -> "Rollup":
        return Rollup(self.delay.merge(other.delay), self.service.merge(other.service), self.wait.merge(other.wait),
                      self.incomplete + other.incomplete, self.drops + other.drops, self.lost + other.lost)


def rollups_of(header: TraceHeader, events: np.ndarray, owned: np.ndarray, lost: int = 0) -> dict[Key, Rollup]:
    """The rollups of the frames whose origin is among the ``owned`` events (a mask of ``events``:
    the range's; the others follow it), and of the owned drop events; ``lost`` events are filed in
    the frame row of the range's last minute and hour."""
    out: dict[Key, Rollup] = {}
    if not len(events):
        return out
    mine = events[owned]
    origins = mine[mine["point"] == ORIGIN]
    table = frame_table(header, events)
    fd = frame_delays(table)
    keys = _pack(table.source, table.frame)
    rows = np.isin(keys, _pack(origins["source"], origins["frame"])) & (table.origin_stage >= 0)
    complete = rows & fd.chains.complete
    for width in WIDTHS_NS:
        start = table.origin // width * width
        for t in np.unique(start[rows]):
            at = rows & (start == t)
            done = at & complete
            frame = out.setdefault((FRAME_ROW, width, int(t)), Rollup())
            frame.delay = Sketch.of(fd.delay[done])
            frame.incomplete = int(at.sum() - done.sum())
            for s, name in enumerate(table.stages):
                if not fd.chains.has_exit[s]:
                    continue
                delay = fd.per_stage["delay"][done, s]
                if np.isnan(delay).all():
                    continue
                service, wait = fd.per_stage["service"][done, s], fd.per_stage["wait"][done, s]
                out[(name, width, int(t))] = Rollup(Sketch.of(delay), Sketch.of(service), Sketch.of(wait))
        drops = mine[mine["point"] == DROP]
        if len(drops):
            where, counts = np.unique(np.stack([drops["stage"].astype(np.int64), drops["ts"] // width * width]),
                                      axis=1, return_counts=True)
            for (stage, t), n in zip(where.T.tolist(), counts.tolist()):
                name = header.stages[stage] if 0 <= stage < len(header.stages) else f"stage {stage}"
                out.setdefault((name, width, t), Rollup()).drops += n
        if lost and len(mine):
            last = int(mine["ts"].max()) // width * width
            out.setdefault((FRAME_ROW, width, last), Rollup()).lost += lost
    return out


def _pack(source: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(source, frame) as one int64 (sources < 2**19, frames < 2**44: protocol.wire)."""
    return (np.asarray(source, np.int64) << 44) | (np.asarray(frame, np.int64) & ((1 << 44) - 1))
