"""What a run's sources delivered and lost within the rolling window, by node time.

:class:`dcuscope.model.facts.Accounting` counts a run's sources over the whole run. The
statistics panel's "last N s" shows the window's frames, so its sources table must count the
same window (a table of 102 frames beside 871 delivered reads as a contradiction): this keeps
the origins per source in bins of ``BIN_NS`` of node time, the drops with their time, and the
cumulative facts (frames lost upstream, dropped by the decoder) as they changed, each for as
long as a window can reach back, so that :meth:`SourceWindow.sources` answers for any cutoff
within it. Origins are binned, so the window's delivered count starts up to ``BIN_NS`` early.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from dcuscope.protocol.events import DROP, DROP_REASONS, FACT, FACT_DECODER_DROPPED, FACT_LOST_UPSTREAM, ORIGIN

BIN_NS = 100_000_000
"""Origins are counted per source in bins this long (node time)."""
SPAN_BINS = 4096
"""A batch's origins of a source spanning fewer bins than this are counted by ``bincount``."""
MAX_DROPS = 65_536
"""Drops kept for the window at most (a pipeline dropping more within a window reads the newest)."""
_COUNTED_FACTS = (FACT_LOST_UPSTREAM, FACT_DECODER_DROPPED)


class SourceWindow:
    """Per source, origins, drops and counter facts of the last ``window_s`` (and a bin) of node time."""

    def __init__(self, window_s: float) -> None:
        self._keep_ns = int(window_s * 1e9) + BIN_NS
        self._bins: dict[int, dict[int, int]] = {}
        """Bin (ts // BIN_NS) -> source -> origins."""
        self._drops: deque[tuple[int, int, str]] = deque(maxlen=MAX_DROPS)
        """(ts, source, reason), oldest first."""
        self._facts: dict[tuple[int, int], deque[tuple[int, int]]] = {}
        """(source, kind) -> (ts, cumulative value), oldest first: the last one before a window's reach
        (its base), then those within."""
        self._newest = 0

    def add(self, events: np.ndarray, origins: tuple[list[list[int]], int] | None = None) -> None:
        """Note a batch of a run's events (every point; only origins, drops and counter facts count);
        ``origins``: its origins counted per source and bin of ``BIN_NS`` already, with its greatest point
        (:meth:`dcuscope.model.compiled.OriginCounter.count`)."""
        if not len(events):
            return
        point, ts = events["point"], events["ts"]
        self._newest = max(self._newest, int(ts.max()))
        (sources, bins, counts), top = origins if origins is not None else _origins(events, point)
        for source, b, n in zip(sources, bins, counts):
            per = self._bins.setdefault(b, {})
            per[source] = per.get(source, 0) + n
        if top >= DROP:  # rare: most batches hold frame timestamps only
            self._add_drops_and_facts(events, point)
        self._trim()

    def _add_drops_and_facts(self, events: np.ndarray, point: np.ndarray) -> None:
        for t, source, reason in events[point == DROP][["ts", "source", "code"]].tolist():
            self._drops.append((t, source, DROP_REASONS.get(reason, "unknown")))
        for t, value, source, kind in events[point == FACT][["ts", "frame", "source", "code"]].tolist():
            if kind in _COUNTED_FACTS:
                self._facts.setdefault((source, kind), deque()).append((t, value))

    def _trim(self) -> None:
        reach = self._newest - self._keep_ns
        if self._bins and min(self._bins) + 1 <= reach // BIN_NS:  # a bin left the reach (not at every batch)
            for b in [b for b in self._bins if (b + 1) * BIN_NS <= reach]:
                del self._bins[b]
        while self._drops and self._drops[0][0] < reach:
            self._drops.popleft()
        for history in self._facts.values():
            while len(history) > 1 and history[1][0] < reach:  # the last one before the reach stays: the base
                history.popleft()

    def sources(self, whole: dict[str, dict], cutoff_ns: int) -> dict[str, dict]:
        """``whole`` (``Accounting.sources`` of the run, whose nominal rate and fps stay) with its counts
        taken over node time from ``cutoff_ns`` on: delivered, lost upstream, decoder dropped, dropped by reason."""
        delivered: dict[int, int] = {}
        for b, per in self._bins.items():
            if (b + 1) * BIN_NS > cutoff_ns:
                for source, n in per.items():
                    delivered[source] = delivered.get(source, 0) + n
        dropped: dict[int, dict[str, int]] = {}
        for t, source, reason in self._drops:
            if t >= cutoff_ns:
                reasons = dropped.setdefault(source, {})
                reasons[reason] = reasons.get(reason, 0) + 1
        out = {}
        for sid, entry in whole.items():
            source = int(sid)
            out[sid] = dict(entry, delivered=delivered.get(source, 0),
                            lost_upstream=self._counted(source, FACT_LOST_UPSTREAM, cutoff_ns),
                            decoder_dropped=self._counted(source, FACT_DECODER_DROPPED, cutoff_ns),
                            dropped=dict(sorted(dropped.get(source, {}).items())))
        return out

    def _counted(self, source: int, kind: int, cutoff_ns: int) -> int:
        """How much a cumulative counter rose from ``cutoff_ns`` on: its newest value less the last before
        the cutoff (a counter first reported within the window counts whole: it rose in it)."""
        history = self._facts.get((source, kind))
        if not history:
            return 0
        before = [v for t, v in history if t < cutoff_ns]
        return max(0, history[-1][1] - (before[-1] if before else 0))


def _origins(events: np.ndarray, point: np.ndarray) -> tuple[list[list[int]], int]:
    """What :meth:`dcuscope.model.compiled.OriginCounter.count` gives, with numpy: ([sources, bins, counts]
    of the batch's origins per source and bin of ``BIN_NS``), and its greatest point."""
    origin = point == ORIGIN
    out: list[list[int]] = [[], [], []]
    if origin.any():
        bins, sources = events["ts"][origin] // BIN_NS, events["source"][origin]
        for source in np.unique(sources).tolist():  # a batch holds a few sources
            mine = bins[sources == source]
            first = int(mine.min())
            if int(mine.max()) - first < SPAN_BINS:  # a batch spans a few bins: counted without a sort
                counts = np.bincount(mine - first)
                keys = np.flatnonzero(counts)
                keys, counts = keys + first, counts[keys]
            else:  # times far apart (a node's clock stepped, or a hostile one): never an array that wide
                keys, counts = np.unique(mine, return_counts=True)
            out[0] += [source] * len(keys)
            out[1] += keys.tolist()
            out[2] += counts.tolist()
    return out, int(point.max())
