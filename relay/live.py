"""Live per-run delay engine: pairs a node's events by frame as batches arrive (numpy per batch).

The definitions are those of :mod:`probes.stats`, applied through its own functions
(``chains``, ``stage_delays_ns``, ``gaps_ns``, ``frame_delays_ns``, ``summarize``) so that the
relay's statistics over a run equal ``node_stats`` over the same events.

A frame lives in the *open* table (one row per (source, frame): the earliest timestamp of each
(stage, point) cell, as ``frame_table`` keeps) until it is

- *finalised*: its chain is complete (``probes.stats.chains``) and ``settle_s`` of the node's
  time passed since its chain ended, so stragglers still land in it; its per-frame delays then
  join the session's value arrays and its row leaves the open table; or
- *evicted*: incomplete, with no event for ``evict_s`` of the node's time; it is counted.

Time here is the node's own event time (its newest timestamp), so a network cut or a replay
after a relay restart ages nothing. Events for a frame already finalised or evicted (at or
below the source's watermark) are counted as ``late`` and ignored. Frames show up for the UI as
soon as their chain is complete (``drain_visible``).

``chains`` derives one cross-frame fact, whether a stage has an exit point at all; a sentinel
row (no origin, so never complete) carrying the exits seen so far makes every subset of frames
see the run's value of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from probes.events import EXIT, TraceHeader
from probes.stats import (MISSING, NS_PER_MS, Chains, FrameTable, chains, frame_delays_ns, gaps_ns,
                          stage_delays_ns, summarize)
from relay.sessionvalues import RELATIVE_ERROR, OriginSpans, SessionValues

KEY_SHIFT = 44  # key = source << 44 | frame; relay.protocol bounds both to fit
FINALISE_PERIOD_NS = 500_000_000
"""Node time between two finalisation/eviction passes."""


@dataclass(frozen=True)
class LiveConfig:
    window_s: float = 10.0
    settle_s: float = 2.0
    evict_s: float = 10.0
    ring_frames: int = 65536
    """Finalised frames kept whole for the rolling window."""
    recent_frames: int = 4096
    """Complete frames kept for the UI and /api/frames."""
    max_open_frames: int = 200_000
    exact_values: int = 262_144
    """Values per series kept exactly for session percentiles (2 MB each); past it, a log
    histogram with percentiles within 1 % (relay.sessionvalues), so a run of days stays bounded."""
    evicted_kept: int = 65_536
    """Eviction times kept for the rolling window's incomplete count (older ones are outside it)."""
    """Open frames at most (~40 MB with 8 stages): beyond, the stalest are evicted, so that a
    node whose timestamps stand still cannot make the relay grow without bound."""


class Grow:
    """A numpy array with amortised appends along axis 0."""

    def __init__(self, dtype, tail: tuple = ()) -> None:
        self._a = np.zeros((64, *tail), dtype)
        self.n = 0

    def extend(self, values: np.ndarray) -> None:
        k = len(values)
        if self.n + k > len(self._a):
            bigger = np.zeros((max(2 * len(self._a), self.n + k), *self._a.shape[1:]), self._a.dtype)
            bigger[:self.n] = self._a[:self.n]
            self._a = bigger
        self._a[self.n:self.n + k] = values
        self.n += k

    def keep_last(self, k: int) -> None:
        if self.n > k:
            self._a[:k] = self._a[self.n - k:self.n]
            self.n = k

    @property
    def view(self) -> np.ndarray:
        return self._a[:self.n]


@dataclass
class _Frames:
    """Frames as full cells, the input both of chains and of the value extraction."""

    source: np.ndarray
    frame: np.ndarray
    cells: np.ndarray  # (n, n_stages, 3) int64


def frame_table_from_cells(stages: list[str], source: np.ndarray, frame: np.ndarray, cells: np.ndarray) -> FrameTable:
    """The FrameTable ``probes.stats.frame_table`` builds, from already paired cells."""
    n = len(source)
    origins = cells[:, :, 0]
    has_origin = origins != MISSING
    origin_stage = np.where(has_origin.any(axis=1), has_origin.argmax(axis=1), -1)
    origin = np.where(origin_stage >= 0, origins[np.arange(n), np.maximum(origin_stage, 0)], MISSING)
    return FrameTable(stages=list(stages), source=source.astype(np.int32), frame=frame.astype(np.int64),
                      origin=origin, origin_stage=origin_stage,
                      enter=np.ascontiguousarray(cells[:, :, 1]), exit=np.ascontiguousarray(cells[:, :, 2]))


class LiveRun:
    """Live pairing and statistics of one run of one node."""

    def __init__(self, header: TraceHeader, config: LiveConfig = LiveConfig()) -> None:
        self.header = header
        self.stages = list(header.stages)
        self.config = config
        s = len(self.stages)
        self._s = s
        # Open frames, sorted by key.
        self._keys = np.zeros(0, np.int64)
        self._cells = np.zeros((0, s, 3), np.int64)
        self._last = np.zeros(0, np.int64)
        self._shown = np.zeros(0, bool)
        self._has_exit = np.zeros(s, bool)
        self._watermark = np.full(0, -1, np.int64)
        self._sources = np.zeros(0, bool)
        self.newest = 0
        # Finalised frames.
        self._stage_values: dict[str, SessionValues] = {}
        self._gap_values: dict[str, SessionValues] = {}
        self._frame_values = SessionValues(config.exact_values)
        self._origins = OriginSpans()
        self._ring = {"source": Grow(np.int32), "frame": Grow(np.int64), "cells": Grow(np.int64, (s, 3)),
                      "end": Grow(np.int64)}
        self._evicted_last = Grow(np.int64)
        self._recent = {"n": Grow(np.int64), "source": Grow(np.int32), "frame": Grow(np.int64),
                        "cells": Grow(np.int64, (s, 3)), "end": Grow(np.int64)}
        self.finalised = 0
        self.evicted = 0
        self.late = 0
        self.events = 0
        self.visible = 0
        """Frames made visible so far: the cursor of the newest one."""
        self._dirty = False
        self._pending: list[np.ndarray] = []
        self._next_finalise = 0

    # --- ingest -------------------------------------------------------------------------------

    def add(self, events: np.ndarray) -> None:
        """Queue a batch of validated events (stage and point in range, see relay.protocol).

        Merging costs a few dozen numpy calls whatever the batch size, so batches wait here
        until the next :meth:`maintain` (the relay's tick) or read, and merge as one.
        """
        if len(events):
            self._pending.append(events)
            self.events += len(events)

    def _merge_pending(self) -> None:
        if not self._pending:
            return
        events = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
        self._pending = []
        self._merge(events)

    def _merge(self, events: np.ndarray) -> None:
        src = events["source"].astype(np.int64)
        frame = events["frame"].astype(np.int64)
        ts = events["ts"].astype(np.int64)
        stage = events["stage"].astype(np.int64)
        point = events["point"].astype(np.int64)
        key = (src << KEY_SHIFT) | frame
        self.newest = max(self.newest, int(ts.max()))
        self._has_exit |= np.bincount(stage[point == EXIT], minlength=self._s)[:self._s] > 0
        self._note_sources(src)

        pos, found = self._locate(key)
        if not found.all():
            nf = ~found
            late = np.zeros(len(key), bool)
            late[nf] = frame[nf] <= self._watermark[src[nf]]  # _note_sources sized it
            if late.any():
                self.late += int(late.sum())
                keep = ~late
                key, ts, stage, point = key[keep], ts[keep], stage[keep], point[keep]
                found = found[keep]
            if not found.all():
                self._open(np.unique(key[~found]))
            pos, _ = self._locate(key)
        if len(key) == 0:
            return
        flat = (pos * self._s + stage) * 3 + point
        order = np.lexsort((ts, flat))
        fs, tsort = flat[order], ts[order]
        first = np.ones(len(fs), bool)
        first[1:] = fs[1:] != fs[:-1]
        fu, tu = fs[first], tsort[first]
        cells = self._cells.reshape(-1)
        cur = cells[fu]
        cells[fu] = np.where(cur == MISSING, tu, np.minimum(cur, tu))
        np.maximum.at(self._last, pos, ts)
        self._dirty = True

    def _locate(self, key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos = np.searchsorted(self._keys, key)
        if len(self._keys) == 0:
            return pos, np.zeros(len(key), bool)
        return pos, self._keys[np.minimum(pos, len(self._keys) - 1)] == key

    def _open(self, new_keys: np.ndarray) -> None:
        keys = np.concatenate([self._keys, new_keys])
        order = np.argsort(keys, kind="stable")
        k = len(new_keys)
        self._keys = keys[order]
        self._cells = np.concatenate([self._cells, np.full((k, self._s, 3), MISSING, np.int64)])[order]
        self._last = np.concatenate([self._last, np.zeros(k, np.int64)])[order]
        self._shown = np.concatenate([self._shown, np.zeros(k, bool)])[order]

    def _note_sources(self, src: np.ndarray) -> None:
        top = int(src.max()) + 1
        if top > len(self._sources):
            self._sources = np.concatenate([self._sources, np.zeros(top - len(self._sources), bool)])
            self._watermark = np.concatenate([self._watermark, np.full(top - len(self._watermark), -1, np.int64)])
        self._sources[src] = True

    # --- periodic: completion, finalisation, eviction -------------------------------------------

    def maintain(self) -> int:
        """Show complete frames, finalise settled ones, evict stale ones; returns frames shown."""
        self._merge_pending()
        if not self._dirty or len(self._keys) == 0:
            return 0
        self._dirty = False
        open_ = self._open_frames()
        table, ch = self._chains(open_)
        complete = ch.complete[:-1]
        end = ch.end[:-1]
        shown = complete & ~self._shown
        k = int(shown.sum())
        if k:
            self._shown |= shown
            r = self._recent
            r["n"].extend(np.arange(self.visible + 1, self.visible + k + 1))
            r["source"].extend(open_.source[shown])
            r["frame"].extend(open_.frame[shown])
            r["cells"].extend(open_.cells[shown])
            r["end"].extend(end[shown])
            self.visible += k
            if r["n"].n > 2 * self.config.recent_frames:
                for g in r.values():
                    g.keep_last(self.config.recent_frames)

        # Finalising costs as much as showing; settled frames can wait a little longer.
        if self.newest < self._next_finalise and len(self._keys) <= self.config.max_open_frames:
            return k
        self._next_finalise = self.newest + FINALISE_PERIOD_NS
        done = complete & (end <= self.newest - int(self.config.settle_s * 1e9))
        stale = ~complete & (self._last < self.newest - int(self.config.evict_s * 1e9))
        excess = len(self._keys) - int(done.sum()) - int(stale.sum()) - self.config.max_open_frames
        if excess > 0:
            candidates = np.flatnonzero(~done & ~stale)
            stale[candidates[np.argsort(self._last[candidates], kind="stable")[:excess]]] = True
        if done.any():
            self._finalise(_Frames(open_.source[done], open_.frame[done], open_.cells[done]), end[done])
        if stale.any():
            self.evicted += int(stale.sum())
            self._evicted_last.extend(self._last[stale])
            if self._evicted_last.n > 2 * self.config.evicted_kept:
                self._evicted_last.keep_last(self.config.evicted_kept)
            self._raise_watermark(open_.source[stale], open_.frame[stale])
        gone = done | stale
        if gone.any():
            keep = ~gone
            self._keys, self._cells = self._keys[keep], self._cells[keep]
            self._last, self._shown = self._last[keep], self._shown[keep]
        return k

    def _open_frames(self) -> _Frames:
        return _Frames((self._keys >> KEY_SHIFT).astype(np.int32), self._keys & ((1 << KEY_SHIFT) - 1), self._cells)

    def _chains(self, frames: _Frames) -> tuple[FrameTable, Chains]:
        """Table and chains of ``frames`` plus the sentinel row (last)."""
        sentinel = np.full((1, self._s, 3), MISSING, np.int64)
        sentinel[0, self._has_exit, 2] = 1
        src = np.concatenate([frames.source, frames.source[:1] if len(frames.source) else np.zeros(1, np.int32)])
        table = frame_table_from_cells(self.stages, src, np.concatenate([frames.frame, [0]]),
                                       np.concatenate([frames.cells, sentinel]))
        return table, chains(table)

    def _finalise(self, frames: _Frames, end: np.ndarray) -> None:
        table, ch = self._chains(frames)
        for name, v in stage_delays_ns(table, ch).items():
            self._series(self._stage_values, name).extend(v / NS_PER_MS)
        for name, v in gaps_ns(table, ch).items():
            self._series(self._gap_values, name).extend(v / NS_PER_MS)
        self._frame_values.extend(frame_delays_ns(table, ch) / NS_PER_MS)
        c = ch.complete
        self._origins.extend(table.origin[c], table.source[c])
        self.finalised += int(c.sum())
        ring = self._ring
        ring["source"].extend(frames.source)
        ring["frame"].extend(frames.frame)
        ring["cells"].extend(frames.cells)
        ring["end"].extend(end)
        if ring["end"].n > 2 * self.config.ring_frames:
            for g in ring.values():
                g.keep_last(self.config.ring_frames)
        self._raise_watermark(frames.source, frames.frame)

    def _all_series(self) -> list[SessionValues]:
        return [self._frame_values, *self._stage_values.values(), *self._gap_values.values()]

    def _series(self, series: dict[str, SessionValues], name: str) -> SessionValues:
        if name not in series:
            series[name] = SessionValues(self.config.exact_values)
        return series[name]

    def _raise_watermark(self, source: np.ndarray, frame: np.ndarray) -> None:
        np.maximum.at(self._watermark, source.astype(np.int64), frame.astype(np.int64))

    # --- statistics -----------------------------------------------------------------------------

    def session_stats(self, dropped: int = 0) -> dict:
        """``probes.stats.node_stats`` of every event received for this run."""
        self.maintain()
        open_ = self._open_frames()
        table, ch = self._chains(open_)
        stage_v = {k: v / NS_PER_MS for k, v in stage_delays_ns(table, ch).items()}
        gap_v = {k: v / NS_PER_MS for k, v in gaps_ns(table, ch).items()}
        stages = {}
        for s, name in enumerate(self.stages):
            if self._has_exit[s]:
                stages[name] = self._series(self._stage_values, name).summary(stage_v.get(name))
        gaps = {}
        for name in sorted(set(self._gap_values) | set(gap_v), key=self._gap_order):
            gaps[name] = self._series(self._gap_values, name).summary(gap_v.get(name))
        frame = self._frame_values.summary(frame_delays_ns(table, ch) / NS_PER_MS)
        c = ch.complete
        n_open_complete = int(c.sum())
        n_open_incomplete = len(open_.source) - n_open_complete
        return {
            "stages": stages, "gaps": gaps, "frame": frame,
            "fps": self._origins.fps(self._all_sources(), table.origin[c], table.source[c]),
            "dropped": int(dropped),
            "frames": {"complete": self.finalised + n_open_complete, "incomplete": self.evicted + n_open_incomplete},
            "percentile_error": 0.0 if all(v.exact for v in self._all_series()) else RELATIVE_ERROR,
        }

    def window_stats(self) -> dict:
        """The same statistics over frames whose chain ended in the last ``window_s`` (node time)."""
        self.maintain()
        cutoff = self.newest - int(self.config.window_s * 1e9)
        ring = self._ring
        sel = ring["end"].view >= cutoff
        open_ = self._open_frames()
        _, och = self._chains(open_)
        osel = och.complete[:-1] & (och.end[:-1] >= cutoff)
        frames = _Frames(np.concatenate([ring["source"].view[sel], open_.source[osel]]),
                         np.concatenate([ring["frame"].view[sel], open_.frame[osel]]),
                         np.concatenate([ring["cells"].view[sel], open_.cells[osel]]))
        table, ch = self._chains(frames)
        c = ch.complete
        incomplete = int((self._evicted_last.view >= cutoff).sum()) + \
            int((~och.complete[:-1] & (self._last >= cutoff)).sum())
        return {
            "window_s": self.config.window_s,
            "stages": {k: summarize(v / NS_PER_MS) for k, v in stage_delays_ns(table, ch).items()},
            "gaps": {k: summarize(v / NS_PER_MS) for k, v in gaps_ns(table, ch).items()},
            "frame": summarize(frame_delays_ns(table, ch) / NS_PER_MS),
            "fps": OriginSpans().fps(self._all_sources(), table.origin[c], table.source[c]),
            "frames": {"complete": int(c.sum()), "incomplete": incomplete},
        }

    def _all_sources(self) -> list[int]:
        return sorted(set(int(k) for k in self.header.sources) | set(np.flatnonzero(self._sources).tolist()))

    def _gap_order(self, name: str) -> tuple[int, int]:
        a, _, b = name.partition("->")
        index = {n: i for i, n in enumerate(self.stages)}
        return index.get(b, 0), index.get(a, 0)

    # --- frames for the UI --------------------------------------------------------------------

    def recent(self, since: int = 0, limit: int = 200, newest: bool = False) -> dict:
        """Complete frames with cursor > ``since``, as column arrays: the first ``limit`` of
        them, or the last ``limit`` with ``newest``. Only the last ``recent_frames`` are kept."""
        self.maintain()
        r = self._recent
        n = r["n"].view
        after = np.flatnonzero(n > since)
        sel = after[-limit:] if newest else after[:limit]
        return {"n": n[sel], "source": r["source"].view[sel], "frame": r["frame"].view[sel],
                "cells": r["cells"].view[sel], "end": r["end"].view[sel]}


def bottleneck(stats: dict) -> dict | None:
    """The stage with the largest share of the mean frame delay."""
    means = {k: v["mean_ms"] for k, v in stats["stages"].items() if v["mean_ms"] is not None}
    if not means:
        return None
    name = max(means, key=means.get)
    frame_mean = stats["frame"]["mean_ms"]
    return {"stage": name, "mean_ms": means[name],
            "share": means[name] / frame_mean if frame_mean else None}
