"""What a node's events say besides frame timestamps: drops with their reasons, and facts
(which thread pushes each stage's output, each source's nominal rate and upstream losses).

Both paths count the same way: ``dcuscope stats`` adds all events of a trace at once, the
relay's live engine adds them batch by batch. Counters are kept per source id seen, in dicts
(a hostile id costs one entry, never an array sized by the id).
"""

from __future__ import annotations

import numpy as np

from dcuscope.protocol.events import (DROP, DROP_REASONS, FACT, FACT_DECODER_DROPPED, FACT_LOST_UPSTREAM, FACT_NOMINAL_MHZ,
                           FACT_THREAD, ORIGIN)

SMALL_IDS = 4096
"""Source ids below this are counted in an array; others (any int32 a node may send) in a dict."""


class Accounting:
    """Running counts of one run's drops and facts."""

    def __init__(self, stages: list[str]) -> None:
        self.stages = list(stages)
        self.delivered: dict[int, int] = {}
        """Source -> frames that reached their origin (stamped)."""
        self.dropped: dict[int, dict[str, int]] = {}
        """Source -> reason -> frames the pipeline dropped."""
        self._thread: dict[int, tuple[int, int]] = {}  # stage -> (ts, thread)
        self._source_facts: dict[tuple[int, int], tuple[int, int]] = {}  # (source, kind) -> (ts, value)

    def add(self, events: np.ndarray, origins: tuple[list[list[int]], int] | None = None) -> None:
        """Count a batch; ``origins``: its origins counted per source already, with its greatest point
        (:meth:`dcuscope.model.compiled.OriginCounter.count`)."""
        point = events["point"]
        if origins is not None:
            (sources, _, counts), top = origins
            for sid, n in zip(sources, counts):
                self.delivered[sid] = self.delivered.get(sid, 0) + n
            if top < DROP:
                return
        else:
            self._count_origins(events["source"][point == ORIGIN])
            if len(point) == 0 or point.max() < DROP:  # frame timestamps only, as nearly every batch
                return
        for e in events[point == DROP].tolist():
            reasons = self.dropped.setdefault(int(e[2]), {})
            reason = DROP_REASONS.get(int(e[5]), "unknown")
            reasons[reason] = reasons.get(reason, 0) + 1
        for ts, value, source, stage, _point, kind in events[point == FACT].tolist():
            if kind == FACT_THREAD:
                if ts >= self._thread.get(stage, (-1, 0))[0]:
                    self._thread[stage] = (ts, value)
            elif ts >= self._source_facts.get((source, kind), (-1, 0))[0]:
                self._source_facts[(source, kind)] = (ts, value)

    def _count_origins(self, origin: np.ndarray) -> None:
        if len(origin) and 0 <= origin.min() and origin.max() < SMALL_IDS:  # a camera index: counted without a sort
            counts = np.bincount(origin)
            ids = np.flatnonzero(counts)
            counts = counts[ids]
        else:
            ids, counts = np.unique(origin, return_counts=True)
        for sid, n in zip(ids.tolist(), counts.tolist()):
            self.delivered[sid] = self.delivered.get(sid, 0) + n

    def threads(self) -> dict[str, int]:
        """Stage name -> the streaming thread that last pushed its output."""
        return {self.stages[s]: thread for s, (_, thread) in self._thread.items() if 0 <= s < len(self.stages)}

    def sources(self, fps: dict[str, float]) -> dict[str, dict]:
        """Source id (str) -> ``{delivered, fps, nominal_fps, lost_upstream, decoder_dropped,
        dropped: {reason: n}}``; ``fps`` (complete frames per second) as the delay model gives it."""
        ids = set(self.delivered) | set(self.dropped) | {s for s, _ in self._source_facts} | {int(k) for k in fps}
        out = {}
        for sid in sorted(ids):
            nominal = self._fact(sid, FACT_NOMINAL_MHZ)
            out[str(sid)] = {
                "delivered": self.delivered.get(sid, 0), "fps": fps.get(str(sid), 0.0),
                "nominal_fps": nominal / 1000 if nominal else None,
                "lost_upstream": self._fact(sid, FACT_LOST_UPSTREAM) or 0,
                "decoder_dropped": self._fact(sid, FACT_DECODER_DROPPED) or 0,
                "dropped": dict(sorted(self.dropped.get(sid, {}).items())),
            }
        return out

    def _fact(self, source: int, kind: int) -> int | None:
        found = self._source_facts.get((source, kind))
        return found[1] if found else None
