"""``dcuscope stats``: per-stage and per-frame delay statistics of trace files or a stored session,
or of one DCU over days from the store's rollups (``--node``).

Over a stored session each node's statistics carry the ``clock`` entry of :mod:`dcuscope.relay.clock.entry`
(the correction its timestamps were moved by, at its last event, and its bound); trace files hold
the node's own clock, uncorrected. Returns the exit status: 0, or 2 after one ``dcuscope: error: ...``
line on stderr for a bad input (missing file, not a trace, no such database or session).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from dcuscope.commands.traceinputs import add_input_arguments, clocks, open_output, read_inputs, user_errors
from dcuscope.core.errors import DcuscopeError
from dcuscope.probes.trace.stats import stats_document
from dcuscope.probes.trace.tracefile import Trace
from dcuscope.relay.clock.entry import clock_entry

STAT_COLUMNS = ("count", "mean_ms", "p50_ms", "p95_ms", "p99_ms", "max_ms")


def add_stats_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "stats", help="per-stage and per-frame delay statistics of trace files or a stored session",
        description="Per node: stage delays, gaps between stages and end-to-end frame delays "
                    "(count, mean, p50, p95, p99, max in ms); each stage's delay split into service "
                    "(its own work) and wait (queued, batching, blocked downstream), its busy "
                    "fraction (utilization) and share of the frame delay; the bottleneck (the busiest "
                    "stage of a saturated streaming thread) and why; per source, frames delivered vs "
                    "the nominal rate, lost upstream and dropped by reason.",
    )
    add_input_arguments(p)
    p.add_argument("--node", metavar="NAME",
                   help="with --db: one DCU over days or months, from the store's rollups (per minute and hour, "
                        "written as the relay compacts): counts, means, min, max, drops exact, percentiles within "
                        "1 %% of the value (a sketch)")
    p.add_argument("--since", metavar="DURATION", help="with --node: how far back, e.g. 90m, 12h, 30d (default 1d)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p.set_defaults(func=run_stats)
    return p


def run_stats(args: argparse.Namespace) -> int:
    if args.node is not None or args.since is not None:
        return _rollup_stats(args)
    with user_errors() as failed:
        traces = read_inputs(args, "stats")
        doc = stats_document(traces)
        for st, trace, clock in zip(doc["nodes"].values(), traces, clocks(traces)):
            if clock is not None:
                st["clock"] = clock_entry(trace.correction, trace.last_ns)
        with open_output("-") as out:
            if args.json:
                out.write(json.dumps(doc, indent=2) + "\n")
            else:
                out.write(format_stats(doc, [_origin(t, args.db) for t in traces]))
    return 2 if failed else 0


def _rollup_stats(args: argparse.Namespace) -> int:
    with user_errors() as failed:
        if args.db is None or args.node is None or args.traces or args.session is not None:
            raise DcuscopeError("stats: --node and --since read a store's rollups: give --db PATH|URL --node NAME "
                                "[--since DURATION], without TRACE files or --session")
        from dcuscope.relay.store.engines import is_url
        from dcuscope.relay.store.history import parse_duration_ns, summary

        if not is_url(args.db) and not Path(args.db).is_file():
            raise DcuscopeError(f"stats: {args.db}: no such database")
        started = time.monotonic()
        now = time.time_ns()
        doc = summary(args.db, args.node, now - parse_duration_ns(args.since or "1d"), now)
        doc["elapsed_s"] = round(time.monotonic() - started, 3)
        if not doc["rows"] and not doc["raw"]["events"]:
            raise DcuscopeError(_nothing_stored(args))
        with open_output("-") as out:
            out.write(json.dumps(doc, indent=2) + "\n" if args.json else format_rollups(doc))
    return 2 if failed else 0


def _nothing_stored(args: argparse.Namespace) -> str:
    """Why ``stats --node --since`` has nothing to say: nothing of that node is stored in the span (its
    rollups and its raw batches are both read), and which nodes have something."""
    from dcuscope.relay.store.history import nodes
    from dcuscope.relay.urls import redact

    db = redact(args.db)
    known = [n["node"] for n in nodes(args.db)]
    others = f" (nodes with data: {', '.join(known[:10])})" if known and args.node not in known else ""
    return (f"stats: nothing stored of node {args.node!r} since {args.since or '1d'} in {db}{others}: a run's "
            f"frames count here once its relay stored its first events")


ROLLUP_COLUMNS = ("count", "mean_ms", "min_ms", "p50_ms", "p90_ms", "p99_ms", "max_ms")


def format_rollups(doc: dict) -> str:
    """The table of :func:`dcuscope.relay.store.history.summary`, with what is exact and what is not."""
    def stamp(ns: int | None) -> str:
        return "-" if ns is None else time.strftime("%Y-%m-%d %H:%M", time.gmtime(ns / 1e9)) + " UTC"

    lines = [f"node {doc['node']}  (rollups of minutes and hours starting {stamp(doc['first_ns'])} to "
             f"{stamp(doc['last_ns'])}: {doc['rows']} rows read in {doc.get('elapsed_s', 0):.2f} s)"]
    rows = [("stage " + k, v) for k, v in doc["stages"].items()] + [("frame (end to end)", doc["frame"])]
    width = max(len(name) for name, _ in rows)
    lines.append("  " + " " * width + "".join(f"{c:>10}" for c in ROLLUP_COLUMNS) + f"{'drops':>8}")
    for name, v in rows:
        cells = [f"{v['count']:>10}"] + [f"{_num(v[c]):>10}" for c in ROLLUP_COLUMNS[1:]]
        lines.append(f"  {name:<{width}}" + "".join(cells) + f"{v.get('drops', ''):>8}")
    split = [(k, v) for k, v in doc["stages"].items() if v["service"]["count"]]
    if split:
        lines.append("  " + " " * width + "".join(f"{c:>15}" for c in ("service mean", "service p99", "wait mean",
                                                                        "wait p99")))
        for name, v in split:
            cells = [_num(v["service"]["mean_ms"]), _num(v["service"]["p99_ms"]), _num(v["wait"]["mean_ms"]),
                     _num(v["wait"]["p99_ms"])]
            lines.append(f"  {'stage ' + name:<{width}}" + "".join(f"{c:>15}" for c in cells))
    frame = doc["frame"]
    lines.append(f"  frames         {frame['count']} complete, {frame['incomplete']} incomplete; {frame['lost']} events lost")
    lines.append(f"  exact: count, mean, min, max, drops, frames, lost; p50, p90, p99 from the sketch, within "
                 f"{doc['relative_error']:.0%} of the value")
    if doc["raw"]["said"]:  # batches not compacted yet: counted from them, or said to be left out
        lines.append(f"  raw: {doc['raw']['said']}")
    return "\n".join(lines) + "\n"


def _origin(trace, db: str | None) -> str:
    """Where a node's events come from, for the title of its table."""
    if isinstance(trace, Trace):
        return f"{trace.path}{'' if trace.complete else ', no end line: the run did not close the trace'}"
    named = trace.header.node.endswith(f" · run {trace.run[:8]}")  # its name says its run already
    return f"{db}: session {trace.session}{'' if named else f', run {trace.run[:8]}'}{'' if trace.ended else ', not ended'}"


def format_stats(doc: dict, origins: list[str] | None = None) -> str:
    """Readable aligned tables, one block per node (``origins``: where each came from, for the
    titles): delays (stages, gaps, frame), where the time goes (service, wait, utilization,
    share of delay), the bottleneck and why, every source's frames, drops, and for a stored run
    the clock correction its timestamps were moved by, with its bound."""
    lines: list[str] = []
    for i, (node, st) in enumerate(doc["nodes"].items()):
        title = f"node {node}"
        if origins and i < len(origins):
            title += f"  ({origins[i]})"
        lines.append(title)
        lines += _delay_table(st) + _split_table(st) + _bottleneck_lines(st) + _source_lines(st)
        frames = st["frames"]
        lines.append(f"  frames         {frames['complete']} complete, {frames['incomplete']} incomplete")
        lines.append(f"  dropped events {st['dropped']}")
        lines += _clock_lines(st)
        lines.append("")
    if "journeys" in doc:
        lines += journey_lines(doc["journeys"]) + [""]
    return "\n".join(lines)


def journey_lines(j: dict) -> list[str]:
    """The hops between nodes and the frames' journeys across them (:mod:`dcuscope.model.journeys`)."""
    lines = ["journeys across nodes (frames that went from one pipeline to another)"]
    rows = [("hop " + k, v) for k, v in j["hops"].items()]
    for path, v in j["paths"].items():
        rows.append((f"journey {path}", v))
        rows += [(f"  {'in ' if name in j['hops'] else 'on '}{name}", part) for name, part in v["parts"].items()]
    width = max(len(name) for name, _ in rows)
    lines.append("  " + " " * width + "".join(f"{c:>10}" for c in STAT_COLUMNS))
    for name, v in rows:
        lines.append(f"  {name:<{width}}" + f"{v['count']:>10}" + "".join(f"{_num(v[c]):>10}" for c in STAT_COLUMNS[1:]))
    lines.append("  (a journey: from the frame's first origin, or its capture time, to its end on the last node)")
    for name, hop in j["hops"].items():
        error = ("clocks not aligned (trace files: compare only nodes that share a clock, one machine or PTP)"
                 if hop["clock_error_ms"] is None else f"clock error ± {hop['clock_error_ms']:.3f} ms (both nodes' bounds)")
        lines.append(f"  hop {name}: {hop['lost']} lost on the way; {error}")
    for counts, meaning in ((j["untraced"], "arrived from no traced sender"),
                            (j["ambiguous"], "could be two sent frames: left unjoined")):
        for node, n in counts.items():
            lines.append(f"  {node}: {n} {'frame' if n == 1 else 'frames'} {meaning}")
    return lines


def _delay_table(st: dict) -> list[str]:
    rows = [("stage " + k, v) for k, v in st["stages"].items()]
    rows += [("gap " + k, v) for k, v in st["gaps"].items()]
    rows.append(("frame (end to end)", st["frame"]))
    if st.get("glass", {}).get("count"):
        rows.append(("frame (glass to glass)", st["glass"]))
    width = max(len(name) for name, _ in rows)
    lines = ["  " + " " * width + "".join(f"{c:>10}" for c in STAT_COLUMNS)]
    for name, s in rows:
        cells = [f"{s['count']:>10}"] + [f"{_num(s[c]):>10}" for c in STAT_COLUMNS[1:]]
        lines.append(f"  {name:<{width}}" + "".join(cells))
    return lines


SPLIT_COLUMNS = ("service mean", "service p99", "wait mean", "busy", "share of delay", "in stage")


def _split_table(st: dict) -> list[str]:
    """Where each stage's delay goes: its own work (service) or waiting, how busy it is."""
    if not st["stages"] or all(v.get("utilization") is None for v in st["stages"].values()):
        return ["  (no service/wait split: a format-1 trace or Python probes)"]
    width = max(len("stage " + k) for k in st["stages"])
    lines = ["  " + " " * width + "".join(f"{c:>15}" for c in SPLIT_COLUMNS)]
    for name, v in st["stages"].items():
        cells = [_num(v["service"]["mean_ms"]), _num(v["service"]["p99_ms"]), _num(v["wait"]["mean_ms"]),
                 _pct(v.get("utilization")), _pct(v.get("share")), _num(v.get("occupancy"), 2)]
        lines.append(f"  {'stage ' + name:<{width}}" + "".join(f"{c:>15}" for c in cells))
    return lines


def _bottleneck_lines(st: dict) -> list[str]:
    b = st.get("bottleneck")
    if not b:
        return []
    # Unsaturated, the reason names the busiest stage itself: said once, not as the bottleneck's name too.
    what = f"{b['stage']}: " if b.get("saturated") is not False else "none: "
    return [f"  {'bottleneck':<14} {what}{b['reason']}"]


def _source_lines(st: dict) -> list[str]:
    lines = []
    for sid, src in st.get("sources", {}).items():
        nominal = _against_nominal(src["fps"], src.get("nominal_fps"))
        dropped = ", ".join(f"{reason} {n}" for reason, n in src["dropped"].items()) or "0"
        lines.append(f"  source {sid:<7} {src['delivered']} delivered, {src['fps']:.2f} frames/s{nominal}; "
                     f"RTP packets lost {src['lost_upstream']}, decoder dropped {src['decoder_dropped']}, "
                     f"pipeline dropped {dropped}")
    if not lines:
        fps = "  ".join(f"src {k}: {v:.2f}" for k, v in st["fps"].items()) or "-"
        lines.append(f"  frames/s       {fps}")
    return lines


FASTER_THAN_NOMINAL = 1.05
"""A source delivering this much above its nominal rate was read faster than real time (a file
not paced as a camera): its shortfall against the nominal rate would mean nothing."""


def _against_nominal(fps: float, nominal: float | None) -> str:
    if not nominal:
        return ""
    if fps > nominal * FASTER_THAN_NOMINAL:
        return f" (read faster than real time: nominal {nominal:.2f})"
    return f" of {nominal:.2f} nominal"


def _clock_lines(st: dict) -> list[str]:
    """What was subtracted from the node's timestamps and its bound (stored sessions only)."""
    c = st.get("clock")
    if not c:
        return []
    why = f" ({c['why']})" if c.get("why") else ""
    offset, bound = offset_and_bound(c["correction_ns"], c["uncertainty_ns"])
    return [f"  clock          {c['applied']}: {offset} subtracted ± {bound}{why}"]


def offset_and_bound(offset_ns: float, bound_ns: float) -> tuple[str, str]:
    """A clock offset and its bound in one unit, the larger one's, as the page's tooltip
    (ui/static/timefmt.js formatOffsetBound): ("-1.0 µs", "5.1 µs"), ("+3.012 ms", "0.051 ms")."""
    big = max(abs(offset_ns), abs(bound_ns))
    scale, unit, digits = (1e3, "µs", 1 if big < 1e4 else 0) if big < 1e6 else (1e6, "ms", 3) if big < 1e9 else (1e9, "s", 6)
    offset = f"{abs(offset_ns) / scale:.{digits}f}"
    sign = "" if float(offset) == 0 else "+" if offset_ns >= 0 else "-"
    return f"{sign}{offset} {unit}", f"{abs(bound_ns) / scale:.{digits}f} {unit}"


def _num(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value * 100:.1f} %"
