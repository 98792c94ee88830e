"""Per-frame delays and their statistics, from arrays of probe events (vectorised numpy).

Definitions (DESIGN.md, after the paper):

- stage delay at stage X = exit - enter of one frame at X (stages without an exit point, such
  as the sink, have none);
- gap A->B = enter at B - exit at A, for consecutive stages A, B (in header order) that the
  frame passed through; at the origin stage the origin timestamp stands for the exit;
- frame delay = end of the frame's chain - origin, the paper's S; the chain ends at the exit of
  the last stage, or at its enter when that stage has no exit point (the sink). So, for every
  complete frame, frame delay = sum of its stage delays + sum of its gaps, exactly.

A frame is *complete* when its chain is unbroken: it has an origin, an enter at every stage it
passed after the origin, an exit (or origin) at every stage before the last, and it reached
the last stage. Only complete frames enter the statistics; the others are counted, never
turned into zero or partial delays. Loops run over stages and sources, never over events.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from probes.errors import TraceError
from probes.events import ENTER, EXIT, ORIGIN, POINT_NAMES, TraceHeader

MISSING = -1
"""Timestamp of a tracepoint a frame never hit. Real timestamps (ns) are never negative."""

PERCENTILES = (50, 95, 99)
_NEVER = np.iinfo(np.int64).max
NS_PER_MS = 1e6


@dataclass
class FrameTable:
    """One row per frame identity (source, frame), sorted by source then frame number."""

    stages: list[str]
    source: np.ndarray
    """(n,) int32."""
    frame: np.ndarray
    """(n,) int64."""
    origin: np.ndarray
    """(n,) int64 ns, MISSING if the origin event is missing."""
    origin_stage: np.ndarray
    """(n,) int64 stage index of the origin event, -1 if missing."""
    enter: np.ndarray
    """(n, n_stages) int64 ns, MISSING where the frame has no enter at that stage."""
    exit: np.ndarray
    """(n, n_stages) int64 ns, MISSING where the frame has no exit at that stage."""

    def __len__(self) -> int:
        return int(self.source.shape[0])


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


def frame_table(header: TraceHeader, events: np.ndarray) -> FrameTable:
    """Pair events by frame identity; where a tracepoint saw a frame twice keep the earliest."""
    n_stages = len(header.stages)
    stage = events["stage"].astype(np.int64)
    point = events["point"].astype(np.int64)
    if len(events) and (stage.min() < 0 or stage.max() >= n_stages or point.min() < 0 or point.max() > EXIT):
        raise TraceError(f"node {header.node}: event stage or point out of range for {n_stages} stages")
    ts = np.ascontiguousarray(events["ts"], dtype=np.int64)
    row, source, frame = _frame_rows(np.ascontiguousarray(events["source"]), np.ascontiguousarray(events["frame"]))
    n = len(source)

    # Earliest timestamp per (frame, stage, point): a scatter-min, no per-event Python.
    cells = np.full(n * n_stages * len(POINT_NAMES), _NEVER, np.int64)
    np.minimum.at(cells, (row * n_stages + stage) * len(POINT_NAMES) + point, ts)
    cells[cells == _NEVER] = MISSING
    return frame_table_from_cells(header.stages, source, frame, cells.reshape(n, n_stages, len(POINT_NAMES)))


def frame_table_from_cells(stages: list[str], source: np.ndarray, frame: np.ndarray, cells: np.ndarray) -> FrameTable:
    """FrameTable from paired cells: ``cells[row, stage, point]`` = ts or MISSING.

    Points are 0 origin, 1 enter, 2 exit; the relay pairs incrementally and builds tables here.
    """
    n = len(source)
    origins = cells[:, :, ORIGIN]
    has_origin = origins != MISSING
    origin_stage = np.where(has_origin.any(axis=1), has_origin.argmax(axis=1), -1)
    origin = np.where(origin_stage >= 0, origins[np.arange(n), np.maximum(origin_stage, 0)], MISSING)
    return FrameTable(
        stages=list(stages), source=np.asarray(source, np.int32), frame=np.asarray(frame, np.int64),
        origin=origin, origin_stage=origin_stage,
        enter=np.ascontiguousarray(cells[:, :, ENTER]), exit=np.ascontiguousarray(cells[:, :, EXIT]),
    )


def _frame_rows(source: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row of each event's frame identity, and the identities sorted by (source, frame)."""
    if len(source) and source.min() >= 0 and source.max() < 1 << 22 and frame.min() >= 0 and frame.max() < 1 << 40:
        # One sort of one int64 key instead of a two-key lexsort: ~3x faster on 1M events.
        keys, row = np.unique((source.astype(np.int64) << 40) | frame, return_inverse=True)
        return row.ravel(), (keys >> 40).astype(np.int32), keys & ((1 << 40) - 1)
    order = np.lexsort((frame, source))
    s_src, s_frame = source[order], frame[order]
    new = np.ones(len(order), bool)
    new[1:] = (s_src[1:] != s_src[:-1]) | (s_frame[1:] != s_frame[:-1])
    row = np.empty(len(order), np.int64)
    row[order] = np.cumsum(new) - 1
    return row, s_src[new].astype(np.int32), s_frame[new].astype(np.int64)


def chains(table: FrameTable) -> Chains:
    """Derive each frame's chain of stages, its completeness and its end timestamp."""
    n, n_stages = table.enter.shape
    rows = np.arange(n)
    has_origin = table.origin_stage >= 0
    t_in = table.enter
    t_out = table.exit.copy()
    t_out[rows[has_origin], table.origin_stage[has_origin]] = table.origin[has_origin]
    passed = (t_in != MISSING) | (t_out != MISSING)

    stage_idx = np.arange(n_stages)
    last_upto = np.maximum.accumulate(np.where(passed, stage_idx, -1), axis=1)
    prev = np.full((n, n_stages), -1, np.int64)
    prev[:, 1:] = last_upto[:, :-1]

    has_exit = (table.exit != MISSING).any(axis=0)
    last = n_stages - 1
    is_origin = stage_idx[None, :] == table.origin_stage[:, None]
    needs_out = passed & ((stage_idx[None, :] < last) | has_exit[None, :])
    broken = (passed & ~is_origin & (t_in == MISSING)).any(axis=1) | (needs_out & (t_out == MISSING)).any(axis=1)
    first_passed = np.where(passed.any(axis=1), passed.argmax(axis=1), -1)
    complete = has_origin & (first_passed == table.origin_stage) & (t_in[:, last] != MISSING) & ~broken

    end = np.where(t_out[:, last] != MISSING, t_out[:, last], t_in[:, last])
    return Chains(t_in=t_in, t_out=t_out, passed=passed, prev=prev, complete=complete, end=end, has_exit=has_exit)


def summarize(values_ms: np.ndarray | Iterable[float]) -> dict:
    """``{count, mean_ms, p50_ms, p95_ms, p99_ms, max_ms}``; values are None when count is 0."""
    values = np.asarray(values_ms, dtype=np.float64).ravel()
    if values.size == 0:
        return {"count": 0, "mean_ms": None, "p50_ms": None, "p95_ms": None, "p99_ms": None, "max_ms": None}
    p50, p95, p99 = np.percentile(values, PERCENTILES, method="linear")
    return {
        "count": int(values.size), "mean_ms": float(values.mean()),
        "p50_ms": float(p50), "p95_ms": float(p95), "p99_ms": float(p99), "max_ms": float(values.max()),
    }


def stage_delays_ns(table: FrameTable, ch: Chains) -> dict[str, np.ndarray]:
    """Stage name -> exit - enter (ns) of each complete frame, for stages with an exit point."""
    out = {}
    for s, name in enumerate(table.stages):
        if not ch.has_exit[s]:
            continue
        ok = ch.complete & (table.enter[:, s] != MISSING) & (table.exit[:, s] != MISSING)
        out[name] = table.exit[ok, s] - table.enter[ok, s]
    return out


def gaps_ns(table: FrameTable, ch: Chains) -> dict[str, np.ndarray]:
    """"A->B" -> enter at B - exit (or origin) at A (ns) of each complete frame, pipeline order."""
    out = {}
    rows = np.arange(len(table))
    for b, name_b in enumerate(table.stages):
        ok = ch.complete & (ch.t_in[:, b] != MISSING) & (ch.prev[:, b] >= 0)
        if not ok.any():
            continue
        prev_b = ch.prev[ok, b]
        gap = ch.t_in[ok, b] - ch.t_out[rows[ok], prev_b]
        for a in np.unique(prev_b):
            out[f"{table.stages[a]}->{name_b}"] = gap[prev_b == a]
    return out


def frame_delays_ns(table: FrameTable, ch: Chains) -> np.ndarray:
    """Chain end - origin (ns) of each complete frame, in table order."""
    return ch.end[ch.complete] - table.origin[ch.complete]


def fps_by_source(table: FrameTable, ch: Chains, sources: Iterable[int] = ()) -> dict[str, float]:
    """Source id (str) -> complete frames per second over the span of their origin timestamps.

    With n frames over a span T the rate is (n - 1) / T: n frames mark n - 1 intervals, so a
    10 fps camera reads 10.0, not 10 + 10/n. 0.0 when fewer than two frames completed.
    """
    ids = sorted(set(int(s) for s in sources) | set(np.unique(table.source).tolist()))
    out = {}
    for sid in ids:
        origin = table.origin[ch.complete & (table.source == sid)]
        span = int(origin.max() - origin.min()) if origin.size >= 2 else 0
        out[str(sid)] = (origin.size - 1) * 1e9 / span if span > 0 else 0.0
    return out


def node_stats(header: TraceHeader, events: np.ndarray, dropped: int = 0) -> dict:
    """Statistics of one node's events; the shape ``dcuscope stats --json`` prints per node."""
    table = frame_table(header, events)
    ch = chains(table)
    n_complete = int(ch.complete.sum())
    return {
        "stages": {k: summarize(v / NS_PER_MS) for k, v in stage_delays_ns(table, ch).items()},
        "gaps": {k: summarize(v / NS_PER_MS) for k, v in gaps_ns(table, ch).items()},
        "frame": summarize(frame_delays_ns(table, ch) / NS_PER_MS),
        "fps": fps_by_source(table, ch, header.sources),
        "dropped": int(dropped),
        "frames": {"complete": n_complete, "incomplete": len(table) - n_complete},
    }


def stats_document(traces: Iterable) -> dict:
    """``{"nodes": {NODE: node_stats}}`` for traces (objects with header, events, dropped).

    Two traces of the same node name are kept apart as NODE, NODE_2, ... (different runs).
    """
    nodes: dict[str, dict] = {}
    for trace in traces:
        nodes[unique_name(trace.header.node, nodes)] = node_stats(trace.header, trace.events, trace.dropped)
    return {"nodes": nodes}


def unique_name(name: str, taken) -> str:
    """``name``, or ``name_2``, ``name_3``... the first not in ``taken``."""
    if name not in taken:
        return name
    k = 2
    while f"{name}_{k}" in taken:
        k += 1
    return f"{name}_{k}"
