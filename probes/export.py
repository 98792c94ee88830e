"""Exports of probe events: Chrome Trace Event JSON (ui.perfetto.dev, chrome://tracing) and CSV.

Both take ``(header, events)`` pairs, one per node, so that the trace files and the relay's
store can feed them alike.

Perfetto/Chrome JSON layout: one process per node, one thread (track) per stage and source
("infer · src 2"), one complete slice ("ph": "X") per frame per stage from its enter to its
exit, instants for the tracepoints without a duration (origin, sink), and one flow per frame
that links its slices stage after stage. ``ts`` and ``dur`` are in µs, relative to the
earliest event of the export, whose absolute time (ns, the node's clock) is in
``otherData.t0_ns``. Slices on one thread must nest, so when a stage holds two frames of one
source at once (a queue in front of an aggregator), the later frame goes to a second lane,
"infer · src 2 #2".
"""

from __future__ import annotations

import csv
from typing import IO, Iterable, Iterator

import numpy as np

from probes.delays import NS_PER_MS, STAGE_COLUMNS, frame_delays
from probes.events import TraceHeader
from probes.frametable import MISSING, frame_table
from probes.stats import unique_name

FLOW_CATEGORY = "frame"
CSV_COLUMNS = ("node", "source", "frame", "stage", "enter_ns", "exit_ns", *(f"{c}_ms" for c in STAGE_COLUMNS), "complete")

NodeEvents = tuple[TraceHeader, np.ndarray]


def perfetto_document(nodes: Iterable[NodeEvents]) -> dict:
    """The whole Chrome Trace Event JSON object for the events of one or more nodes."""
    nodes = list(nodes)
    non_empty = [ev["ts"].min() for _, ev in nodes if len(ev)]
    t0 = int(min(non_empty)) if non_empty else 0
    trace_events: list[dict] = []
    names: dict[str, int] = {}
    flow_ids = iter(range(1, 1 << 62))
    for pid, (header, events) in enumerate(nodes, start=1):
        name = unique_name(header.node, names)
        names[name] = pid
        trace_events += node_trace_events(header, events, pid=pid, name=name, t0_ns=t0, flow_ids=flow_ids)
    return {
        "traceEvents": trace_events,
        "displayTimeUnit": "ms",
        "otherData": {"producer": "dcuscope", "t0_ns": t0, "ts": "µs since t0_ns",
                      "clocks": {name: h.clock for name, (h, _) in zip(names, nodes)}},
    }


def node_trace_events(
    header: TraceHeader, events: np.ndarray, *, pid: int, t0_ns: int, name: str | None = None,
    flow_ids: Iterator[int] | None = None,
) -> list[dict]:
    """Trace events of one node as process ``pid``; flow ids come from ``flow_ids``."""
    flow_ids = flow_ids if flow_ids is not None else iter(range(1, 1 << 62))
    fd = frame_delays(frame_table(header, events))
    table, ch = fd.table, fd.chains
    delay_ns, gap_ms = fd.per_stage["delay"], fd.per_stage["gap"] / NS_PER_MS
    stages = table.stages
    out: list[dict] = [
        _meta("process_name", pid, 0, name=name or header.node),
        _meta("process_sort_index", pid, 0, sort_index=pid),
    ]

    def us(ns):
        return np.round((ns - t0_ns) / 1e3, 3)

    # slices[f] collects (stage, tid, start_us, dur_us) of frame f, in stage order.
    slices: list[list[tuple]] = [[] for _ in range(len(table))]
    tid_of: dict[tuple[int, int, int], int] = {}
    for s, stage in enumerate(stages):
        for sid in np.unique(table.source[ch.passed[:, s]]):
            rows = np.flatnonzero(ch.passed[:, s] & (table.source == sid))
            enter, exit_ = table.enter[rows, s], table.exit[rows, s]
            is_slice = (enter != MISSING) & (exit_ != MISSING)
            lane = np.zeros(len(rows), np.int64)
            lane[is_slice] = assign_lanes(enter[is_slice], exit_[is_slice])
            for k in range(int(lane.max()) + 1):
                tid = len(tid_of) + 1
                tid_of[(s, int(sid), k)] = tid
                label = f"{stage} · src {sid}" + (f" #{k + 1}" if k else "")
                out.append(_meta("thread_name", pid, tid, name=label))
                out.append(_meta("thread_sort_index", pid, tid, sort_index=tid))
            for i, r in enumerate(rows.tolist()):
                tid = tid_of[(s, int(sid), int(lane[i]))]
                args = {"source": int(sid), "frame": int(table.frame[r]), "complete": bool(ch.complete[r])}
                gap = float(gap_ms[r, s])
                if gap == gap:  # not NaN: the frame has a previous exit there
                    args["gap_ms"] = gap
                if is_slice[i]:
                    start, dur = float(us(enter[i])), float(delay_ns[r, s]) / 1e3
                    args["delay_ms"] = float(delay_ns[r, s]) / NS_PER_MS
                    out.append({"ph": "X", "name": f"frame {table.frame[r]}", "cat": stage, "pid": pid,
                                "tid": tid, "ts": start, "dur": dur, "args": args})
                    if dur > 0:
                        slices[r].append((tid, start, dur))
                else:
                    # Origin, sink, or a tracepoint whose pair was lost: a point in time.
                    ts_ns = ch.t_out[r, s] if enter[i] == MISSING else enter[i]
                    what = "origin" if table.origin_stage[r] == s else ("enter" if enter[i] != MISSING else "exit")
                    args["point"] = what
                    out.append({"ph": "i", "s": "t", "name": f"frame {table.frame[r]}", "cat": stage,
                                "pid": pid, "tid": tid, "ts": float(us(ts_ns)), "args": args})
    for r, chain in enumerate(slices):
        if len(chain) >= 2:
            out += _flow(pid, next(flow_ids), chain)
    return out


def assign_lanes(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Lane index per interval such that intervals in one lane never overlap (touching is fine).

    Greedy in order of start: the lowest lane whose last interval has ended. One lane in the
    usual case, checked vectorised before falling back to the loop.
    """
    order = np.argsort(start, kind="stable")
    s, e = start[order], end[order]
    lanes = np.zeros(len(start), np.int64)
    if len(s) < 2 or bool(np.all(s[1:] >= np.maximum.accumulate(e)[:-1])):
        return lanes
    lane_end: list[int] = []
    sorted_lanes = np.zeros(len(s), np.int64)
    for i, (a, b) in enumerate(zip(s.tolist(), e.tolist())):
        for k, busy_until in enumerate(lane_end):
            if busy_until <= a:
                break
        else:
            k = len(lane_end)
            lane_end.append(0)
        lane_end[k] = b
        sorted_lanes[i] = k
    lanes[order] = sorted_lanes
    return lanes


def _meta(kind: str, pid: int, tid: int, **args) -> dict:
    return {"ph": "M", "name": kind, "pid": pid, "tid": tid, "args": args}


def _flow(pid: int, flow_id: int, chain: list[tuple]) -> list[dict]:
    """s / t... / f events binding to the middle of each slice of one frame, in stage order."""
    phases = ["s"] + ["t"] * (len(chain) - 2) + ["f"]
    out = []
    for ph, (tid, start, dur) in zip(phases, chain):
        ev = {"ph": ph, "name": "frame", "cat": FLOW_CATEGORY, "id": flow_id, "pid": pid, "tid": tid,
              "ts": round(start + dur / 2, 3)}
        if ph == "f":
            ev["bp"] = "e"  # bind to the enclosing slice, not the next one
        out.append(ev)
    return out


def csv_rows(header: TraceHeader, events: np.ndarray, node: str | None = None) -> Iterator[list]:
    """One row per frame per stage it passed (CSV_COLUMNS), by source, frame, stage order.

    At the origin stage ``exit_ns`` is the origin timestamp; missing values are empty.
    """
    fd = frame_delays(frame_table(header, events))
    table, ch = fd.table, fd.chains
    node = node or header.node
    rows, stages = np.nonzero(ch.passed)
    figures = [_ms_cells(fd.per_stage[name][rows, stages]) for name in STAGE_COLUMNS]
    columns = zip(
        table.source[rows].tolist(), table.frame[rows].tolist(), stages.tolist(), ch.t_in[rows, stages].tolist(),
        ch.t_out[rows, stages].tolist(), ch.complete[rows].tolist(), *figures,
    )
    for src, frm, s, e, x, complete, *cells in columns:
        yield [node, src, frm, table.stages[s], "" if e == MISSING else e, "" if x == MISSING else x, *cells,
               int(complete)]


def _ms_cells(ns: np.ndarray) -> list[str]:
    """ns -> ms with 6 decimals (1 ns), empty where undefined (NaN)."""
    return ["" if v != v else f"{v / NS_PER_MS:.6f}" for v in ns.tolist()]


def write_csv(out: IO[str], nodes: Iterable[NodeEvents]) -> int:
    """Write the CSV of one or more nodes to an open text file; returns the number of rows."""
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    count = 0
    names: set[str] = set()
    for header, events in nodes:
        name = unique_name(header.node, names)
        names.add(name)
        for row in csv_rows(header, events, node=name):
            writer.writerow(row)
            count += 1
    return count
