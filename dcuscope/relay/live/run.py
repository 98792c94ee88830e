"""Live per-run delay engine: pairs a node's events by frame as batches arrive (in the compiled core,
:mod:`dcuscope.model.compiled`, where it loads; numpy, the reference, otherwise).

Every figure comes from the delay model, :mod:`dcuscope.model.delays` (``frame_delays``, ``series``,
``delay_summary``), so that the relay's statistics over a run equal ``node_stats`` over the
same events, and its window's are those of the frames in it.

A frame lives in the *open* table (one row per (source, frame): the earliest timestamp of each
(stage, point) cell, as ``frame_table`` keeps) until it is

- *finalised*: its chain is complete (``model.delays.chains``) and ``settle_s`` of the node's
  time passed since its chain ended, so stragglers still land in it; its per-frame delays then
  join the session's value arrays and its row leaves the open table; or
- *evicted*: incomplete, with no event for ``evict_s`` of the node's time; it is counted.

Time here is the node's own event time (its newest timestamp), so a network cut or a replay
after a relay restart ages nothing. The rolling window alone is cut at the present instead
(:meth:`LiveRun.present_ns`): the node's newest event plus the relay's time since it last heard
from the node, so that the window of a run that ended or went silent empties within ``window_s``
rather than holding its last frames for ever. Events for a frame already finalised or evicted
(at or below the source's watermark) are counted as ``late`` and ignored. Frames show up for the UI as
soon as their chain is complete (:meth:`LiveRun.recent`).

Memory is bounded in bytes (:meth:`LiveRun.set_budget`): the budget is split between the open
table, the window's ring, the recent frames and the exact values, and each part's cap in frames or
values follows from the run's row size, so a run declaring many stages holds fewer frames, not more
bytes. A batch that would open more frames than the cap evicts the stalest open frames first, and
opens only its newest ones if it holds more new frames than the cap (the rest count as evicted).
Source ids are kept in a sorted array of those seen (never an array sized by an id).

Whether a stage has an exit point at all is the one fact of a chain that spans frames; the
engine keeps the run's value of it and hands it to ``chains``, so that every subset of frames
is judged by the exits the whole run has seen.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from dcuscope.model.delays import (NS_PER_MS, STAGE_COLUMNS, FrameDelays, FrameValues, Series, delay_summary,
                                          frame_delays, frame_values, series, series_of)
from dcuscope.model.facts import Accounting
from dcuscope.model.frametable import MISSING, FrameTable, frame_events, frame_table_from_cells
from dcuscope.protocol.events import EXIT, FRAME_CELLS, GROUP, READY, TraceHeader
from dcuscope.model import compiled as compiled_core
from dcuscope.relay.live import framepack
from dcuscope.relay.live.opentable import OpenTable
from dcuscope.relay.live.sourcewindow import BIN_NS, SourceWindow
from dcuscope.relay.live.values import RELATIVE_ERROR, OriginSpans, RunValues

NEVER = np.iinfo(np.int64).max
KEY_SHIFT = 44  # key = source << 44 | frame; protocol.wire bounds both to fit
FINALISE_PERIOD_NS = 500_000_000
"""Node time between two finalisation/eviction passes."""
MERGE_EVENTS = 65536
"""Queued events merged at once at most (one batch's worth), so a merge's transient arrays stay small."""
FRAME_OVERHEAD = 32
"""Bytes an open frame holds besides its cells (key, last timestamp, shown flag, merge copies)."""
RECENT_OVERHEAD = 20
"""Bytes a recent frame holds besides its cells and pushed columns (cursor, source, frame)."""
SHARES = {"open": 0.25, "ring": 0.2, "recent": 0.05, "exact": 0.45, "evicted": 0.05}
"""How a run's byte budget is split between its parts."""
PUSHED_FRAMES = 512
"""Complete frames whose pushed columns are kept: at least the most a push carries
(``relay.api.interest.MAX_FRAMES``, 500)."""
MIN_FRAMES = 16
"""Frames every part may hold whatever the budget."""


def kept_frame_bytes(stages: int) -> int:
    """Bytes a frame kept for the rolling window holds with ``stages`` stages: its
    :class:`~dcuscope.model.delays.FrameValues` (four per-stage float64 columns, ``prev`` (int16)
    and ``first`` per stage, three of 8 bytes), ``lacks_exit`` per stage, its source (4) and end (8)."""
    return stages * (len(STAGE_COLUMNS) * 8 + 2 + 1 + 1) + 3 * 8 + 4 + 8


@dataclass(frozen=True)
class LiveConfig:
    window_s: float = 10.0
    settle_s: float = 2.0
    evict_s: float = 10.0
    ring_frames: int = 65536
    """Finalised frames kept for the rolling window (their values, :attr:`LiveRun._ring`)."""
    recent_frames: int = 4096
    """Complete frames kept for the UI and /api/frames."""
    max_open_frames: int = 200_000
    """Open frames at most (~77 MB with 8 stages, 6 cells each): beyond, the stalest are evicted, so that a
    node whose timestamps stand still cannot make the relay grow without bound. The run's byte budget
    (``LiveRun.set_budget``) may lower it, as it lowers the ring, the recent frames and exact values."""
    exact_values: int = 262_144
    """Values per series kept exactly for whole-run percentiles (2 MB each); past it, a log
    histogram with percentiles within 1 % (relay.live.values), so a run of days stays bounded. The
    run's byte budget may lower it (default relay: 64 MiB a run, ~110,000 values a series at 8 stages)."""
    evicted_kept: int = 65_536
    """Eviction times kept for the rolling window's incomplete count (older ones are outside it)."""


class Grow:
    """A numpy array with amortised appends along axis 0, keeping (with a ``cap``) the newest
    ``cap`` to ``2 * cap`` rows in at most ``2 * cap`` rows of memory."""

    def __init__(self, dtype, tail: tuple = (), cap: int | None = None) -> None:
        self._a = np.zeros((64, *tail), dtype)
        self.n = 0
        self.cap = cap

    def extend(self, values: np.ndarray) -> None:
        if self.cap is not None and self.n + len(values) > 2 * self.cap:
            values = values[-self.cap:]
            self.keep_last(self.cap - len(values))
        k = len(values)
        if self.n + k > len(self._a):
            size = max(2 * len(self._a), self.n + k)
            bigger = np.zeros((size if self.cap is None else min(size, 2 * self.cap), *self._a.shape[1:]),
                              self._a.dtype)
            bigger[:self.n] = self._a[:self.n]
            self._a = bigger
        self._a[self.n:self.n + k] = values
        self.n += k

    def set_cap(self, cap: int) -> None:
        """Keep the newest ``cap`` rows from now on; memory shrinks to ``2 * cap`` rows now."""
        self.cap = cap
        if self.n > 2 * cap:
            self.keep_last(cap)
        if len(self._a) > 2 * cap:
            self._a = self._a[:max(self.n, 2 * cap)].copy()

    @property
    def nbytes(self) -> int:
        return self._a.nbytes

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


@dataclass
class _Tick:
    """One run's maintenance between merging and showing: its open frames and those judged now,
    with what judging them gave (:meth:`LiveRun._judge_rows`, or with numpy :func:`_judge_together`)."""

    run: LiveRun
    rows: np.ndarray
    """The open rows judged now."""
    complete: np.ndarray | None = None
    end: np.ndarray | None = None
    ints: np.ndarray | None = None
    """Their :func:`dcuscope.relay.live.framepack.node_columns` (cursors not set)."""
    floats: np.ndarray | None = None
    _open: _Frames | None = None

    @property
    def open_(self) -> _Frames:
        """The run's open frames (made when first asked: a compiled tick that finalises nothing never does)."""
        if self._open is None:
            self._open = self.run._open_frames()
        return self._open


def maintain_all(runs: Iterable[LiveRun]) -> None:
    """:meth:`LiveRun.maintain` of every run, the frames of runs of one graph judged in one pass of
    the delay model: its cost is numpy's per call, so a relay's tick costs one pass per graph, not
    one per DCU."""
    ticks = [tick for run in runs if (tick := run._start_tick()) is not None]
    groups: dict[tuple, list[_Tick]] = {}
    for tick in ticks:
        if not len(tick.rows):
            continue
        if tick.run._compiled is not None:  # one compiled pass a run: nothing to gain from judging runs together
            tick.run._judge_rows(tick)
        else:
            groups.setdefault(tick.run._judge_key(), []).append(tick)
    for group in groups.values():
        _judge_together(group)
    for tick in ticks:
        tick.run._end_tick(tick)


def _judge_together(ticks: list[_Tick]) -> None:
    """Judge the frames of ``ticks`` (runs of one :meth:`LiveRun._judge_key`) in one pass: which are
    complete, where their chains end, and their pushed columns."""
    judged = [_Frames(t.open_.source[t.rows], t.open_.frame[t.rows], t.open_.cells[t.rows]) for t in ticks]
    if len(ticks) == 1:
        frames = judged[0]
    else:
        frames = _Frames(*(np.concatenate([getattr(f, k) for f in judged]) for k in ("source", "frame", "cells")))
    fd = ticks[0].run._delays(frames)
    ints, floats = framepack.node_columns(np.zeros(len(fd), np.int64), fd)
    at = 0
    for t in ticks:
        part = slice(at, at + len(t.rows))
        t.complete, t.end = fd.chains.complete[part], fd.chains.end[part]
        t.ints, t.floats = ints[:, part], floats[:, part]
        at = part.stop


class LiveRun:
    """Live pairing and statistics of one run of one node."""

    def __init__(self, header: TraceHeader, config: LiveConfig = LiveConfig(), budget: int | None = None, *,
                 compiled: bool = True) -> None:
        """``compiled``: merge batches and judge frames with the compiled core where it loads
        (:mod:`dcuscope.model.compiled`); False does both with numpy (the two leave a run alike)."""
        self.header = header
        self.stages = list(header.stages)
        self.config = config
        s = len(self.stages)
        self._s = s
        self._compiled = compiled_core.load() if compiled else None
        self._open = OpenTable(s, self._compiled)
        self._links: np.ndarray | None = None
        """The header's links as the compiled judge takes them (made at the first tick)."""
        self._origins_counter = None if self._compiled is None else compiled_core.OriginCounter(self._compiled, BIN_NS)
        """Counts each merged batch's origins per source and window bin, for the accounting and the window."""
        self._has_exit = np.zeros(s, bool)
        self._judged_exits: np.ndarray | None = None
        """``_has_exit`` when the shown frames were judged: should it change, they are judged again."""
        # Source ids seen, sorted, with what is kept per id alongside.
        self._src_ids = np.zeros(0, np.int64)
        self._watermark = np.zeros(0, np.int64)
        self._framed = np.zeros(0, bool)
        """Sources with frame timestamps (not only drops or facts)."""
        self.newest = 0
        self._heard_ns: int | None = None
        """``time.monotonic_ns()`` when the last batch was added (None before the first)."""
        # Finalised frames.
        self._values: dict[str, dict[str, RunValues]] = {kind: {} for kind in ("stages", "gaps", "service", "wait")}
        self._open_cap = config.max_open_frames
        self._exact_limit = config.exact_values
        self._frame_values = RunValues(config.exact_values)
        self._glass_values = RunValues(config.exact_values)
        self._busy: dict[str, int] = {}
        self._first_origin: int | None = None
        self._last_end: int | None = None
        self.accounting = Accounting(self.stages)
        self._source_window = SourceWindow(config.window_s)
        self._origins = OriginSpans()
        ring, recent = config.ring_frames, config.recent_frames
        self._ring = {"source": Grow(np.int32, cap=ring), "end": Grow(np.int64, cap=ring),
                      **{f"stage_{k}": Grow(np.float64, (s,), ring) for k in STAGE_COLUMNS}, "prev": Grow(np.int16, (s,), ring),
                      "first": Grow(bool, (s,), ring), "frame_delay": Grow(np.float64, cap=ring),
                      "glass": Grow(np.float64, cap=ring), "origin": Grow(np.int64, cap=ring),
                      "lacks_exit": Grow(bool, (s,), ring)}
        """The complete frames finalised, kept for the rolling window: the values its statistics take
        of them (:class:`~dcuscope.model.delays.FrameValues`), so that they are not judged again,
        and the stages each passed with no exit there. None of the values depends on the run's exit
        points; completeness does, and only through those stages: a kept frame that passed a stage
        without an exit there is incomplete once the run has seen an exit at that stage."""
        self._evicted_last = Grow(np.int64, cap=config.evicted_kept)
        self._recent = {"n": Grow(np.int64, cap=recent), "source": Grow(np.int32, cap=recent),
                        "frame": Grow(np.int64, cap=recent), "cells": Grow(np.int64, (s, FRAME_CELLS), recent)}
        """The complete frames, newest last (for :meth:`recent`)."""
        pushed = min(PUSHED_FRAMES, recent)
        self._pushed = {"ints": Grow(np.int64, (framepack.int_rows(s),), pushed),
                        "floats": Grow(np.float64, (framepack.float_rows(s),), pushed)}
        """The newest complete frames' pushed columns (:func:`dcuscope.relay.live.framepack.node_columns`, a
        row per frame, the cursor first; for :meth:`recent_columns`)."""
        self.finalised = 0
        self.evicted = 0
        self.late = 0
        self.events = 0
        self.visible = 0
        """Frames made visible so far: the cursor of the newest one."""
        self._dirty = False
        self._pending: list[np.ndarray] = []
        self._next_finalise = 0
        self._settle_ns = int(config.settle_s * 1e9)
        """How long a complete frame waits for stragglers before it is finalised (0 once the run ended)."""
        self.on_finalise: Callable[[FrameDelays, Series], None] | None = None
        """Called with the figures of every finalised batch of frames (all complete), exactly once
        per frame: the exporters (``/metrics``, OTLP) take them from here, so they derive nothing again."""
        if budget is not None:
            self.set_budget(budget)

    # --- memory ---------------------------------------------------------------------------------

    def set_budget(self, budget: int) -> None:
        """Hold at most about ``budget`` bytes from now on: each part's cap follows from its share
        and the run's row size; what is over a lowered cap goes now (open frames evicted, the
        oldest kept frames dropped, exact values moved into histograms)."""
        c, row = self.config, self._s * FRAME_CELLS * 8
        share = {part: int(budget * f) for part, f in SHARES.items()}
        self._open_cap = min(c.max_open_frames, max(MIN_FRAMES, share["open"] // (row + FRAME_OVERHEAD)))
        ring = min(c.ring_frames, max(MIN_FRAMES, share["ring"] // (2 * kept_frame_bytes(self._s))))
        pushed = (framepack.int_rows(self._s) + framepack.float_rows(self._s)) * 8
        recent = min(c.recent_frames, max(MIN_FRAMES, share["recent"] // (2 * (row + pushed + RECENT_OVERHEAD))))
        for g in self._ring.values():
            g.set_cap(ring)
        for g in self._recent.values():
            g.set_cap(recent)
        for g in self._pushed.values():
            g.set_cap(min(PUSHED_FRAMES, recent))
        self._evicted_last.set_cap(min(c.evicted_kept, max(MIN_FRAMES, share["evicted"] // 16)))
        # Series: per stage its delays, service, wait and the gap to the next, plus frame and glass.
        self._exact_limit = min(c.exact_values, max(64, share["exact"] // (8 * (4 * self._s + 1))))
        for v in self._all_series():
            v.lower_limit(self._exact_limit)
        excess = self._open.n - self._open_cap
        if excess > 0:
            self._evict_open(np.argsort(self._open.last, kind="stable")[:excess])

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays this run holds (they dominate its memory)."""
        arrays = (self._src_ids, self._watermark, self._framed, *self._pending)
        grows = (*self._ring.values(), *self._recent.values(), *self._pushed.values(), self._evicted_last)
        return (self._open.nbytes + sum(a.nbytes for a in arrays) + sum(g.nbytes for g in grows)
                + sum(v.nbytes for v in self._all_series()))

    @property
    def pending_events(self) -> int:
        """Events queued by :meth:`add`, not yet merged."""
        return sum(len(e) for e in self._pending)

    @property
    def open_count(self) -> int:
        """Frames open now (neither finalised nor evicted)."""
        return self._open.n

    def open_keys(self) -> np.ndarray:
        """The keys (``source << KEY_SHIFT | frame``) of the open frames, in no set order."""
        return self._open.keys.copy()

    @property
    def open_cap(self) -> int:
        """Open frames this run may hold now."""
        return self._open_cap

    def admit_sources(self, sources: np.ndarray, limit: int) -> int:
        """Note the source ids of a batch unless the run would then name more than ``limit``
        distinct ones; returns how many it would name (nothing is noted when over)."""
        new = self._new_sources(sources)
        total = len(self._src_ids) + len(new)
        if total <= limit:
            self._note_sources(new)
        return total

    # --- ingest -------------------------------------------------------------------------------

    def add(self, events: np.ndarray, admitted: bool = False) -> None:
        """Queue a batch of validated events (stage and point in range, see protocol.wire);
        ``admitted``: its source ids were noted already (:meth:`admit_sources`).

        Merging costs a few dozen numpy calls whatever the batch size, so batches wait here
        until the next :meth:`maintain` (the relay's tick) or read, and merge as one.
        """
        if len(events):
            if not admitted:
                self._note_sources(self._new_sources(events["source"]))
            self._pending.append(events)
            self.events += len(events)
            self._heard_ns = time.monotonic_ns()

    def present_ns(self, bound_ns: int | None = None) -> int:
        """The present on the node's clock, as far as the relay can tell: the node's newest event
        plus the relay's time since it last heard from the node (a silent node's clock goes on
        without events), no later than ``bound_ns`` (the relay's clock moved to the node's, where
        its correction is known) and never before the newest event."""
        self._merge_pending()
        silent = 0 if self._heard_ns is None else time.monotonic_ns() - self._heard_ns
        present = self.newest + silent
        if bound_ns is not None:
            present = min(present, bound_ns)
        return max(self.newest, present)

    def _merge_pending(self) -> None:
        while self._pending:
            take, n = [], 0
            while self._pending and (not take or n + len(self._pending[0]) <= MERGE_EVENTS):
                take.append(self._pending.pop(0))
                n += len(take[-1])
            self._merge(np.concatenate(take) if len(take) > 1 else take[0])

    def _merge(self, events: np.ndarray) -> None:
        origins = None
        if self._origins_counter is not None:
            origins = self._origins_counter.count(np.ascontiguousarray(events))
        self.accounting.add(events, origins)
        self._source_window.add(events, origins)
        if self._open.compiled and self._open.n + len(events) <= self._open_cap:
            self._merge_compiled(events)
            return
        events = frame_events(events)
        if len(events) == 0:
            return
        # Views of the batch's fields (frame and ts are int64 already; the small ints widen in arithmetic).
        src = events["source"].astype(np.int64)
        frame, ts, stage, point, code = (events[f] for f in ("frame", "ts", "stage", "point", "code"))
        key = (src << KEY_SHIFT) | frame
        self.newest = max(self.newest, int(ts.max()))
        self._has_exit |= np.bincount(stage[point == EXIT], minlength=self._s)[:self._s] > 0
        if not self._framed.all():
            self._framed[self._src_index(src)] = True

        pos, placed = self._place(key, frame, src, ts)
        if not placed.all():
            pos, ts, stage, point, code = pos[placed], ts[placed], stage[placed], point[placed], code[placed]
        if len(pos) == 0:
            return
        slot = (pos * self._s + stage) * FRAME_CELLS
        flat = slot + point
        # The earliest time of each cell: a scatter-min, missing cells (-1) counted as never.
        cells = self._open.flat_cells
        cells[flat[cells[flat] == MISSING]] = NEVER
        np.minimum.at(cells, flat, ts)
        ready = point == READY
        cells[slot[ready] + GROUP] = code[ready]
        np.maximum.at(self._open.last, pos, ts)
        self._dirty = True

    def _merge_compiled(self, events: np.ndarray) -> None:
        """:meth:`_merge` in one compiled pass, where the batch cannot take the open table over its cap
        (were each event a new frame): frames open in event order rather than key order, nothing else differs."""
        if not self._framed.all():
            framed = frame_events(events)["source"]
            if len(framed):
                self._framed[self._src_index(framed.astype(np.int64))] = True
        late, self.newest, placed = self._open.merge(events, self._src_ids, self._watermark, self._has_exit, self.newest)
        self.late += late
        if placed:
            self._dirty = True

    def _place(self, key: np.ndarray, frame: np.ndarray, src: np.ndarray,
               ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Open the frames of these events that are new; returns each event's row in the open
        table and which events have one: not those of a frame finalised or evicted before (late,
        counted), nor those of a frame evicted now to make room."""
        pos, found = self._open.locate(key)
        if found.all():
            return pos, found
        late = np.zeros(len(key), bool)
        late[~found] = frame[~found] <= self._watermark[self._src_index(src[~found])]
        self.late += int(late.sum())
        opening = ~found & ~late
        if not opening.any():
            return pos, found
        new, inv = np.unique(key[opening], return_inverse=True)
        before = self._open.n
        dropped = self._make_room(new, ts[opening], inv)
        if self._open.n == before and not dropped.any():  # nothing evicted: the rows are known
            self._open.open(new)
            pos[opening] = before + inv.ravel()
            return pos, found | opening
        self._open.open(new[~dropped])
        return self._open.locate(key)

    def _make_room(self, new: np.ndarray, ts: np.ndarray, inv: np.ndarray) -> np.ndarray:
        """Keep the open table within its cap before ``new`` keys (sorted; ``ts`` their events'
        times, ``inv`` each event's key) open: the stalest open frames are evicted first; if the
        new ones alone are over the cap, only the newest open. Returns which new keys do not."""
        cap = self._open_cap
        dropped = np.zeros(len(new), bool)
        if len(new) > cap:
            newest = np.full(len(new), np.iinfo(np.int64).min)
            np.maximum.at(newest, inv, ts)
            dropped[np.argsort(newest, kind="stable")[:len(new) - cap]] = True
            self._count_evicted(new[dropped] >> KEY_SHIFT, new[dropped] & ((1 << KEY_SHIFT) - 1), newest[dropped])
        excess = self._open.n + len(new) - int(dropped.sum()) - cap
        if excess > 0:
            self._evict_open(np.argsort(self._open.last, kind="stable")[:excess])
        return dropped

    def _evict_open(self, rows: np.ndarray) -> None:
        """Evict these open frames now (the open table is over its cap)."""
        t = self._open
        gone = np.zeros(t.n, bool)
        gone[rows] = True
        keys = t.keys[gone]
        self._count_evicted(keys >> KEY_SHIFT, keys & ((1 << KEY_SHIFT) - 1), t.last[gone])
        t.keep(~gone)

    def _count_evicted(self, source: np.ndarray, frame: np.ndarray, last: np.ndarray) -> None:
        self.evicted += len(source)
        self._evicted_last.extend(last)
        self._raise_watermark(source, frame)

    def _new_sources(self, sources: np.ndarray) -> np.ndarray:
        """The distinct ids of ``sources`` not seen before, sorted (none, the common case, found without a sort:
        in one compiled pass where it loads)."""
        ids = self._src_ids
        if len(ids):
            compiled = self._compiled is not None and sources.dtype == np.int32 and sources.ndim == 1
            if compiled and self._compiled.first_unknown(sources, ids) < 0:
                return ids[:0]
            known = ids[np.minimum(np.searchsorted(ids, sources), len(ids) - 1)] == sources
            if known.all():
                return ids[:0]
            sources = sources[~known]
        return np.unique(sources)

    def _note_sources(self, new: np.ndarray) -> None:
        """Add source ids not seen before (``new``, unique)."""
        if not len(new):
            return
        ids = np.concatenate([self._src_ids, new.astype(np.int64)])
        order = np.argsort(ids, kind="stable")
        self._src_ids = ids[order]
        self._watermark = np.concatenate([self._watermark, np.full(len(new), -1, np.int64)])[order]
        self._framed = np.concatenate([self._framed, np.zeros(len(new), bool)])[order]

    def _src_index(self, source: np.ndarray) -> np.ndarray:
        """Where each of these (noted) source ids sits in the per-source arrays."""
        return np.searchsorted(self._src_ids, source)

    # --- periodic: completion, finalisation, eviction -------------------------------------------

    def maintain(self) -> int:
        """Show complete frames, finalise settled ones, evict stale ones; returns frames shown.
        (:func:`maintain_all` does it for many runs, judging their frames together.)"""
        tick = self._start_tick()
        if tick is None:
            return 0
        if len(tick.rows):
            if self._compiled is not None:
                self._judge_rows(tick)
            else:
                _judge_together([tick])
        return self._end_tick(tick)

    def _start_tick(self) -> _Tick | None:
        """Merge what came; the open frames to judge now, or None when nothing changed. A frame
        shown is complete at the end it had then: only the others are judged each tick (most open
        frames are shown ones waiting to settle), unless the run's exit points changed since
        (which may change any frame's chain)."""
        self._merge_pending()
        t = self._open
        if not self._dirty or t.n == 0:
            return None
        self._dirty = False
        if self._judged_exits is None or not np.array_equal(self._judged_exits, self._has_exit):
            self._judged_exits = self._has_exit.copy()
            rows = np.arange(t.n)
        else:
            rows = np.flatnonzero(~t.shown)
        return _Tick(self, rows)

    def _judge_rows(self, tick: _Tick) -> None:
        """:func:`_judge_together` of one run's tick in one compiled pass over its open table's rows."""
        if self._links is None:
            self._links = compiled_core.links_of(self.header.links, self._s)
        tick.complete, tick.end, tick.ints, tick.floats = self._open.judge(tick.rows, self._has_exit, self._links)

    def _judge_key(self) -> tuple:
        """Runs with the same key are judged by the delay model alike (their frames may be judged together)."""
        return tuple(self.stages), tuple(tuple(link) for link in self.header.links), self._has_exit.tobytes()

    def _end_tick(self, tick: _Tick) -> int:
        t, rows = self._open, tick.rows
        new = tick.complete & ~t.shown[rows] if len(rows) else np.zeros(0, bool)
        shown = rows[new]  # the frames shown now are among those judged now, in row order
        k = len(shown)
        if k:
            t.shown[shown] = True
            t.end[shown] = tick.end[new]
            r = self._recent
            n = np.arange(self.visible + 1, self.visible + k + 1)
            ints = tick.ints[:, new]  # rows 1 and 2: source and frame
            ints[0] = n
            r["n"].extend(n)
            r["source"].extend(ints[1])
            r["frame"].extend(ints[2])
            r["cells"].extend(t.cells[shown])
            self._pushed["ints"].extend(ints.T)
            self._pushed["floats"].extend(tick.floats[:, new].T)
            self.visible += k

        # Finalising costs as much as showing; settled frames can wait a little longer.
        if self.newest < self._next_finalise and t.n <= self._open_cap:
            return k
        self._next_finalise = self.newest + FINALISE_PERIOD_NS
        complete, end = t.shown.copy(), t.end.copy()
        if len(rows):  # a shown frame judged again (the run's exit points changed) may be incomplete now
            complete[rows], end[rows] = tick.complete, tick.end
        done = complete & (end <= self.newest - self._settle_ns)
        stale = ~complete & (t.last < self.newest - int(self.config.evict_s * 1e9))
        excess = t.n - int(done.sum()) - int(stale.sum()) - self._open_cap
        if excess > 0:
            candidates = np.flatnonzero(~done & ~stale)
            stale[candidates[np.argsort(t.last[candidates], kind="stable")[:excess]]] = True
        open_ = tick.open_
        if done.any():
            self._finalise(_Frames(open_.source[done], open_.frame[done], open_.cells[done]))
        if stale.any():
            self._count_evicted(open_.source[stale], open_.frame[stale], t.last[stale])
        gone = done | stale
        if gone.any():
            t.keep(~gone)
        return k

    def finish(self) -> None:
        """The node ended its run: no straggler can come, so its complete frames are finalised now
        rather than after ``settle_s`` of a node time that no longer moves (the exporters would
        never see a run's last seconds). Incomplete frames stay open, counted as they were."""
        self._settle_ns = 0
        self._next_finalise = 0
        self._dirty = True
        self.maintain()

    def _open_frames(self) -> _Frames:
        keys = self._open.keys
        return _Frames((keys >> KEY_SHIFT).astype(np.int32), keys & ((1 << KEY_SHIFT) - 1), self._open.cells)

    def _table(self, frames: _Frames) -> FrameTable:
        table = frame_table_from_cells(self.stages, frames.source, frames.frame, frames.cells)
        table.links = self.header.links
        return table

    def _delays(self, frames: _Frames) -> FrameDelays:
        """The delay model's figures of ``frames``, judged by the exit points of the whole run."""
        return frame_delays(self._table(frames), self._has_exit, compiled=self._compiled is not None)

    def _finalise(self, frames: _Frames) -> None:
        fd = self._delays(frames)
        kept = frame_values(fd)
        values = series_of(kept, self.stages, self._has_exit)
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
        if self.on_finalise is not None:
            self.on_finalise(fd, values)
        # The window keeps the complete ones (a frame shown, then judged incomplete when the run's
        # exit points changed, is finalised all the same, and counted nowhere).
        ring = self._ring
        ring["source"].extend(frames.source[c])
        ring["end"].extend(kept.end)
        for k in STAGE_COLUMNS:
            ring[f"stage_{k}"].extend(kept.per_stage[k])
        for k, v in (("prev", kept.prev), ("first", kept.first), ("frame_delay", kept.frame), ("glass", kept.glass),
                     ("origin", kept.origin)):
            ring[k].extend(v)
        ring["lacks_exit"].extend((fd.chains.passed & (fd.chains.t_out == MISSING))[c])
        self._raise_watermark(frames.source, frames.frame)

    def _kept_values(self, rows: np.ndarray) -> FrameValues:
        ring = self._ring
        return FrameValues({k: ring[f"stage_{k}"].view[rows] for k in STAGE_COLUMNS}, prev=ring["prev"].view[rows],
                           first=ring["first"].view[rows], frame=ring["frame_delay"].view[rows],
                           glass=ring["glass"].view[rows], origin=ring["origin"].view[rows], end=ring["end"].view[rows])

    def _note_span(self, first_origin: int, last_end: int) -> None:
        self._first_origin = first_origin if self._first_origin is None else min(self._first_origin, first_origin)
        self._last_end = last_end if self._last_end is None else max(self._last_end, last_end)

    def _all_series(self) -> list[RunValues]:
        return [self._frame_values, self._glass_values, *(v for d in self._values.values() for v in d.values())]

    def _series(self, kind: str, name: str) -> RunValues:
        series = self._values[kind]
        if name not in series:
            series[name] = RunValues(self._exact_limit)
        return series[name]

    def _raise_watermark(self, source: np.ndarray, frame: np.ndarray) -> None:
        np.maximum.at(self._watermark, self._src_index(source.astype(np.int64)), frame.astype(np.int64))

    # --- statistics -----------------------------------------------------------------------------

    def run_stats(self, dropped: int = 0) -> dict:
        """``model.delays.node_stats`` of every event received for this run."""
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
            "span_s": values.span_ns / 1e9,
            "dropped": int(dropped),
            "frames": {"complete": self.finalised + n_open_complete,
                       "incomplete": self.evicted + len(fd) - n_open_complete},
            "percentile_error": 0.0 if all(v.exact for v in self._all_series()) else RELATIVE_ERROR,
        }

    def _session_summary(self, series: list[tuple[str, str, np.ndarray]]) -> list[dict]:
        """``summarize`` of the finalised values of each series and its ``values_ms`` (open frames)."""
        return RunValues.summaries([(self._held(kind, name), values_ms) for kind, name, values_ms in series])

    def _held(self, kind: str, name: str) -> RunValues:
        if kind == "frame":
            return self._frame_values
        if kind == "glass":
            return self._glass_values
        return self._series(kind, name)

    def window_stats(self, end_ns: int | None = None) -> dict:
        """The same statistics over frames whose chain ended in the ``window_s`` before ``end_ns``
        (node time; by default :meth:`present_ns`), which the answer gives as ``end_ns``."""
        self.maintain()
        end = self.present_ns() if end_ns is None else end_ns
        cutoff = end - int(self.config.window_s * 1e9)
        ring = self._ring
        sel = np.flatnonzero(ring["end"].view >= cutoff)
        # Kept frames are judged by the run's exit points as they are now, as the open ones are.
        sel = sel[~(ring["lacks_exit"].view[sel] & self._has_exit).any(axis=1)]
        open_ = self._open_frames()
        ofd = self._delays(open_)
        och = ofd.chains
        osel = och.complete & (och.end >= cutoff)
        values = FrameValues.concat([self._kept_values(sel), frame_values(ofd).take(osel[och.complete])])
        source = np.concatenate([ring["source"].view[sel], open_.source[osel]])
        incomplete = int((self._evicted_last.view >= cutoff).sum()) + int((~och.complete & (self._open.last >= cutoff)).sum())
        fps = OriginSpans().fps(self._all_sources(), values.origin, source)
        return {
            "window_s": self.config.window_s,
            "end_ns": end,
            **delay_summary(series_of(values, self.stages, self._has_exit, self.accounting.threads())),
            "fps": fps,
            # Counted over the same window as the frames, as the statistics panel shows them side by side.
            "sources": self._source_window.sources(self.accounting.sources(fps), cutoff),
            "frames": {"complete": len(values), "incomplete": incomplete},
        }

    def _all_sources(self) -> list[int]:
        return sorted(set(int(k) for k in self.header.sources) | set(self._src_ids[self._framed].tolist()))

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

    def recent_columns(self, since: int = 0, limit: int = 200) -> tuple[np.ndarray, np.ndarray]:
        """The last ``limit`` complete frames with cursor > ``since``, as they were judged when shown:
        :func:`dcuscope.relay.live.framepack.node_columns` (ints, floats), each (rows, frames). What the
        pushes send, with no pairing or delay figure derived again."""
        self.maintain()
        ints, floats = self._pushed["ints"].view, self._pushed["floats"].view
        start = max(int(np.searchsorted(ints[:, 0], since, side="right")), len(ints) - limit)
        return ints[start:].T, floats[start:].T

    @property
    def has_exit(self) -> np.ndarray:
        """Per stage, whether the run has seen an exit point there."""
        return self._has_exit.copy()
