"""Exports of probe events: Chrome Trace Event JSON (ui.perfetto.dev, chrome://tracing) and CSV.

Both take ``(header, events)`` pairs, one per node, so that the trace files and the relay's
store can feed them alike. Every figure comes from :mod:`dcuscope.model.delays`; nothing is derived
here.

Perfetto/Chrome JSON layout: one process per node, one thread (track) per stage and source
("infer · src 2"), one complete slice ("ph": "X") per frame per stage from its enter to its
exit, instants for the tracepoints without a duration (origin, sink), and one flow per frame
that links its slices stage after stage. ``ts`` and ``dur`` are in µs, relative to the
earliest event of the export, whose absolute time (ns, the node's clock) is in
``otherData.t0_ns``. Slices on one thread must nest, so when a stage holds two frames of one
source at once (a queue in front of an aggregator), the later frame goes to a second lane,
"infer · src 2 #2".

Where the model has service times (format-2 traces), each stage slice holds two nested
slices, "wait" (enter .. enter + wait) and "service" (the rest, to the exit), none of zero
length; the args of every slice carry ``delay_ms``, ``gap_ms``, ``service_ms``, ``wait_ms``
where defined. Frames with a capture time get a slice capture .. origin on a track
"capture · src N", their glass-to-glass delay in its args. Counter tracks per node:
"utilization <stage>" (busy fraction per bucket, 100 ms unless told) and "frames in <stage>"
(frames between enter and exit). ``ts`` and ``dur`` are chosen so that int(µs * 1000), how
Perfetto reads them, gives back the exact ns: the parts nest in their slice exactly.

Clock: where the timestamps were moved to the relay's clock (a stored session), each node's
correction goes along (a :class:`ClockCorrection`, such as ``relay.clock.correction.Correction``).
Perfetto: the process label reads "clock estimate: -3.000 ms ± 120.0 µs", ``otherData.clock``
holds per node {applied, why, correction_ns, uncertainty_ns, at_ns} (at the node's last event),
and every frame slice's args ``clock_ns`` (the offset subtracted at the frame's origin) and
``clock_uncertainty_ns`` (its bound). CSV: columns ``clock_ns`` and ``clock_uncertainty_ns``,
the frame's, on each of its rows. Without a correction (trace files: the node's own clock,
nothing subtracted) ``clock_ns`` is 0 and the bound is unknown: empty, and absent from Perfetto.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from typing import IO, Iterable, Iterator, Protocol, Sequence

import numpy as np

from dcuscope.model.delays import NS_PER_MS, STAGE_COLUMNS, FrameDelays, busy_timeline, fill_levels, frame_delays
from dcuscope.model.frametable import MISSING, frame_table
from dcuscope.model.journeys import Joined, join
from dcuscope.model.names import unique_name
from dcuscope.protocol.events import TraceHeader

FLOW_CATEGORY = "frame"
BUCKET_NS = 100_000_000
"""Width of the utilization counters' buckets unless told otherwise: 100 ms."""
CSV_COLUMNS = ("node", "source", "frame", "stage", "enter_ns", "exit_ns", *(f"{c}_ms" for c in STAGE_COLUMNS), "complete",
               "capture_ns", "glass_ms", "clock_ns", "clock_uncertainty_ns")

NodeEvents = tuple[TraceHeader, np.ndarray]


class ClockCorrection(Protocol):
    """What was subtracted from a node's timestamps, per timestamp, and its bound (the relay's
    ``relay.clock.correction.Correction`` is one)."""

    applied: str
    why: str

    def offsets(self, ts: np.ndarray) -> np.ndarray: ...

    def uncertainties(self, ts: np.ndarray) -> np.ndarray: ...


def clock_metadata(clock: ClockCorrection, at_ns: int) -> dict:
    """{applied, why, correction_ns, uncertainty_ns, at_ns} of ``clock`` at timestamp ``at_ns``."""
    at = np.array([at_ns], dtype=np.int64)
    return {"applied": clock.applied, "why": clock.why, "correction_ns": int(clock.offsets(at)[0]),
            "uncertainty_ns": int(clock.uncertainties(at)[0]), "at_ns": at_ns}


def clock_label(meta: dict) -> str:
    """The process label of a node's clock: "clock estimate: -3.000 ms ± 120.0 µs"."""
    return (f"clock {meta['applied']}: {meta['correction_ns'] / NS_PER_MS:+.3f} ms "
            f"± {meta['uncertainty_ns'] / 1e3:.1f} µs")


def perfetto_document(nodes: Iterable[NodeEvents], bucket_ns: int = BUCKET_NS,
                      clocks: Sequence[ClockCorrection | None] | None = None) -> dict:
    """The whole Chrome Trace Event JSON object for the events of one or more nodes, their
    utilization counters per ``bucket_ns``; ``clocks``: per node the correction its timestamps
    were moved by (None: none)."""
    nodes = list(nodes)
    clocks = list(clocks) if clocks is not None else [None] * len(nodes)
    non_empty = [ev["ts"].min() for _, ev in nodes if len(ev)]
    t0 = int(min(non_empty)) if non_empty else 0
    trace_events: list[dict] = []
    names: dict[str, int] = {}
    metadata: dict[str, dict] = {}
    flow_ids = iter(range(1, 1 << 62))
    slices: list[dict] = []
    for pid, ((header, events), clock) in enumerate(zip(nodes, clocks), start=1):
        name = unique_name(header.node, names)
        names[name] = pid
        slices.append({})
        trace_events += node_trace_events(header, events, pid=pid, name=name, t0_ns=t0, flow_ids=flow_ids,
                                          bucket_ns=bucket_ns, clock=clock, frame_slices=slices[-1])
        if clock is not None:
            metadata[name] = clock_metadata(clock, int(events["ts"].max()) if len(events) else 0)
    joined = join([_Node(h, ev, c) for (h, ev), c in zip(nodes, clocks)], list(names))
    trace_events += hop_trace_events(joined, slices, pid=len(nodes) + 1, t0_ns=t0, flow_ids=flow_ids)
    return {
        "traceEvents": trace_events,
        "displayTimeUnit": "ms",
        "otherData": {"producer": "dcuscope", "t0_ns": t0, "ts": "µs since t0_ns",
                      "clocks": {name: h.clock for name, (h, _) in zip(names, nodes)}, "clock": metadata},
    }


def node_trace_events(
    header: TraceHeader, events: np.ndarray, *, pid: int, t0_ns: int, name: str | None = None,
    flow_ids: Iterator[int] | None = None, bucket_ns: int = BUCKET_NS, clock: ClockCorrection | None = None,
    frame_slices: dict | None = None,
) -> list[dict]:
    """Trace events of one node as process ``pid``; flow ids come from ``flow_ids``;
    utilization counters per ``bucket_ns``; ``clock``: the correction its timestamps were moved by;
    ``frame_slices``: filled with each frame's slices, (source, frame) -> [(tid, start µs, dur µs)]
    in stage order (where its journey goes on, the flow to the next node starts at its last)."""
    flow_ids = flow_ids if flow_ids is not None else iter(range(1, 1 << 62))
    fd = frame_delays(frame_table(header, events))
    tracks = _Tracks(pid, [
        _meta("process_name", pid, 0, name=name or header.node),
        _meta("process_sort_index", pid, 0, sort_index=pid),
    ])
    if clock is not None:
        tracks.events.append(_meta("process_labels", pid, 0, labels=clock_label(
            clock_metadata(clock, int(events["ts"].max()) if len(events) else 0))))
    frame_clock = _frame_clock(fd, clock)
    # chains[f] collects (tid, start_us, dur_us) of frame f's slices, in stage order.
    chains: list[list[tuple]] = [[] for _ in range(len(fd))]
    out: list[dict] = []
    for s in range(len(fd.table.stages)):
        for sid in np.unique(fd.table.source[fd.chains.passed[:, s]]):
            out += _stage_source_events(fd, s, int(sid), tracks, t0_ns, chains, frame_clock)
    out += _capture_events(fd, tracks, t0_ns)
    out += _counter_events(fd, pid, t0_ns, bucket_ns)
    for chain in chains:
        if len(chain) >= 2:
            out += _flow(pid, next(flow_ids), chain)
    if frame_slices is not None:
        for r, chain in enumerate(chains):
            if chain:
                frame_slices[(int(fd.table.source[r]), int(fd.table.frame[r]))] = chain
    return tracks.events + out


@dataclass
class _Node:
    header: TraceHeader
    events: np.ndarray
    correction: ClockCorrection | None


def hop_trace_events(joined: Joined, slices: list[dict], *, pid: int, t0_ns: int,
                     flow_ids: Iterator[int]) -> list[dict]:
    """The hops between nodes (:mod:`dcuscope.model.journeys`) as process ``pid`` "hops", a track per
    hop, a slice per frame from its sending to its arrival (a hop a hair below zero, one machine's
    shared memory: an instant), and a flow per frame across the processes: from its last slice on
    the sender through the hop to its first slice on the receiver."""
    if not joined.crossed:
        return []
    tracks = _Tracks(pid, [_meta("process_name", pid, 0, name="hops between nodes"),
                           _meta("process_sort_index", pid, 0, sort_index=pid)])
    tids = {name: tracks.add(name) for name in joined.hops}
    out = []
    for c in joined.crossed:
        start = float(_us(c.sent_ns - t0_ns))
        ns = c.arrived_ns - c.sent_ns
        args = {"hop_ms": ns / NS_PER_MS, "from_frame": c.sender[2], "to_frame": c.receiver[2]}
        if c.error_ns is not None:
            args["clock_error_ms"] = c.error_ns / NS_PER_MS
        dur = float(_us(max(ns, 0)))
        out.append({"ph": "X", "name": f"frame {c.sender[2]} → {c.receiver[2]}", "cat": "hop", "pid": pid,
                    "tid": tids[c.hop], "ts": start, "dur": dur, "args": args})
        sent = slices[c.sender[0]].get(c.sender[1:])
        got = slices[c.receiver[0]].get(c.receiver[1:])
        chain = [(c.sender[0] + 1, *sent[-1])] if sent else []
        chain.append((pid, tids[c.hop], start, dur))
        chain += [(c.receiver[0] + 1, *got[0])] if got else []
        if len(chain) >= 2:
            out += _cross_flow(next(flow_ids), chain)
    return tracks.events + out


def _cross_flow(flow_id: int, chain: list[tuple]) -> list[dict]:
    """s / t / f events of one frame across processes, each at the middle of its slice."""
    phases = ["s"] + ["t"] * (len(chain) - 2) + ["f"]
    out = []
    for ph, (pid, tid, start, dur) in zip(phases, chain):
        ev = {"ph": ph, "name": "journey", "cat": FLOW_CATEGORY, "id": flow_id, "pid": pid, "tid": tid,
              "ts": round(start + dur / 2, 3)}
        if ph == "f":
            ev["bp"] = "e"
        out.append(ev)
    return out


class _Tracks:
    """Thread tracks of one process: each new one gets the next tid and its name events."""

    def __init__(self, pid: int, events: list[dict]):
        self.pid, self.events, self.count = pid, events, 0

    def add(self, label: str) -> int:
        self.count += 1
        self.events.append(_meta("thread_name", self.pid, self.count, name=label))
        self.events.append(_meta("thread_sort_index", self.pid, self.count, sort_index=self.count))
        return self.count


def _frame_clock(fd: FrameDelays, clock: ClockCorrection | None) -> tuple[list[int], list[int]] | None:
    """Per frame of ``fd``, the offset subtracted at its origin (a frame without one: at its last
    timestamp) and its bound; None without a correction. The events are corrected already:
    evaluated at the corrected time, off from the node-time value by drift x offset at most
    (2 ns for 50 ppm and 37 ms)."""
    if clock is None:
        return None
    origin = fd.table.origin
    at = np.where(origin != MISSING, origin, np.maximum(fd.chains.t_in, fd.chains.t_out).max(axis=1, initial=0))
    return clock.offsets(at).tolist(), clock.uncertainties(at).tolist()


def _stage_source_events(fd: FrameDelays, s: int, sid: int, tracks: _Tracks, t0_ns: int,
                         chains: list[list[tuple]], frame_clock: tuple[list[int], list[int]] | None) -> list[dict]:
    """The slices (with their wait and service parts) and instants of one source at stage ``s``,
    on as many lanes as it needs; appends each frame's slice to its chain for the flows."""
    table, ch, stage = fd.table, fd.chains, fd.table.stages[s]
    rows = np.flatnonzero(ch.passed[:, s] & (table.source == sid))
    enter, exit_ = table.enter[rows, s], table.exit[rows, s]
    is_slice = (enter != MISSING) & (exit_ != MISSING)
    lane = np.zeros(len(rows), np.int64)
    lane[is_slice] = assign_lanes(enter[is_slice], exit_[is_slice])
    tids = [tracks.add(f"{stage} · src {sid}" + (f" #{k + 1}" if k else "")) for k in range(int(lane.max()) + 1)]
    # Instants: origin, sink, or a tracepoint whose pair was lost.
    point_ns = np.where(enter == MISSING, ch.t_out[rows, s], enter)
    columns = (rows.tolist(), lane.tolist(), is_slice.tolist(), _us(enter - t0_ns).tolist(),
               _us(fd.per_stage["delay"][rows, s]).tolist(), _us(point_ns - t0_ns).tolist())
    out = []
    for r, k, sliced, start, dur, point in zip(*columns):
        base = {"name": f"frame {table.frame[r]}", "cat": stage, "pid": tracks.pid, "tid": tids[k]}
        args = _frame_args(fd, r, s, frame_clock)
        if sliced:
            out.append({"ph": "X", **base, "ts": start, "dur": dur, "args": args})
            out += _parts(fd, r, s, {**base, "args": {"source": sid, "frame": args["frame"]}}, t0_ns)
            if dur > 0:
                chains[r].append((tids[k], start, dur))
        else:
            what = "origin" if table.origin_stage[r] == s else ("enter" if table.enter[r, s] != MISSING else "exit")
            out.append({"ph": "i", "s": "t", **base, "ts": point, "args": {**args, "point": what}})
    return out


def _frame_args(fd: FrameDelays, r: int, s: int, frame_clock: tuple[list[int], list[int]] | None = None) -> dict:
    """Args of frame ``r``'s slice or instant at stage ``s``: its identity, completeness, its
    clock offset and bound (where corrected) and each per-stage figure it has (``delay_ms``,
    ``gap_ms``, ``service_ms``, ``wait_ms``)."""
    args = {"source": int(fd.table.source[r]), "frame": int(fd.table.frame[r]), "complete": bool(fd.chains.complete[r])}
    if frame_clock is not None:
        args["clock_ns"], args["clock_uncertainty_ns"] = frame_clock[0][r], frame_clock[1][r]
    for name in STAGE_COLUMNS:
        value = float(fd.per_stage[name][r, s])
        if value == value:  # not NaN: the frame has the tracepoints this figure needs
            args[f"{name}_ms"] = value / NS_PER_MS
    return args


def _parts(fd: FrameDelays, r: int, s: int, base: dict, t0_ns: int) -> list[dict]:
    """The "wait" (enter .. enter + wait) and "service" (the rest, to the exit) slices nested
    in frame ``r``'s slice at stage ``s``; none where the model has no service time, and none
    of zero length."""
    wait, service = fd.per_stage["wait"][r, s], fd.per_stage["service"][r, s]
    if wait != wait:
        return []
    enter = int(fd.table.enter[r, s])
    parts = (("wait", enter, int(wait)), ("service", enter + int(wait), int(service)))
    return [{"ph": "X", **base, "name": name, "ts": float(_us(start - t0_ns)), "dur": float(_us(ns)),
             "args": {**base["args"], f"{name}_ms": ns / NS_PER_MS}} for name, start, ns in parts if ns > 0]


def _capture_events(fd: FrameDelays, tracks: _Tracks, t0_ns: int) -> list[dict]:
    """Per source whose frames have a capture time, a track "capture · src N" with a slice per
    frame from its capture to its origin, its glass-to-glass delay (end - capture) in args."""
    table = fd.table
    out = []
    for sid in np.unique(table.source[table.capture != MISSING]).tolist():
        rows = np.flatnonzero((table.source == sid) & (table.capture != MISSING) & (table.origin != MISSING))
        if not len(rows):
            continue
        # A capture clock ahead of the node's would give a negative duration, which viewers
        # reject: such a slice shrinks to an instant at the capture time.
        start = table.capture[rows]
        end = np.maximum(table.origin[rows], start)
        lane = assign_lanes(start, end)
        tids = [tracks.add(f"capture · src {sid}" + (f" #{k + 1}" if k else "")) for k in range(int(lane.max()) + 1)]
        columns = (rows.tolist(), lane.tolist(), _us(start - t0_ns).tolist(), _us(end - start).tolist(),
                   (fd.glass[rows] / NS_PER_MS).tolist())
        for r, k, ts, dur, glass in zip(*columns):
            args = {"source": sid, "frame": int(table.frame[r]), "complete": bool(fd.chains.complete[r])}
            if glass == glass:
                args["glass_ms"] = glass
            out.append({"ph": "X", "name": "capture", "cat": "capture", "pid": tracks.pid, "tid": tids[k],
                        "ts": ts, "dur": dur, "args": args})
    return out


def _counter_events(fd: FrameDelays, pid: int, t0_ns: int, bucket_ns: int) -> list[dict]:
    """Counter tracks: "utilization <stage>" (busy fraction per bucket, from
    :func:`dcuscope.model.delays.busy_timeline`; back to 0 at the end of the span) and "frames in
    <stage>" (:func:`dcuscope.model.delays.fill_levels`)."""
    out = []
    timeline = busy_timeline(fd, bucket_ns)
    if timeline.busy:
        ts = _us(timeline.edges - t0_ns).tolist()
        util = {stage: [*timeline.utilization(stage).tolist(), 0.0] for stage in timeline.busy}
        out += [{"ph": "C", "name": "utilization", "cat": "counter", "pid": pid, "tid": 0, "ts": t,
                 "args": {stage: values[i] for stage, values in util.items()}} for i, t in enumerate(ts)]
    for s, stage in enumerate(fd.table.stages):
        times, levels = fill_levels(fd, s)
        out += [{"ph": "C", "name": "frames in", "cat": "counter", "pid": pid, "tid": 0, "ts": t, "args": {stage: n}}
                for t, n in zip(_us(times - t0_ns).tolist(), levels.tolist())]
    return out


def _us(ns: np.ndarray | float) -> np.ndarray:
    """Integer ns -> float µs that reads back to the same ns: viewers take int(µs * 1000)
    (Perfetto truncates), so where the nearest double falls short, take the next one up;
    then nested slices stay nested to the nanosecond. NaN stays NaN."""
    ns = np.asarray(ns, dtype=np.float64)
    us = ns / 1e3
    return np.where(us * 1e3 < ns, np.nextafter(us, np.inf), us)


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


def csv_rows(header: TraceHeader, events: np.ndarray, node: str | None = None,
             clock: ClockCorrection | None = None) -> Iterator[list]:
    """One row per frame per stage it passed (CSV_COLUMNS), by source, frame, stage order.

    At the origin stage ``exit_ns`` is the origin timestamp; missing values are empty.
    ``capture_ns`` (the source's capture time), ``glass_ms`` (glass-to-glass delay),
    ``clock_ns`` and ``clock_uncertainty_ns`` (what ``clock`` subtracted at its origin, and its
    bound: 0 and empty without one) are the frame's, on each of its rows.
    """
    fd = frame_delays(frame_table(header, events))
    table, ch = fd.table, fd.chains
    node = node or header.node
    rows, stages = np.nonzero(ch.passed)
    figures = [_ms_cells(fd.per_stage[name][rows, stages]) for name in STAGE_COLUMNS]
    frame_clock = _frame_clock(fd, clock)
    offsets = [frame_clock[0][r] for r in rows.tolist()] if frame_clock else [0] * len(rows)
    bounds = [frame_clock[1][r] for r in rows.tolist()] if frame_clock else [""] * len(rows)
    columns = zip(
        table.source[rows].tolist(), table.frame[rows].tolist(), stages.tolist(), ch.t_in[rows, stages].tolist(),
        ch.t_out[rows, stages].tolist(), ch.complete[rows].tolist(), table.capture[rows].tolist(),
        _ms_cells(fd.glass[rows]), offsets, bounds, *figures,
    )
    for src, frm, s, e, x, complete, capture, glass, off, bound, *cells in columns:
        yield [node, src, frm, table.stages[s], "" if e == MISSING else e, "" if x == MISSING else x, *cells,
               int(complete), "" if capture == MISSING else capture, glass, off, bound]


def _ms_cells(ns: np.ndarray) -> list[str]:
    """ns -> ms with 6 decimals (1 ns), empty where undefined (NaN)."""
    return ["" if v != v else f"{v / NS_PER_MS:.6f}" for v in ns.tolist()]


def write_csv(out: IO[str], nodes: Iterable[NodeEvents], clocks: Sequence[ClockCorrection | None] | None = None) -> int:
    """Write the CSV of one or more nodes to an open text file (``clocks``: per node the
    correction its timestamps were moved by, or None); returns the number of rows."""
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    count = 0
    names: set[str] = set()
    nodes = list(nodes)
    for (header, events), clock in zip(nodes, list(clocks) if clocks is not None else [None] * len(nodes)):
        name = unique_name(header.node, names)
        names.add(name)
        for row in csv_rows(header, events, node=name, clock=clock):
            writer.writerow(row)
            count += 1
    return count
