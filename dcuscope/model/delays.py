"""The delay model: from a frame table to every delay figure dcuscope reports (vectorised numpy, and
in the compiled core where it loads: :func:`frame_delays` per frame, :func:`summaries` per series).

``dcuscope stats``, both exports, the relay's live engine, its stored-session API and
``/api/stats`` all derive their figures here, so that they agree exactly. Definitions
(DESIGN.md, after the paper):

- stage delay at stage X = exit - enter of one frame at X (stages without an exit point, such
  as the sink, have none);
- gap A->B = enter at B - exit at A, for consecutive stages A, B (in header order) that the
  frame passed through; at the origin stage the origin timestamp stands for the exit;
- frame delay = end of the frame's chain - origin, the paper's S; the chain ends at the exit of
  the last stage, or at its enter when that stage has no exit point (the sink). So, for every
  complete frame, frame delay = sum of its stage delays + sum of its gaps, exactly;
- service at X = exit - start, wait at X = start - enter, where start = the frame's ``ready``
  at X (when X's pushing thread was free and the last frame of the output buffer had entered,
  see protocol.events) clamped into [enter, exit]: stage delay = service + wait, exactly. Wait is
  time queued, waiting for a batch to form, or blocked while the thread pushed downstream;
  service is the work on the buffer that carried the frame out (a batch's work, for each of
  its frames);
- busy time of X = the sum, over the output buffers of X, of their service (a batch counted
  once); utilization = busy time / the wall span of the frames (first origin to last end);
  a streaming thread's utilization = the sum over the stages whose output it pushes;
- the bottleneck is the stage that limits throughput: the busiest stage on a saturated thread
  (utilization >= :data:`SATURATED`); when no thread is saturated, the busiest stage, marked
  not saturated, with where frames spend most time (largest share of frame delay);
- glass-to-glass delay = end - capture, for frames whose source gave a capture time.

A frame is *complete* when its chain is unbroken: it has an origin, an enter at every stage it
passed after the origin, an exit (or origin) at every stage before the last, and it reached
the last stage. Only complete frames enter the statistics; the others are counted, never
turned into zero or partial delays. Loops run over stages and sources, never over events.

Three steps, each one function: :func:`frame_delays` (per frame: its chain, its per-stage
columns, its end-to-end delay), :func:`series` (the values the statistics take, of complete
frames: :func:`frame_values` picks them per frame, :func:`series_of` gathers them per stage) and
:func:`delay_summary` (count, mean, percentiles, share, bottleneck: every series summarized in one
call of :func:`summaries`). A new
per-stage figure is one more entry of ``FrameDelays.per_stage`` (:data:`STAGE_COLUMNS`): the
CSV, the per-frame JSON and the summaries list it from there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import numpy as np

from dcuscope.model import compiled as compiled_core
from dcuscope.model.facts import Accounting
from dcuscope.model.frametable import MISSING, FrameTable, frame_table
from dcuscope.protocol.events import TraceHeader

PERCENTILES = (50, 95, 99)
NS_PER_MS = 1e6
STAGE_COLUMNS = ("delay", "gap", "service", "wait")
"""Per-frame, per-stage figures of :class:`FrameDelays` (``per_stage``): ``delay`` = exit -
enter; ``gap`` = enter - exit (or origin) of the previous stage the frame passed; ``service``
and ``wait``, delay = service + wait."""
SATURATED = 0.9
"""Utilization of a streaming thread from which it counts as saturated: it cannot take more."""


@dataclass
class Chains:
    """Each frame's path through the stages, as :func:`chains` derives it from a FrameTable."""

    t_in: np.ndarray
    """(n, n_stages) enter ts, MISSING."""
    t_out: np.ndarray
    """(n, n_stages) exit ts; at the frame's origin stage its origin ts. MISSING."""
    passed: np.ndarray
    """(n, n_stages) bool: the frame has an event at that stage."""
    prev: np.ndarray
    """(n, n_stages) index of the previous stage the frame passed, -1 for none."""
    complete: np.ndarray
    """(n,) bool, see the module docstring."""
    end: np.ndarray
    """(n,) ts where the chain ends (last exit, or the last stage's enter), MISSING."""
    has_exit: np.ndarray
    """(n_stages,) bool: the stage has an exit point (some frame has an exit there)."""


def chains(table: FrameTable, has_exit: np.ndarray | None = None) -> Chains:
    """Derive each frame's chain of stages, its completeness and its end timestamp.

    ``has_exit`` is the one fact that spans frames (whether a stage has an exit point at all):
    taken from the table unless given, so that the relay can judge a few frames by the
    exits its whole run has seen.
    """
    n, n_stages = table.enter.shape
    rows = np.arange(n)
    has_origin = table.origin_stage >= 0
    t_in = table.enter
    t_out = table.exit.copy()
    t_out[rows[has_origin], table.origin_stage[has_origin]] = table.origin[has_origin]
    passed = (t_in != MISSING) | (t_out != MISSING)

    if has_exit is None:
        has_exit = (table.exit != MISSING).any(axis=0)
    if table.links:
        prev, needs_out, reached_end, end = _graph_chains(table, passed, t_in, t_out, has_exit)
    else:
        stage_idx = np.arange(n_stages)
        last_upto = np.maximum.accumulate(np.where(passed, stage_idx, -1), axis=1)
        prev = np.full((n, n_stages), -1, np.int64)
        prev[:, 1:] = last_upto[:, :-1]
        last = n_stages - 1
        needs_out = passed & ((stage_idx[None, :] < last) | has_exit[None, :])
        reached_end = t_in[:, last] != MISSING
        end = np.where(t_out[:, last] != MISSING, t_out[:, last], t_in[:, last])
    is_origin = np.arange(n_stages)[None, :] == table.origin_stage[:, None]
    broken = (passed & ~is_origin & (t_in == MISSING)).any(axis=1) | (needs_out & (t_out == MISSING)).any(axis=1)
    if table.links:  # the graph says what is upstream (stage order need not: stages are numbered as found)
        starts_at_origin = prev[rows, np.maximum(table.origin_stage, 0)] == -1
    else:
        starts_at_origin = np.where(passed.any(axis=1), passed.argmax(axis=1), -1) == table.origin_stage
    complete = has_origin & starts_at_origin & reached_end & ~broken
    return Chains(t_in=t_in, t_out=t_out, passed=passed, prev=prev, complete=complete, end=end,
                  has_exit=np.asarray(has_exit, bool))


def _graph_chains(table: FrameTable, passed: np.ndarray, t_in: np.ndarray, t_out: np.ndarray, has_exit: np.ndarray):
    """:func:`chains` where the trace gives the graph (branches through a tee, several sinks):
    a stage's previous stage is the upstream stage the frame passed; a stage that feeds others
    needs an exit; the frame must reach an end (a stage feeding none) from every stage it
    passed; it ends where its last branch ends."""
    n, n_stages = passed.shape
    upstream: list[list[int]] = [[] for _ in range(n_stages)]
    feeds = np.zeros(n_stages, bool)
    for a, b in table.links:
        if 0 <= a < n_stages and 0 <= b < n_stages and a != b:
            upstream[b].append(a)
            feeds[a] = True
    prev = np.full((n, n_stages), -1, np.int64)
    went_on = ~passed | ~feeds[None, :]  # a passed stage that feeds others: did the frame pass one?
    for b in range(n_stages):
        for a in upstream[b]:
            prev[:, b] = np.maximum(prev[:, b], np.where(passed[:, a], a, -1))
            went_on[:, a] |= passed[:, b]
    needs_out = passed & (feeds | has_exit)[None, :]
    ends = ~feeds
    end_ts = np.where(t_out != MISSING, t_out, t_in)
    end = np.where(passed & ends[None, :], end_ts, MISSING).max(axis=1)
    reached_end = (passed & ends[None, :]).any(axis=1) & went_on.all(axis=1)
    return prev, needs_out, reached_end, end


@dataclass
class FrameDelays:
    """Every figure of each frame of a table (rows as the table's), derived once.

    Delays are differences of int64 ns held as float64 ns, NaN where undefined: exact below
    2**53 ns (104 days), and one array type whether a value exists or not.
    """

    table: FrameTable
    chains: Chains
    per_stage: dict[str, np.ndarray]
    """Name (:data:`STAGE_COLUMNS`) -> (n, n_stages) float64 ns, NaN where the frame lacks a
    tracepoint it needs. Defined for incomplete frames too (the exports show them)."""
    delay: np.ndarray
    """(n,) float64 ns: end - origin of each complete frame, NaN for the others."""
    glass: np.ndarray
    """(n,) float64 ns: end - capture of each complete frame with a capture time, else NaN."""

    def __len__(self) -> int:
        return len(self.table)


def frame_delays(table: FrameTable, has_exit: np.ndarray | None = None, *, compiled: bool = True) -> FrameDelays:
    """The chains, per-stage columns and end-to-end delays of every frame of ``table``: in one
    compiled pass (:mod:`dcuscope.model.compiled`) where the library loads and ``compiled``, else
    with numpy (the reference: :func:`frame_delays_numpy`). The two give equal figures."""
    core = compiled_core.load() if compiled else None
    if core is None or len(table) == 0 or table.enter.shape[1] == 0:
        return frame_delays_numpy(table, has_exit)
    return _frame_delays_compiled(core, table, has_exit)


def frame_delays_numpy(table: FrameTable, has_exit: np.ndarray | None = None) -> FrameDelays:
    """:func:`frame_delays` with numpy, a column at a time (the reference of the compiled pass)."""
    ch = chains(table, has_exit)
    n = len(table)
    both = (table.exit != MISSING) & (table.enter != MISSING)
    delay = np.where(both, (table.exit - table.enter).astype(np.float64), np.nan)
    before = ch.t_out[np.arange(n)[:, None], np.maximum(ch.prev, 0)]
    gap_ok = (ch.prev >= 0) & (before != MISSING) & (ch.t_in != MISSING)
    gap = np.where(gap_ok, (ch.t_in - before).astype(np.float64), np.nan)
    end_to_end = np.where(ch.complete, (ch.end - table.origin).astype(np.float64), np.nan)
    glass = np.where(ch.complete & (table.capture != MISSING), (ch.end - table.capture).astype(np.float64), np.nan)
    timed = both & (table.ready != MISSING)
    start = np.minimum(np.maximum(table.ready, table.enter), table.exit)
    service = np.where(timed, (table.exit - start).astype(np.float64), np.nan)
    wait = np.where(timed, (start - table.enter).astype(np.float64), np.nan)
    return FrameDelays(table=table, chains=ch, delay=end_to_end, glass=glass,
                       per_stage={"delay": delay, "gap": gap, "service": service, "wait": wait})


def _frame_delays_compiled(core: compiled_core.CompiledCore, table: FrameTable, has_exit: np.ndarray | None) -> FrameDelays:
    n, s = table.enter.shape
    if has_exit is None:
        has_exit = (table.exit != MISSING).any(axis=0)
    has_exit = np.ascontiguousarray(has_exit, bool)
    ins = [np.ascontiguousarray(a, np.int64) for a in (table.origin, table.origin_stage, table.capture, table.enter,
                                                         table.exit, table.ready)]
    links = compiled_core.links_of(table.links, s)
    t_out, prev, end = np.empty((n, s), np.int64), np.empty((n, s), np.int64), np.empty(n, np.int64)
    passed, complete = np.empty((n, s), bool), np.empty(n, bool)
    per_stage = {k: np.empty((n, s)) for k in STAGE_COLUMNS}
    delay, glass, scratch = np.empty(n), np.empty(n), np.empty(2 * s, np.uint8)
    at = [a.ctypes.data for a in (*ins, has_exit, links)]
    outs = [a.ctypes.data for a in (t_out, prev, end, passed, complete, *(per_stage[k] for k in STAGE_COLUMNS), delay,
                                    glass, scratch)]
    core.judge(compiled_core.Judge(n, s, *at[:8], len(links), *outs))
    ch = Chains(t_in=table.enter, t_out=t_out, passed=passed, prev=prev, complete=complete, end=end, has_exit=has_exit)
    return FrameDelays(table=table, chains=ch, delay=delay, glass=glass, per_stage=per_stage)


@dataclass
class Series:
    """The values the statistics summarise (float64 ns), of complete frames, in table order."""

    stages: dict[str, np.ndarray]
    """Stage with an exit point -> its delays, pipeline order (possibly empty)."""
    gaps: dict[str, np.ndarray]
    """"A->B" -> gaps, in pipeline order of B, then of A."""
    frame: np.ndarray
    """End-to-end delays."""
    service: dict[str, np.ndarray] = field(default_factory=dict)
    """Stage -> service times of its frames that have one (pipeline order)."""
    wait: dict[str, np.ndarray] = field(default_factory=dict)
    """Stage -> wait times, the same frames as ``service``."""
    glass: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """Glass-to-glass delays (end - capture) of the frames with a capture time."""
    busy: dict[str, int] = field(default_factory=dict)
    """Stage -> busy time, ns: service summed over its output buffers (a batch once: over the
    first frame of each, :attr:`FrameTable.group`). Whole ns, so sums are exact in any order."""
    span_ns: int = 0
    """Wall time the frames cover: first origin to last end, ns."""
    threads: dict[str, int] = field(default_factory=dict)
    """Stage -> number of the streaming thread that pushes its output (protocol.events facts)."""


@dataclass
class FrameValues:
    """What :func:`series` takes of each complete frame, and nothing else (rows in table order):
    a set of frames summarised again later (the relay's rolling window, whose frames were judged
    when they were finalised) needs neither their events nor the delay model's pass over them."""

    per_stage: dict[str, np.ndarray]
    """:data:`STAGE_COLUMNS` -> (n, n_stages) float64 ns, NaN where undefined (as :class:`FrameDelays`)."""
    prev: np.ndarray
    """(n, n_stages) the previous stage each frame passed (-1 for none): whose gap it is."""
    first: np.ndarray
    """(n, n_stages) bool: the frame is the first of its output buffer there (its service is busy time)."""
    frame: np.ndarray
    """(n,) float64 ns end-to-end delays."""
    glass: np.ndarray
    """(n,) float64 ns glass-to-glass delays, NaN without a capture time."""
    origin: np.ndarray
    """(n,) int64 origin timestamps."""
    end: np.ndarray
    """(n,) int64 chain ends."""

    FIELDS = ("prev", "first", "frame", "glass", "origin", "end")

    def __len__(self) -> int:
        return len(self.frame)

    def take(self, rows: np.ndarray) -> FrameValues:
        return FrameValues({k: v[rows] for k, v in self.per_stage.items()},
                           **{k: getattr(self, k)[rows] for k in self.FIELDS})

    @staticmethod
    def concat(parts: list[FrameValues]) -> FrameValues:
        return FrameValues({k: np.concatenate([p.per_stage[k] for p in parts]) for k in STAGE_COLUMNS},
                           **{k: np.concatenate([getattr(p, k) for p in parts]) for k in FrameValues.FIELDS})


def frame_values(fd: FrameDelays) -> FrameValues:
    """The :class:`FrameValues` of the complete frames of ``fd`` (views when all are complete)."""
    c = fd.chains.complete
    rows = slice(None) if c.all() else c
    return FrameValues({k: fd.per_stage[k][rows] for k in STAGE_COLUMNS}, prev=fd.chains.prev[rows],
                       first=fd.table.group[rows] > 0, frame=fd.delay[rows], glass=fd.glass[rows],
                       origin=fd.table.origin[rows], end=fd.chains.end[rows])


def series(fd: FrameDelays, threads: dict[str, int] | None = None) -> Series:
    """The stage delays, gaps, service and wait times, frame delays and busy times of the
    complete frames of ``fd``; ``threads`` as :attr:`Series.threads`."""
    return series_of(frame_values(fd), fd.table.stages, fd.chains.has_exit, threads)


def series_of(values: FrameValues, stages: list[str], has_exit: np.ndarray,
              threads: dict[str, int] | None = None) -> Series:
    """:func:`series` of frames given by their :class:`FrameValues`, judged by ``has_exit`` (the
    exit points the frames were judged by: which stages have delays): gathered in one compiled pass
    where the library loads (numpy's cost is its calls', ~0.4 ms for 8 stages), else by
    :func:`series_of_numpy`, its reference."""
    core = compiled_core.load()
    if core is None or not len(stages):
        return series_of_numpy(values, stages, has_exit, threads)
    v = values
    made, busy = core.series([v.per_stage[k] for k in STAGE_COLUMNS], v.glass, v.prev, v.first, has_exit)
    span_ns = int(v.end.max() - v.origin.min()) if len(v) else 0
    s = Series(stages={}, gaps={}, frame=v.frame, span_ns=span_ns, threads=dict(threads or {}))
    for kind, a, b, part in made:
        if kind == "glass":
            s.glass = part
        elif kind == "gaps":
            s.gaps[f"{stages[a]}->{stages[b]}"] = part
        else:
            getattr(s, kind)[stages[b]] = part
            if kind == "service":
                s.busy[stages[b]] = int(busy[b])
    return s


def series_of_numpy(values: FrameValues, stages: list[str], has_exit: np.ndarray,
                    threads: dict[str, int] | None = None) -> Series:
    """:func:`series_of` with numpy (the reference of the compiled core's, c/stats.c)."""
    v = values
    delay, gap, service, wait = (v.per_stage[k] for k in STAGE_COLUMNS)
    span_ns = int(v.end.max() - v.origin.min()) if len(v) else 0
    out = Series(stages={}, gaps={}, frame=v.frame, glass=v.glass[~np.isnan(v.glass)], span_ns=span_ns,
                 threads=dict(threads or {}))
    for s, name in enumerate(stages):
        if has_exit[s]:
            out.stages[name] = delay[~np.isnan(delay[:, s]), s]
            timed = ~np.isnan(service[:, s])
            if timed.any():
                out.service[name], out.wait[name] = service[timed, s], wait[timed, s]
                out.busy[name] = int(service[timed & v.first[:, s], s].sum())
    for b, name_b in enumerate(stages):
        ok = ~np.isnan(gap[:, b])
        if not ok.any():
            continue
        prev_b, gap_b = v.prev[ok, b], gap[ok, b]
        # The previous stages, in order: counted (a gap's previous stage is a stage, never -1).
        for a in np.flatnonzero(np.bincount(prev_b, minlength=len(stages))):
            same = prev_b == a
            out.gaps[f"{stages[a]}->{name_b}"] = gap_b if same.all() else gap_b[same]
    return out


@dataclass
class Timeline:
    """Busy time of each stage per time bucket, from the service intervals of its output
    buffers (a batch counted once), over the span of :func:`series` (first origin to last
    end of the complete frames): summed over the buckets, busy time is ``Series.busy``."""

    edges: np.ndarray
    """(n + 1,) int64 ns: bucket k is [edges[k], edges[k + 1]); the last one may be shorter."""
    busy: dict[str, np.ndarray]
    """Stage -> (n,) int64 ns of service inside each bucket."""

    def utilization(self, stage: str) -> np.ndarray:
        """Busy fraction of ``stage`` per bucket (above 1 only if its buffers' work overlaps)."""
        return self.busy[stage] / np.diff(self.edges)


def busy_timeline(fd: FrameDelays, bucket_ns: int) -> Timeline:
    """Busy time per ``bucket_ns`` bucket of every stage with service times, of the complete
    frames (those the utilization of :func:`delay_summary` counts)."""
    if bucket_ns <= 0:
        raise ValueError(f"bucket_ns must be positive, got {bucket_ns}")
    ch, service = fd.chains, fd.per_stage["service"]
    c = ch.complete
    if not c.any():
        return Timeline(edges=np.zeros(1, np.int64), busy={})
    first, last = int(fd.table.origin[c].min()), int(ch.end[c].max())
    edges = np.append(np.arange(first, last, bucket_ns, dtype=np.int64), np.int64(last))
    busy = {}
    for s, name in enumerate(fd.table.stages):
        timed = c & ~np.isnan(service[:, s])
        if ch.has_exit[s] and timed.any():
            # Each output buffer's work once, on its first frame, as in series().
            first_of_buffer = timed & (fd.table.group[:, s] > 0)
            ends = fd.table.exit[first_of_buffer, s] - first
            starts = ends - service[first_of_buffer, s].astype(np.int64)
            busy[name] = np.diff(_time_inside_before(starts, ends, edges - first))
    return Timeline(edges=edges, busy=busy)


def _time_inside_before(starts: np.ndarray, ends: np.ndarray, t: np.ndarray) -> np.ndarray:
    """For each ``t``: the total length of the intervals [start, end) before it, int64 ns.

    Sum over intervals of clip(t - start, 0, end - start) = sum over starts before t of
    (t - start) - the same over ends: prefix sums, no loop over intervals. Times relative to
    the span's start keep the sums far inside int64.
    """
    a, b = np.sort(starts), np.sort(ends)
    ca = np.concatenate(([0], np.cumsum(a)))
    cb = np.concatenate(([0], np.cumsum(b)))
    na, nb = np.searchsorted(a, t, side="right"), np.searchsorted(b, t, side="right")
    return (na * t - ca[na]) - (nb * t - cb[nb])


def fill_levels(fd: FrameDelays, stage: int) -> tuple[np.ndarray, np.ndarray]:
    """Frames inside stage ``stage`` over time: (times, levels), the level from each time on.

    +1 at a frame's enter, -1 at its exit, of every frame with both there (one lost on the way
    has no known leaving time, so it is left out, not counted inside for ever); at one
    instant exits count before enters, and each time appears once, with the level after all
    its changes. Empty for a stage without exits (the sink).
    """
    enter, exit_ = fd.table.enter[:, stage], fd.table.exit[:, stage]
    both = (enter != MISSING) & (exit_ != MISSING)
    times = np.concatenate((exit_[both], enter[both]))
    steps = np.concatenate((np.full(both.sum(), -1), np.full(both.sum(), 1)))
    order = np.lexsort((steps, times))
    times, levels = times[order], np.cumsum(steps[order])
    last_of_time = np.append(times[1:] != times[:-1], True)[:len(times)]
    return times[last_of_time], levels[last_of_time]


def summarize(values_ms: np.ndarray | Iterable[float]) -> dict:
    """``{count, mean_ms, p50_ms, p95_ms, p99_ms, max_ms}``; values are None when count is 0.

    The mean is that of the values in whole nanoseconds (what timestamps hold), summed exactly
    (float64 adds integers exactly up to 2**53 ns, 104 days in all): so it does not depend on
    the order the values came in, and the relay, which adds finalised and open frames, gets
    the figures of a trace file to the last bit. Sorting would cost 3x the rest. Computed by the
    compiled core where it loads (:func:`summaries`), else by :func:`summarize_numpy`, its reference.
    """
    return summaries([values_ms])[0]


def summaries(series: Sequence[np.ndarray | Iterable[float]]) -> list[dict]:
    """:func:`summarize` of each of ``series``: in one call of the compiled core where it loads (numpy's
    cost is its calls', ~60 µs a series, and the relay's statistics of a DCU are a few dozen series)."""
    arrays = [np.asarray(v, dtype=np.float64).ravel() for v in series]
    core = compiled_core.load()
    if core is None:
        return [summarize_numpy(a) for a in arrays]
    offsets = np.zeros(len(arrays) + 1, np.int64)
    np.cumsum([len(a) for a in arrays], out=offsets[1:])
    values = np.concatenate(arrays) if arrays else np.zeros(0)  # a copy: the core reorders it
    return [summary_of(*row) for row in core.summarize(values, offsets).tolist()]


def summary_of(count: float, mean: float, p50: float, p95: float, p99: float, top: float) -> dict:
    """:func:`summarize`'s dict of its figures (a row of the compiled core's)."""
    if not count:
        return {"count": 0, "mean_ms": None, "p50_ms": None, "p95_ms": None, "p99_ms": None, "max_ms": None}
    return {"count": int(count), "mean_ms": mean, "p50_ms": p50, "p95_ms": p95, "p99_ms": p99, "max_ms": top}


def summarize_numpy(values_ms: np.ndarray | Iterable[float]) -> dict:
    """:func:`summarize` with numpy (the reference of the compiled core's, c/stats.c)."""
    values = np.asarray(values_ms, dtype=np.float64).ravel()
    if values.size == 0:
        return summary_of(0, 0, 0, 0, 0, 0)
    if np.isnan(values).any():
        p50, p95, p99 = np.percentile(values, PERCENTILES, method="linear")  # NaN, as numpy says
    else:  # numpy's figures from one partition at the six ranks they read (np.percentile does more around it)
        n = values.size
        ranks = np.floor((n - 1) * (np.asarray(PERCENTILES, np.float64) / 100)).astype(np.int64)
        part = np.partition(values, np.unique(np.concatenate([ranks, np.minimum(ranks + 1, n - 1)])))
        p50, p95, p99 = linear_percentiles(n, lambda at: part[at])
    total_ns = float(np.rint(values * NS_PER_MS).sum())
    return summary_of(values.size, total_ns / values.size / NS_PER_MS, float(p50), float(p95), float(p99),
                    float(values.max()))


def linear_percentiles(n: int, at: Callable[[np.ndarray], np.ndarray]) -> list[float]:
    """PERCENTILES of ``n`` sorted values, ``at(ranks)`` giving the values at those ranks, as
    ``np.percentile(method="linear")`` computes them (its virtual index, and its lerp from the
    nearer end) without selecting them again."""
    virtual = (n - 1) * (np.asarray(PERCENTILES, np.float64) / 100)
    below = np.floor(virtual)
    gamma = virtual - below
    lo = below.astype(np.int64)
    a, b = at(lo), at(np.minimum(lo + 1, n - 1))
    diff = b - a
    return np.where(gamma >= 0.5, b - diff * (1 - gamma), a + diff * gamma).tolist()


Summarizer = Callable[[list[tuple[str, str, np.ndarray]]], list[dict]]
"""[(kind "stages" | "gaps" | "frame" | "service" | "wait" | "glass", name, values in ms), ...] -> the
``summarize`` dict of each; the relay's live engine passes one that adds the values of frames
already finalised."""


def _plain(series: list[tuple[str, str, np.ndarray]]) -> list[dict]:
    return summaries([values_ms for _, _, values_ms in series])


def delay_summary(s: Series, summarize_ms: Summarizer = _plain) -> dict:
    """``{"stages", "gaps", "frame", "glass", "bottleneck"}``: a ``summarize`` dict per series;
    each stage's with its ``share`` of the mean frame delay, its ``service`` and ``wait``
    summaries, ``utilization`` (busy fraction of the span, None without service times) and
    ``occupancy`` (mean frames inside it: its delays summed over the span). Every series is
    summarized in one call of ``summarize_ms``."""
    none = np.zeros(0)
    asked = [("frame", "frame", s.frame), ("glass", "glass", s.glass)]
    for name, values in s.stages.items():
        asked += [("stages", name, values), ("service", name, s.service.get(name, none)),
                  ("wait", name, s.wait.get(name, none))]
    asked += [("gaps", name, values) for name, values in s.gaps.items()]
    figures = iter(summarize_ms([(kind, name, values / NS_PER_MS) for kind, name, values in asked]))
    frame, glass = next(figures), next(figures)
    stages = {}
    for name in s.stages:
        st = next(figures)
        st["share"] = share(st, frame)
        st["service"], st["wait"] = next(figures), next(figures)
        st["utilization"] = s.busy[name] / s.span_ns if name in s.busy and s.span_ns > 0 else None
        st["occupancy"] = st["count"] * st["mean_ms"] * NS_PER_MS / s.span_ns if st["count"] and s.span_ns > 0 else None
        stages[name] = st
    gaps = {name: next(figures) for name in s.gaps}
    return {"stages": stages, "gaps": gaps, "frame": frame, "glass": glass,
            "bottleneck": bottleneck(stages, s.threads)}


def share(stage: dict, frame: dict) -> float | None:
    """A stage's mean delay over the mean frame delay; None without both."""
    if stage["mean_ms"] is None or not frame["mean_ms"]:
        return None
    return stage["mean_ms"] / frame["mean_ms"]


def bottleneck(stages: dict[str, dict], threads: dict[str, int] | None = None) -> dict | None:
    """The stage that limits throughput, and why: ``{stage, utilization, thread_utilization,
    saturated, share, reason}`` (see the module docstring); None without any stage figure.

    Without service times (format-1 traces, Python probes) it is the stage with the largest
    share of frame delay, which says where frames spend time, not what limits them; the reason
    says so."""
    util = {k: v["utilization"] for k, v in stages.items() if v.get("utilization") is not None}
    means = {k: v["mean_ms"] for k, v in stages.items() if v["mean_ms"] is not None}
    if not means:
        return None
    most_time = max(means, key=means.get)
    if not util:
        return {"stage": most_time, "utilization": None, "thread_utilization": None, "saturated": None,
                "share": stages[most_time]["share"],
                "reason": f"no service times (format-1 trace or Python probes): {most_time} has the largest "
                          f"share of frame delay ({_pct(stages[most_time]['share'])}), which need not be what limits"}
    threads = threads or {}
    on_thread = {k: sum(u for s, u in util.items() if threads.get(s) == threads[k]) if k in threads else u
                 for k, u in util.items()}
    saturated = [k for k in util if on_thread[k] >= SATURATED]
    name = max(saturated or util, key=util.get)
    out = {"stage": name, "utilization": util[name], "thread_utilization": on_thread[name],
           "saturated": bool(saturated), "share": stages[name]["share"]}
    if saturated:
        shared = f"; its streaming thread is busy {_pct(on_thread[name])}" if on_thread[name] > util[name] else ""
        out["reason"] = f"{name} is busy {_pct(util[name])} of the time{shared}: it limits throughput"
    else:
        out["reason"] = (f"no stage is saturated (busiest: {name}, {_pct(util[name])}); frames spend most time in "
                         f"{most_time} ({_pct(stages[most_time]['share'])} of frame delay)")
    return out


def _pct(fraction: float | None) -> str:
    return "?" if fraction is None else f"{fraction * 100:.0f} %"


def fps_by_source(fd: FrameDelays, sources: Iterable[int] = ()) -> dict[str, float]:
    """Source id (str) -> complete frames per second over the span of their origin timestamps.

    With n frames over a span T the rate is (n - 1) / T: n frames mark n - 1 intervals, so a
    10 fps camera reads 10.0, not 10 + 10/n. 0.0 when fewer than two frames completed.
    """
    table, complete = fd.table, fd.chains.complete
    ids = sorted(set(int(s) for s in sources) | set(np.unique(table.source).tolist()))
    out = {}
    for sid in ids:
        origin = table.origin[complete & (table.source == sid)]
        span = int(origin.max() - origin.min()) if origin.size >= 2 else 0
        out[str(sid)] = (origin.size - 1) * 1e9 / span if span > 0 else 0.0
    return out


def node_stats(header: TraceHeader, events: np.ndarray, dropped: int = 0) -> dict:
    """Statistics of one node's events; the shape ``dcuscope stats --json`` prints per node."""
    accounting = Accounting(header.stages)
    accounting.add(events)
    return delay_stats(frame_delays(frame_table(header, events)), header.sources, dropped, accounting)


def delay_stats(fd: FrameDelays, sources: Iterable[int] = (), dropped: int = 0,
                accounting: Accounting | None = None) -> dict:
    """``delay_summary`` of ``fd`` + ``fps`` per source, ``dropped`` events, ``frames``
    (complete and incomplete counts), ``sources`` (every frame accounted for, per source)."""
    accounting = accounting or Accounting(fd.table.stages)
    n_complete = int(fd.chains.complete.sum())
    fps = fps_by_source(fd, sources)
    return {
        **delay_summary(series(fd, accounting.threads())),
        "fps": fps,
        "sources": accounting.sources(fps),
        "dropped": int(dropped),
        "frames": {"complete": n_complete, "incomplete": len(fd) - n_complete},
    }
