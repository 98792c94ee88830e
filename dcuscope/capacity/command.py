"""``dcuscope capacity CONFIG``: how many streams fit on this machine, within bounds, with what
confidence, and what runs out first.

Exit status: 0 an answer (the capacity, possibly 0), 1 not final (the count after the capacity
undecided, the capacity unknown, or a run that failed), 2 bad input (one line), 130 Ctrl-C (after
the report of what was measured).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

from dcuscope.core.errors import UsageError
from dcuscope.extras import require_pipeline

DESCRIPTION = """\
How many cameras can this machine take? Runs the pipeline of CONFIG at 1, 2, 3, ... streams, each
count in its own process for --duration seconds with probes on, and stops at the first count
that does not keep every bound, or at --max-streams.

Each count: the config's sources replicated in turn (stream i plays source i mod their number),
files played in real time like cameras (--rtsp: served as live RTSP streams), the mux's batch size
set to the stream count (unless --keep-batch), a tiler grid widened if it has too few tiles. The
first --warmup seconds of frames are left out.

Per count it reports frames/s per stream, the frame delay (A = S/n, p50, p95, p99) with 95 %
intervals from the block bootstrap that dcuscope compare uses, each stage's delay = service + wait
and utilization, the limiting stage, and the frames dropped. A bound holds at a count when its
whole interval is inside it, fails when the whole interval is outside, and is undecided when the
interval straddles it: then the answer says run longer, not a guess.

The bounds: the slowest stream keeps --fps-floor % of its source's rate (always), and each --slo.
The runs at 1 and 2 streams also predict the capacity (each streaming thread's utilization grows
about linearly with the streams; the first to reach 100 % saturates): --predict runs those two
only; a full search prints the prediction beside the measurement.
"""

EPILOG = """\
examples:
  dcuscope capacity vtest --max-streams 6
  dcuscope capacity configs/quad.yaml --slo "e2e.p99 <= 200ms" --slo "infer.mean <= 60ms" --plot capacity.png
  dcuscope capacity vtest --predict
  dcuscope capacity my.yaml --rtsp --duration 40 --markdown -o capacity.md

--slo STAGE[.KIND].FIGURE OP VALUE, as dcuscope compare's --fail-if but absolute: STAGE a stage name
or e2e (the frame delay); KIND delay (default), service or wait; FIGURE mean, p50, p90, p95 or p99;
OP <= < >= >; VALUE in ms, us or s.

exit status: 0 answered; 1 not final (the count after the capacity undecided, the capacity unknown,
or a run failed); 2 bad input; 130 Ctrl-C or SIGTERM (after printing what was measured).
"""

DEFAULT_MAX_STREAMS = 8
DEFAULT_DURATION = 20.0
DEFAULT_WARMUP = 5.0
DEFAULT_FLOOR_PCT = 90.0


def add_capacity_parser(sub) -> None:
    p = sub.add_parser("capacity", help="how many streams fit: run the pipeline at 1, 2, ... streams against latency "
                                        "bounds, with confidence intervals and a prediction",
                       description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("config", type=Path, metavar="CONFIG", help="a pipeline configuration (a file, or a shipped one's "
                                                               "name: dcuscope configs)")
    p.add_argument("--max-streams", type=int, default=DEFAULT_MAX_STREAMS, metavar="N",
                   help="the highest count tried (default %(default)d)")
    p.add_argument("--slo", action="append", metavar="BOUND",
                   help="a bound every count must keep, e.g. \"e2e.p99 <= 200ms\" (repeatable; see below)")
    p.add_argument("--fps-floor", type=float, default=DEFAULT_FLOOR_PCT, metavar="PCT",
                   help="the %% of its source's frame rate the slowest stream must keep (default %(default)g)")
    p.add_argument("--duration", type=float, default=DEFAULT_DURATION, metavar="S",
                   help="seconds per count from its first frame (default %(default)g); longer runs give "
                        "narrower intervals")
    p.add_argument("--warmup", type=float, default=DEFAULT_WARMUP, metavar="S",
                   help="seconds of frames left out at the start of each count (default %(default)g)")
    p.add_argument("--keep-batch", action="store_true", help="keep the mux's batch-size (default: the stream count)")
    p.add_argument("--rtsp", action="store_true",
                   help="serve the file sources as live RTSP streams on loopback (dcuscope serve-rtsp, on this "
                        "machine: its CPU is reported) instead of playing the files")
    p.add_argument("--all-streams", action="store_true",
                   help="go on to --max-streams past the first count that does not pass (every count's figures, as "
                        "the paper's tables; the capacity is still the last count of the passing run from 1)")
    p.add_argument("--rtsp-bitrate", type=int, default=4000, metavar="KBPS",
                   help="--rtsp: the H.264 bitrate the streams are served at (default %(default)d kbit/s)")
    p.add_argument("--predict", action="store_true", help="run 1 and 2 streams only, and predict the capacity from them")
    out = p.add_mutually_exclusive_group()
    out.add_argument("--json", action="store_true", help="print the whole report as one JSON object")
    out.add_argument("--markdown", action="store_true", help="print the report as Markdown")
    p.add_argument("-o", "--output", type=Path, metavar="REPORT",
                   help="also write the report here (.json: JSON, .md: Markdown, else the table); written after "
                        "every count, so that an interrupted search keeps what it measured")
    p.add_argument("--plot", type=Path, metavar="FILE",
                   help="draw the per-stage delays stacked against the stream count, with frames/s per stream "
                        "(PNG, SVG or PDF by the suffix; needs matplotlib: pip install 'dcuscope[plot]')")
    p.add_argument("--keep-traces", type=Path, metavar="DIR",
                   help="keep each count's trace here (streams-N.trace.jsonl: dcuscope stats, compare, export)")
    p.set_defaults(func=run_capacity)


def _checked(args: argparse.Namespace):
    """The plan of the search, or a UsageError / ConfigError (exit 2) before anything runs."""
    from dcuscope.capacity.plan import check_replicable
    from dcuscope.capacity.search import Plan
    from dcuscope.capacity.verdict import parse_slo
    from dcuscope.pipeline.config import load_config
    from dcuscope.shipped import resolve

    slos = [parse_slo(text) for text in args.slo or ()]
    if args.max_streams < 1:
        raise UsageError("--max-streams must be at least 1")
    if not 0 < args.fps_floor <= 100:
        raise UsageError("--fps-floor is a percentage of the source's rate: more than 0, at most 100")
    if args.duration <= 0 or args.warmup < 0 or args.warmup >= args.duration:
        raise UsageError(f"--warmup ({args.warmup:g} s) must leave part of --duration ({args.duration:g} s) to measure")
    if args.rtsp_bitrate < 1:
        raise UsageError("--rtsp-bitrate must be at least 1 kbit/s")
    if args.predict and args.max_streams < 2:
        raise UsageError("--predict runs 1 and 2 streams: --max-streams must be at least 2")
    if args.plot is not None:
        from dcuscope.capacity.plot import check_plot

        check_plot(args.plot)
    file = resolve(args.config)
    config = load_config(file)
    check_replicable(config, args.rtsp)
    return Plan(config_file=file, config=config, max_streams=args.max_streams, slos=slos,
                fps_floor=args.fps_floor / 100, duration=args.duration, warmup=args.warmup,
                keep_batch=args.keep_batch, rtsp=args.rtsp, rtsp_bitrate=args.rtsp_bitrate,
                counts=[1, 2] if args.predict else list(range(1, args.max_streams + 1)),
                past_failure=args.predict or args.all_streams)


def run_capacity(args: argparse.Namespace) -> int:
    require_pipeline("capacity")
    from dcuscope.capacity.predict import describe, predict
    from dcuscope.capacity.report import render
    from dcuscope.capacity.search import search, stop_on_signals
    from dcuscope.capacity.verdict import FAILS, HOLDS, answer

    plan = _checked(args)
    started = time.monotonic()

    def say(line: str) -> None:
        print(f"capacity [{time.monotonic() - started:4.0f} s] {line}", file=sys.stderr, flush=True)

    doc = {"plan": {"config": str(args.config), "duration_s": plan.duration, "warmup_s": plan.warmup,
                    "max_streams": plan.max_streams, "fps_floor_pct": args.fps_floor, "keep_batch": plan.keep_batch,
                    "rtsp": plan.rtsp, "all_streams": args.all_streams, "predict_only": args.predict,
                    "date": time.strftime("%Y-%m-%d %H:%M %Z")},
           "bounds": [f"fps ≥ {args.fps_floor:g} % of the source's rate"] + [s.short() for s in plan.slos],
           "slos": [asdict(s) for s in plan.slos],
           "counts": [], "prediction": None, "capacity": None, "answer": None, "notes": _notes(plan)}

    def on_count(count: dict) -> None:
        doc["counts"].append(count)
        say(_count_line(count))
        ones = {c["streams"]: c for c in doc["counts"] if c.get("figures")}
        if 1 in ones and 2 in ones and doc["prediction"] is None:
            doc["prediction"] = predict(ones[1], ones[2], plan.slos)
            say(describe(doc["prediction"]))
        _write(args.output, doc)

    with tempfile.TemporaryDirectory(prefix="dcuscope-capacity-") as tmp, stop_on_signals():
        plan.workdir = args.keep_traces or Path(tmp)
        plan.workdir.mkdir(parents=True, exist_ok=True)
        counts, stopped = search(plan, say, on_count)
    undecided = False
    if args.predict:
        doc["answer"] = describe(doc["prediction"]) if doc["prediction"] else "no prediction: " + (
            stopped or "the runs at 1 and 2 streams did not both give figures")
    else:
        doc["capacity"], doc["answer"] = answer(doc["counts"], plan.max_streams, stopped)
        decisive = counts[:doc["capacity"] + 1] if doc["capacity"] is not None else counts
        undecided = doc["capacity"] is None or any(c["outcome"] not in (HOLDS, FAILS) or c["error"] for c in decisive)
    _write(args.output, doc)
    if args.plot is not None and doc["counts"]:
        from dcuscope.capacity.plot import draw

        draw(doc, args.plot)
        say(f"plot: {args.plot}")
    text = json.dumps(doc, indent=1) + "\n" if args.json else render(doc, markdown=args.markdown)
    sys.stdout.write(text)
    sys.stdout.flush()
    if stopped:
        return 130
    return 1 if undecided or (args.predict and not doc["prediction"]) else 0


def _notes(plan) -> list[str]:
    from dcuscope.capacity.plan import adjusted

    notes = []
    changed = adjusted(plan.config, plan.max_streams, plan.keep_batch)
    if changed.batch_size:
        notes.append("the mux's batch-size is the stream count at each count (--keep-batch keeps the config's)")
    if changed.tiler_grid:
        notes.append("the tiler's grid is widened at counts it has too few tiles for")
    if plan.rtsp:
        notes.append("--rtsp: serve-rtsp decodes and re-encodes every stream on this machine: its CPU shares the "
                     "cores with the pipeline's")
    return notes


def _count_line(c: dict) -> str:
    streams = f"{c['streams']} stream{'s' if c['streams'] != 1 else ''}"
    if not c.get("figures"):
        return f"{streams}: {c['outcome']}: {c['error']}"
    f = c["figures"]
    a = f["e2e"].get("mean")
    checks = "; ".join(f"{ch['what']}: {ch['outcome']} ({ch['detail']})" for ch in c["checks"])
    neck = c["limiting"]
    limit = f", limiting {neck['stage']}" + (f" {neck['utilization']:.0%}" if neck and neck["utilization"] is not None
                                               else "") if neck else ""
    return (f"{streams}: {c['outcome'].upper()}: A {a['value']:.1f} ms" if a else f"{streams}: {c['outcome'].upper()}") + f"{limit}; {checks}" + (
            f"; {c['error']}" if c["error"] else "")


def _write(path: Path | None, doc: dict) -> None:
    if path is None:
        return
    from dcuscope.capacity.report import render

    text = json.dumps(doc, indent=1) + "\n" if path.suffix == ".json" else render(doc, markdown=path.suffix == ".md")
    part = path.with_name(path.name + ".part")
    part.write_text(text)
    part.replace(path)
