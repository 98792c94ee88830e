"""``dcuscope compare BASE NEW [MORE...]``: did it get slower? Each figure's change with an honest
interval, a table, JSON or Markdown, and a gate for CI (``--fail-if``).

Exit status: 0 (every bound passed), 1 (a bound failed), 2 (bad input), each with one line saying why.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

from dcuscope.core.errors import DcuscopeError

DESCRIPTION = """\
Compare runs of a pipeline: for each stage (matched by name) and end to end, the frames and the
mean, p50, p90 and p99 of delay, service and wait of every input, and for each input after the
first (BASE) the change against BASE, in ms and in %, with its 95 % confidence interval and a
verdict (slower, faster, no significant change). Inputs of different pipelines (other stages) are
compared only on the stages both have: a stage only one has, and end to end, keep their figures
and get no change or verdict ("not in both").

Frames of one run are not independent (a slow frame delays the next; a busy machine slows a
stretch of them), so intervals come from the circular block bootstrap: each run is resampled in
blocks of consecutive frames (in the order of their origin), the block length chosen from the
run's own autocorrelation (Politis & White's rule); as blocks cut the correlation at their ends,
the resamples spread too little, and each figure's are stretched by the factor that the run's
autocorrelation says is missing. The interval is the 2.5-97.5 percentile range of NEW - BASE
over the resamples, widened by Student's t with a degree of freedom per block (the spread is
itself an estimate from that many blocks). A figure is slower (faster) when its whole interval is
above (below) zero and the change is at least --noise % of BASE and --noise-ms. Each interval is
95 % on its own; the verdict over a whole table uses Holm's correction, so that identical runs are
called different in at most 5 % of comparisons.

The intervals speak of these two runs, frame to frame: what differs from one run to the next
as a whole (the cores the threads got, a machine busier during one run, where live frames fall
against the mux's timing) is not in them. Two runs of one config differ that way by 1-4 % in
some figures, so changes under --noise (5 %) get no verdict. Run BASE and NEW on the same
machine under the same load (at the same time, or one after the other), and bound what
matters with --fail-if.
"""

EPILOG = """\
inputs:
  TRACE             a trace file (dcuscope run --trace, dcuscope trace, GST_TRACERS=dcuscope)
  session:ID        a stored session of --db (one node: pick it with --node when it has several)
  run:ID            a stored run of --db (its id or the first 6+ characters of it)
                    (dcuscope sessions --db DB and dcuscope runs --db DB list them)

examples:
  dcuscope compare before.trace.jsonl after.trace.jsonl
  dcuscope compare --db dcuscope.db session:3 session:4 --node DCU-1
  dcuscope compare base.trace.jsonl new.trace.jsonl --markdown > comment.md
  dcuscope compare base.trace.jsonl new.trace.jsonl --fail-if "infer.p99 > +5%" --fail-if "e2e.p50 > +2ms"

--fail-if STAGE[.KIND].FIGURE OP VALUE: KIND delay (default), service or wait; FIGURE mean, p50,
p90 or p99; STAGE a stage name or e2e; OP > >= < <=; VALUE in %, ms, us or s. A bound fails only
when the whole interval of the change is past it. Exit status: 0 all bounds passed, 1 a bound
failed, 2 bad input; one line each on stderr.
"""


def add_compare_parser(sub) -> None:
    p = sub.add_parser("compare", help="did it get slower? compare runs, with confidence intervals and a CI gate",
                       description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="BASE, then one or more NEW: trace files, session:ID, run:ID")
    p.add_argument("--db", metavar="PATH|URL", help="the relay's store for session:ID and run:ID inputs (SQLite file or "
                                                   "postgresql://...)")
    p.add_argument("--node", metavar="NAME", help="the node to compare, in inputs that hold several")
    out = p.add_mutually_exclusive_group()
    out.add_argument("--json", action="store_true", help="print the comparison as one JSON object")
    out.add_argument("--markdown", action="store_true", help="print a Markdown table (for a pull-request comment)")
    p.add_argument("--fail-if", action="append", metavar="BOUND",
                   help="fail (exit 1) when a change is surely past BOUND, e.g. \"infer.p99 > +5%%\"; repeatable")
    p.add_argument("--noise", type=float, default=5.0, metavar="PCT",
                   help="changes smaller than PCT %% of BASE get no verdict however sure (default %(default)g: two runs "
                        "of one config differ by 1-4 %% in some figures, see above)")
    p.add_argument("--noise-ms", type=float, default=0.1, metavar="MS",
                   help="nor do changes smaller than MS ms (default %(default)g: a thread's wake-up differs by tens of "
                        "µs from run to run)")
    p.add_argument("--resamples", type=int, default=1000, metavar="N",
                   help="bootstrap resamples (default %(default)d; fewer is faster and the interval's ends noisier)")
    p.add_argument("--seed", type=int, default=0, help="the resampling's random seed (default 0: repeatable output)")
    p.set_defaults(func=run_compare)


def run_compare(args: argparse.Namespace) -> int:
    from dcuscope.commands.compareformat import format_markdown, format_table
    from dcuscope.gate import check, parse_bound
    from dcuscope.model.compare import compare

    try:
        bounds = [parse_bound(text) for text in args.fail_if or ()]
        if len(args.inputs) < 2:
            raise DcuscopeError("compare: give BASE and at least one NEW input")
        if not 10 <= args.resamples <= 100_000:
            raise DcuscopeError("compare: --resamples must be between 10 and 100000")
        if not 0 <= args.noise < 100 or not 0 <= args.noise_ms < 1e6:
            raise DcuscopeError("compare: --noise must be a percentage from 0 to 100, --noise-ms at least 0")
        inputs = _load_inputs(args)
        doc = compare(inputs, resamples=args.resamples, seed=args.seed, noise_pct=args.noise,
                      noise_ms=args.noise_ms, progress=_progress())
        outcomes = [o for b in bounds for o in check(doc, b)]
    except DcuscopeError as exc:
        print(f"dcuscope: error: {exc}", file=sys.stderr)
        return 2
    doc["gate"] = [{"bound": o.bound.text, "input": o.input, "failed": o.failed, "reason": o.reason} for o in outcomes]
    text = json.dumps(doc, indent=2) + "\n" if args.json else format_markdown(doc) if args.markdown else format_table(doc)
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except BrokenPipeError:
        pass
    for o in outcomes:
        print(f"dcuscope: gate {o.reason}", file=sys.stderr)
    return 1 if any(o.failed for o in outcomes) else 0


def _progress():
    """Progress on stderr while series are resampled, when a person watches it."""
    if not sys.stderr.isatty():
        return None

    def say(done: int, total: int) -> None:
        print(f"\rcompare: resampling {done}/{total} series", end="" if done < total else "\n",
              file=sys.stderr, flush=True)
    return say


def _load_inputs(args: argparse.Namespace) -> list:
    from dcuscope.model.compare import Input, distinct_labels
    from dcuscope.model.delays import frame_delays
    from dcuscope.model.frametable import frame_table

    out: list[Input] = []
    for text in args.inputs:
        header, events, label, origin, run = _pick_node(text, _read(text, args.db), args.node)
        fd = frame_delays(frame_table(header, events))
        if not fd.chains.complete.any():
            raise DcuscopeError(f"compare: {text}: no complete frame of node {header.node} (did the run carry frames "
                                "through every stage?)")
        journeys = _journeys(args.db, run) if run else {}
        out.append(Input(label=label, origin=origin, node=header.node, fd=fd, kinds=header.kinds, journeys=journeys))
    for i, label in zip(out, distinct_labels([i.label for i in out])):
        i.label = label
    return out


def _journeys(db: str, run: str) -> dict:
    """The rows across nodes of a stored run (:attr:`dcuscope.model.compare.Input.journeys`): its session's
    runs joined on the relay's clock."""
    import numpy as np

    from dcuscope.relay.store.runs import find_runs

    (_, session), = find_runs(db, run)
    runs, names, joined = _joined_session(db, session)
    me = names[runs.index(run)]
    rows = {}
    for name, hop in joined.hops.items():
        if me in (hop.sender, hop.receiver):
            order = np.argsort(hop.sent_ns, kind="stable")
            rows[name] = np.asarray(hop.delays_ns, np.float64)[order] / 1e6
    for j in joined.journeys:
        if j.nodes[-1] == me:
            rows.setdefault("journey " + " → ".join(j.nodes), []).append(j.total_ns / 1e6)
    return {name: np.asarray(v, np.float64) for name, v in rows.items()}


@functools.lru_cache(maxsize=4)
def _joined_session(db: str, session: int) -> tuple[list[str], list[str], object]:
    """A stored session's run ids, their names and its join, once per session however many inputs name it."""
    from dcuscope.model.journeys import join
    from dcuscope.model.names import unique_names
    from dcuscope.relay.store.runs import load_runs

    runs = load_runs(db, session)
    names = unique_names(r.header.node for r in runs)
    return [r.run for r in runs], names, join(runs, names)


def _read(text: str, db: str | None) -> list[tuple]:
    """[(header, events, label, origin, run id)] of one input: one per run it holds. The label names the
    input shortly (a file's name; a stored run as the page names it), the origin says the rest once."""
    if text.startswith(("session:", "run:")):
        kind, _, key = text.partition(":")
        if db is None:
            raise DcuscopeError(f"compare: {text} is stored: give --db PATH|URL of the relay's store")
        if kind == "session" and not key.isdigit():
            raise DcuscopeError(f"compare: {text}: a session id is a number (dcuscope sessions --db DB lists them)")
        if kind == "run" and (len(key) < 6 or any(c not in "0123456789abcdef" for c in key.lower())):
            raise DcuscopeError(f"compare: {text}: a run id is 6 or more hexadecimal digits")
        from dcuscope.relay.store.engines import is_url
        from dcuscope.relay.store.runs import find_runs, load_runs, run_label, session_nodes

        if not is_url(db) and not Path(db).is_file():
            raise DcuscopeError(f"compare: {db}: no such database")
        if kind == "run":  # by its whole id: a prefix of digits only would name a session
            found = find_runs(db, key.lower())
            if len(found) > 1:
                raise DcuscopeError(f"compare: {text} begins {len(found)} run ids "
                                    f"({', '.join(run[:8] for run, _ in found)}): give more digits")
            key = found[0][0] if found else key
        runs = load_runs(db, key, corrected=False)
        if kind == "session" and any(r.session != int(key) for r in runs):
            raise DcuscopeError(f"compare: {db} has no session {key}")
        nodes = [r.header.node for r in runs] if kind == "session" else session_nodes(db, runs[0].session)
        out = []
        for r in runs:
            twins = nodes.count(r.header.node) > 1
            out.append((r.header, r.events, run_label(r.session, r.header.node, r.run, twins),
                        str(db) if twins else f"{db}, run {r.run[:8]}", r.run))
        return out
    from dcuscope.probes.trace.tracefile import read_trace

    if not Path(text).exists() and text.isdigit():
        raise DcuscopeError(f"compare: {text}: no such file (a stored session is session:{text} with --db)")
    trace = read_trace(text)
    name = Path(text).name
    return [(trace.header, trace.events, name.removesuffix(".jsonl").removesuffix(".trace") or name,
             f"{text}, node {trace.header.node}" + ("" if trace.complete else " (no end line)"), "")]


def _pick_node(text: str, candidates: list[tuple], node: str | None) -> tuple:
    if node is not None:
        chosen = [c for c in candidates if c[0].node == node]
        if not chosen:
            raise DcuscopeError(f"compare: {text} has no node {node!r} (it has {_nodes(candidates)})")
        if len(chosen) > 1:
            raise DcuscopeError(f"compare: {text} has {len(chosen)} runs of node {node!r}: name one as "
                                f"{' or '.join('run:' + c[4][:8] for c in chosen)}")
        return chosen[0]
    if len(candidates) > 1:
        raise DcuscopeError(f"compare: {text} holds the nodes {_nodes(candidates)}: pick one with --node NAME")
    return candidates[0]


def _nodes(candidates: list[tuple]) -> str:
    return ", ".join(sorted({c[0].node for c in candidates}))
