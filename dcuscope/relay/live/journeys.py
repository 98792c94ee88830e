"""Journeys across the runs a relay holds, live: :mod:`dcuscope.model.journeys` on the relay's clock.

Each run's crossings (its ``link``/``key`` event pairs) are kept as its batches arrive, on the
node's clock; a batch that ends between a ``link`` and its ``key`` hands the ``link`` to the next.
Joining happens when asked (``/api/journeys``, ``/metrics``, the page's Journeys tab and Stage view),
at most every :data:`MAX_AGE_S`, over each run's last minute of crossings (:data:`LIVE_SPAN_NS`):
each run's crossings moved by its correction then, its frames' spans taken from its recent
complete frames (:meth:`dcuscope.relay.live.run.LiveRun.recent`), its bound the correction's. A
journey whose frames left the runs' recent frames is not shown; its hop still counts. The live
figures are the last minute's; a stored session's (``dcuscope stats --db``) are the whole run's.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from dcuscope.model.frametable import MISSING
from dcuscope.model.journeys import CROSSING_DTYPE, Joined, Side, Spans, crossings, join_sides
from dcuscope.model.names import unique_names
from dcuscope.protocol.events import LINK
from dcuscope.relay.clock.correction import UNKNOWN_BOUND, Correction

KEEP_CROSSINGS = 20_000
"""Crossings kept per run (the newest): about 13 minutes of a 25 frames/s stream that crosses."""
LIVE_SPAN_NS = 60 * 10**9
"""The live join looks at each run's crossings of its last minute (node time): a join's cost is
Python per frame (~16 µs an arrived frame, 20 ms a 25 frames/s link)."""
NEWEST_JOURNEYS = 1000
"""Journeys walked per join: of the frames that arrived last (the page shows tens, /metrics counts
those that ended since its last scrape)."""
MAX_AGE_S = 0.5


@dataclass
class _RunCrossings:
    kept: list[np.ndarray] = field(default_factory=list)
    n: int = 0
    carry: np.ndarray | None = None
    """The batch's last event when it was a ``link``: its ``key`` comes first in the next batch."""

    def add(self, events: np.ndarray) -> None:
        if self.carry is not None:
            events = np.concatenate([self.carry, events])
        self.carry = events[-1:].copy() if len(events) and events["point"][-1] == LINK else None
        found = crossings(events)
        if len(found):
            self.kept.append(found)
            self.n += len(found)
        while self.kept and self.n - len(self.kept[0]) >= KEEP_CROSSINGS:  # the oldest batches' go
            self.n -= len(self.kept.pop(0))

    def all(self) -> np.ndarray:
        if len(self.kept) > 1:
            self.kept = [np.concatenate(self.kept)]
        return self.kept[0] if self.kept else np.zeros(0, CROSSING_DTYPE)


@dataclass(frozen=True)
class RunPart:
    """What a join needs of one run the relay holds: its node, correction and recent frames."""

    node: str
    correction: Correction
    recent: Callable[[], object]
    """The run's recent complete frames' FrameDelays (``LiveRun.recent(...)[1]``)."""


class LiveJourneys:
    def __init__(self) -> None:
        self._runs: dict[str, _RunCrossings] = {}
        self._joined: tuple[float, Joined] | None = None

    def add(self, run: str, events: np.ndarray) -> None:
        """A batch of ``run`` was stored: keep its crossings (cheap when it has none)."""
        kept = self._runs.get(run)
        if len(events) == 0 or (kept is None or kept.carry is None) and events["point"].max() < LINK:
            return
        if kept is None:
            kept = self._runs[run] = _RunCrossings()
        kept.add(events)

    def forget(self, run: str) -> None:
        self._runs.pop(run, None)

    @property
    def runs(self) -> list[str]:
        return [run for run, kept in self._runs.items() if kept.n]

    def joined(self, parts: dict[str, RunPart], fresh: bool = False) -> Joined:
        """The join of the runs in ``parts`` (run id -> its part) that crossed, on the relay's clock."""
        now = time.monotonic()
        if not fresh and self._joined is not None and now - self._joined[0] < MAX_AGE_S:
            return self._joined[1]
        runs = [run for run in self.runs if run in parts]
        names = unique_names(parts[run].node for run in runs)
        joined = join_sides([_side(name, _recent(self._runs[run].all()), parts[run]) for name, run in zip(names, runs)],
                            newest=NEWEST_JOURNEYS)
        self._joined = (now, joined)
        return joined


def _recent(found: np.ndarray) -> np.ndarray:
    """The crossings of the run's last LIVE_SPAN_NS."""
    return found[found["ts"] >= found["ts"].max() - LIVE_SPAN_NS] if len(found) else found


def _side(name: str, found: np.ndarray, part: RunPart) -> Side:
    correction = part.correction
    moved = found.copy()
    moved["ts"] = correction.correct(found["ts"], found["ts"])
    known = correction.applied not in UNKNOWN_BOUND  # else a hop's clock error is unknown too
    on_relay = correction.on_relay_clock() if known else None  # the crossings' times are the relay's now

    def bound(ts: int) -> int | None:
        return int(on_relay.at(ts)[1]) if on_relay is not None else None

    return Side(name, moved, lambda: recent_spans(part.recent(), correction), bound)


def recent_spans(fd, correction: Correction) -> Spans:
    """The spans of a run's recent complete frames (FrameDelays), on the relay's clock."""
    table = fd.table
    first = np.where((table.capture != MISSING) & (table.capture < table.origin), table.capture, table.origin)
    start = correction.correct(table.origin, table.origin)
    # A capture time is the camera's clock: kept as it is (as stored sessions keep it).
    first = np.where(first == table.origin, start, first)
    end = correction.correct(fd.chains.end, table.origin)
    return Spans.of(table.source, table.frame, first, end)


def parts_of(runs: Iterable, correction: Callable, recent_frames: int) -> dict[str, RunPart]:
    """The parts of the relay's held runs (RunState), their corrections by ``correction(rs)``."""
    return {rs.run: RunPart(rs.node, correction(rs),
                            lambda rs=rs: rs.live.recent(0, recent_frames, newest=True)[1]) for rs in runs}
