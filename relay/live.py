"""Live per-run delay engine: pairs a node's events by frame as batches arrive (numpy per batch).

Every figure comes from the delay model, :mod:`probes.delays` (``frame_delays``, ``series``,
``delay_summary``), so that the relay's statistics over a run equal ``node_stats`` over the
same events, and its window's are those of the frames in it.

A frame lives in the *open* table (one row per (source, frame): the earliest timestamp of each
(stage, point) cell, as ``frame_table`` keeps) until it is

- *finalised*: its chain is complete (``probes.delays.chains``) and ``settle_s`` of the node's
  time passed since its chain ended, so stragglers still land in it; its per-frame delays then
  join the session's value arrays and its row leaves the open table; or
- *evicted*: incomplete, with no event for ``evict_s`` of the node's time; it is counted.

Time here is the node's own event time (its newest timestamp), so a network cut or a replay
after a relay restart ages nothing. Events for a frame already finalised or evicted (at or
below the source's watermark) are counted as ``late`` and ignored. Frames show up for the UI as
soon as their chain is complete (:meth:`LiveRun.recent`).

Whether a stage has an exit point at all is the one fact of a chain that spans frames; the
engine keeps the run's value of it and hands it to ``chains``, so that every subset of frames
is judged by the exits the whole run has seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from probes.delays import NS_PER_MS, Chains, FrameDelays, Series, chains, delay_summary, frame_delays, series
from probes.events import EXIT, FRAME_CELLS, GROUP, READY, TraceHeader
from probes.facts import Accounting
from probes.frametable import MISSING, FrameTable, frame_events, frame_table_from_cells
from relay.runvalues import RELATIVE_ERROR, OriginSpans, RunValues

KEY_SHIFT = 44  # key = source << 44 | frame; probes.wire bounds both to fit
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
    """Open frames at most (~77 MB with 8 stages, 6 cells each): beyond, the stalest are evicted, so that a
    node whose timestamps stand still cannot make the relay grow without bound."""
    exact_values: int = 262_144
    """Values per series kept exactly for whole-run percentiles (2 MB each); past it, a log
    histogram with percentiles within 1 % (relay.runvalues), so a run of days stays bounded."""
    evicted_kept: int = 65_536
    """Eviction times kept for the rolling window's incomplete count (older ones are outside it)."""


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
    cells: np.ndarray  # (n, n_stages, FRAME_CELLS) int64


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
        self._cells = np.zeros((0, s, FRAME_CELLS), np.int64)
        self._last = np.zeros(0, np.int64)
        self._shown = np.zeros(0, bool)
        self._has_exit = np.zeros(s, bool)
        self._watermark = np.full(0, -1, np.int64)
        self._sources = np.zeros(0, bool)
        self.newest = 0
        # Finalised frames.
        self._values: dict[str, dict[str, RunValues]] = {kind: {} for kind in ("stages", "gaps", "service", "wait")}
        self._frame_values = RunValues(config.exact_values)
        self._glass_values = RunValues(config.exact_values)
        self._busy: dict[str, int] = {}
        self._first_origin: int | None = None
        self._last_end: int | None = None
        self.accounting = Accounting(self.stages)
        self._origins = OriginSpans()
        self._ring = {"source": Grow(np.int32), "frame": Grow(np.int64), "cells": Grow(np.int64, (s, FRAME_CELLS)),
                      "end": Grow(np.int64)}
        self._evicted_last = Grow(np.int64)
        self._recent = {"n": Grow(np.int64), "source": Grow(np.int32), "frame": Grow(np.int64),
                        "cells": Grow(np.int64, (s, FRAME_CELLS))}
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
        """Queue a batch of validated events (stage and point in range, see probes.wire).

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
        self.accounting.add(events)
        events = frame_events(events)
        if len(events) == 0:
            return
        src = events["source"].astype(np.int64)
        frame = events["frame"].astype(np.int64)
        ts = events["ts"].astype(np.int64)
        stage = events["stage"].astype(np.int64)
        point = events["point"].astype(np.int64)
        code = events["code"].astype(np.int64)
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
                key, ts, stage, point, code = key[keep], ts[keep], stage[keep], point[keep], code[keep]
                found = found[keep]
            if not found.all():
                self._open(np.unique(key[~found]))
            pos, _ = self._locate(key)
        if len(key) == 0:
            return
        slot = (pos * self._s + stage) * FRAME_CELLS
        flat = slot + point
        order = np.lexsort((ts, flat))
        fs, tsort = flat[order], ts[order]
        first = np.ones(len(fs), bool)
        first[1:] = fs[1:] != fs[:-1]
        fu, tu = fs[first], tsort[first]
        cells = self._cells.reshape(-1)
        cur = cells[fu]
        cells[fu] = np.where(cur == MISSING, tu, np.minimum(cur, tu))
        ready = point == READY
        cells[slot[ready] + GROUP] = code[ready]
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
        self._cells = np.concatenate([self._cells, np.full((k, self._s, FRAME_CELLS), MISSING, np.int64)])[order]
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
        ch = self._chains(open_)
        complete, end = ch.complete, ch.end
        shown = complete & ~self._shown
        k = int(shown.sum())
        if k:
            self._shown |= shown
            r = self._recent
            r["n"].extend(np.arange(self.visible + 1, self.visible + k + 1))
            r["source"].extend(open_.source[shown])
            r["frame"].extend(open_.frame[shown])
            r["cells"].extend(open_.cells[shown])
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

    def _table(self, frames: _Frames) -> FrameTable:
        return frame_table_from_cells(self.stages, frames.source, frames.frame, frames.cells)

    def _chains(self, frames: _Frames) -> Chains:
        """Completeness and ends of ``frames``, judged by the exit points of the whole run."""
        return chains(self._table(frames), self._has_exit)

    def _delays(self, frames: _Frames) -> FrameDelays:
        """The delay model's figures of ``frames``, judged by the exit points of the whole run."""
        return frame_delays(self._table(frames), self._has_exit)

    def _finalise(self, frames: _Frames, end: np.ndarray) -> None:
        fd = self._delays(frames)
        values = series(fd)
        for kind in self._values:
            for name, v in getattr(values, kind).items():
                self._series(kind, name).extend(v / NS_PER_MS)
        self._frame_values.extend(values.frame / NS_PER_MS)
        self._glass_values.extend(values.glass / NS_PER_MS)
        for name, busy in values.busy.items():
            self._busy[name] = self._busy.get(name, 0) + busy
        c = fd.chains.complete
        if c.any():
            self._note_span(int(fd.table.origin[c].min()), int(fd.chains.end[c].max()))
        self._origins.extend(fd.table.origin[c], fd.table.source[c])
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

    def _note_span(self, first_origin: int, last_end: int) -> None:
        self._first_origin = first_origin if self._first_origin is None else min(self._first_origin, first_origin)
        self._last_end = last_end if self._last_end is None else max(self._last_end, last_end)

    def _all_series(self) -> list[RunValues]:
        return [self._frame_values, self._glass_values, *(v for d in self._values.values() for v in d.values())]

    def _series(self, kind: str, name: str) -> RunValues:
        series = self._values[kind]
        if name not in series:
            series[name] = RunValues(self.config.exact_values)
        return series[name]

    def _raise_watermark(self, source: np.ndarray, frame: np.ndarray) -> None:
        np.maximum.at(self._watermark, source.astype(np.int64), frame.astype(np.int64))

    # --- statistics -----------------------------------------------------------------------------

    def run_stats(self, dropped: int = 0) -> dict:
        """``probes.delays.node_stats`` of every event received for this run."""
        self.maintain()
        fd = self._delays(self._open_frames())
        open_values = series(fd)
        # Every series the run has seen, finalised frames' values added by _session_summary.
        gap_names = sorted(set(self._values["gaps"]) | set(open_values.gaps), key=self._gap_order)
        busy = dict(self._busy)
        for name, ns in open_values.busy.items():
            busy[name] = busy.get(name, 0) + ns
        first, last = self._first_origin, self._last_end
        if open_values.span_ns:
            c = fd.chains.complete
            first = min(x for x in (first, int(fd.table.origin[c].min())) if x is not None)
            last = max(x for x in (last, int(fd.chains.end[c].max())) if x is not None)
        values = Series(stages=open_values.stages, frame=open_values.frame, service=open_values.service,
                        wait=open_values.wait, glass=open_values.glass, busy=busy,
                        span_ns=last - first if first is not None else 0, threads=self.accounting.threads(),
                        gaps={name: open_values.gaps.get(name, np.zeros(0)) for name in gap_names})
        c = fd.chains.complete
        n_open_complete = int(c.sum())
        fps = self._origins.fps(self._all_sources(), fd.table.origin[c], fd.table.source[c])
        return {
            **delay_summary(values, self._session_summary),
            "fps": fps,
            "sources": self.accounting.sources(fps),
            "dropped": int(dropped),
            "frames": {"complete": self.finalised + n_open_complete,
                       "incomplete": self.evicted + len(fd) - n_open_complete},
            "percentile_error": 0.0 if all(v.exact for v in self._all_series()) else RELATIVE_ERROR,
        }

    def _session_summary(self, kind: str, name: str, values_ms: np.ndarray) -> dict:
        """``summarize`` of the finalised values of a series and ``values_ms`` (open frames)."""
        if kind == "frame":
            return self._frame_values.summary(values_ms)
        if kind == "glass":
            return self._glass_values.summary(values_ms)
        return self._series(kind, name).summary(values_ms)

    def window_stats(self) -> dict:
        """The same statistics over frames whose chain ended in the last ``window_s`` (node time)."""
        self.maintain()
        cutoff = self.newest - int(self.config.window_s * 1e9)
        ring = self._ring
        sel = ring["end"].view >= cutoff
        open_ = self._open_frames()
        och = self._chains(open_)
        osel = och.complete & (och.end >= cutoff)
        fd = self._delays(_Frames(np.concatenate([ring["source"].view[sel], open_.source[osel]]),
                                  np.concatenate([ring["frame"].view[sel], open_.frame[osel]]),
                                  np.concatenate([ring["cells"].view[sel], open_.cells[osel]])))
        c = fd.chains.complete
        incomplete = int((self._evicted_last.view >= cutoff).sum()) + int((~och.complete & (self._last >= cutoff)).sum())
        fps = OriginSpans().fps(self._all_sources(), fd.table.origin[c], fd.table.source[c])
        return {
            "window_s": self.config.window_s,
            **delay_summary(series(fd, self.accounting.threads())),
            "fps": fps,
            "sources": self.accounting.sources(fps),
            "frames": {"complete": int(c.sum()), "incomplete": incomplete},
        }

    def _all_sources(self) -> list[int]:
        return sorted(set(int(k) for k in self.header.sources) | set(np.flatnonzero(self._sources).tolist()))

    def _gap_order(self, name: str) -> tuple[int, int]:
        a, _, b = name.partition("->")
        index = {n: i for i, n in enumerate(self.stages)}
        return index.get(b, 0), index.get(a, 0)

    # --- frames for the UI --------------------------------------------------------------------

    def recent(self, since: int = 0, limit: int = 200, newest: bool = False) -> tuple[np.ndarray, FrameDelays]:
        """Complete frames with cursor > ``since``: their cursors and their delays (rows in
        cursor order); the first ``limit`` of them, or the last ``limit`` with ``newest``.
        Only the last ``recent_frames`` are kept."""
        self.maintain()
        r = self._recent
        n = r["n"].view
        after = np.flatnonzero(n > since)
        sel = after[-limit:] if newest else after[:limit]
        return n[sel], self._delays(_Frames(r["source"].view[sel], r["frame"].view[sel], r["cells"].view[sel]))
