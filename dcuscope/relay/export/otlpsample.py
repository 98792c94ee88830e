"""Which finalised frames go out as OpenTelemetry traces: tail-based, decided where the whole frame is known.

A :data:`dcuscope.relay.live.state.FrameObserver`: told of every finalised batch of a run's frames, it picks
every ``every``-th complete frame of the run (a counter, so the choice is deterministic: the
1st, the N+1-th, ...) and every frame whose delay exceeds its node's ``--frame-limit``, copies
their figures (:mod:`dcuscope.relay.export.otlpframes`) and puts them on the exporter's bounded queue. It runs
on the event loop inside the ingest: numpy over the batch, no Python per frame, never waits.
When the queue lacks room, frames over the limit go first, and what does not fit is counted
as dropped (``queue_full``).
"""

from __future__ import annotations

import numpy as np

from dcuscope.model.delays import FrameDelays, Series
from dcuscope.relay.export.otlpframes import copy_frames
from dcuscope.relay.export.otlpqueue import FrameQueue, OtlpCounters
from dcuscope.relay.live.state import RelayState, RunState

COUNTS_SLACK = 64
"""Counters of runs no longer held are forgotten once this many more than the held runs pile up."""


class Sampler:
    def __init__(self, state: RelayState, every: int, queue: FrameQueue, counters: OtlpCounters) -> None:
        self.state = state
        self.every = every
        self.queue = queue
        self.counters = counters
        self._seen: dict[str, int] = {}
        """Run -> complete frames finalised so far (the 1-in-N counter)."""

    def __call__(self, rs: RunState, fd: FrameDelays, values: Series) -> None:
        rows = np.flatnonzero(fd.chains.complete)
        if len(rows) == 0:
            return
        seen = self._count(rs.run, len(rows))
        if self.every:
            sampled = (seen + np.arange(len(rows))) % self.every == 0
        else:
            sampled = np.zeros(len(rows), bool)
        limit = self.state.frame_limits.limit_ns(rs.node)
        over = fd.delay[rows] > limit if limit is not None else np.zeros(len(rows), bool)
        # Over the limit first: when the queue lacks room, they are what must not be lost.
        chosen = np.concatenate((rows[over], rows[sampled & ~over]))
        n_over = int(over.sum())
        if len(chosen) == 0:
            return
        room = max(self.queue.room(), 0)
        if len(chosen) > room:
            self.counters.dropped["queue_full"] += len(chosen) - room
            chosen = chosen[:room]
            if room == 0:
                return
        is_over = np.arange(len(chosen)) < n_over
        self.counters.frames["over_limit"] += int(is_over.sum())
        self.counters.frames["sampled"] += int((~is_over).sum())
        self.queue.put(copy_frames(rs.node, rs.run, rs.header.kinds, rs.header.sources, fd, chosen, is_over,
                                   self.state.correction(rs), limit))

    def _count(self, run: str, n: int) -> int:
        """Frames of ``run`` counted before these ``n``."""
        seen = self._seen.get(run, 0)
        self._seen[run] = seen + n
        if len(self._seen) > len(self.state.runs) + COUNTS_SLACK:
            self._seen = {r: c for r, c in self._seen.items() if r in self.state.runs or r == run}
        return seen
