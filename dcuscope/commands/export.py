"""``dcuscope export``: trace files or a stored session as Perfetto (Chrome Trace Event JSON) or CSV,
with each node's clock correction per node and per frame (:mod:`dcuscope.probes.trace.export`).

Returns the exit status: 0, or 2 after one ``dcuscope: error: ...`` line for a bad input.
"""

from __future__ import annotations

import argparse
import json
import math

from dcuscope.commands.traceinputs import add_input_arguments, clocks, open_output, read_inputs, user_errors
from dcuscope.core.errors import DcuscopeError
from dcuscope.probes.trace.export import BUCKET_NS, perfetto_document, write_csv


def add_export_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "export", help="convert trace files to Perfetto/Chrome trace JSON or CSV",
        description="perfetto: Chrome Trace Event JSON for ui.perfetto.dev or chrome://tracing "
                    "(a process per node, a track per stage and source, a slice per frame split "
                    "into its wait and service, flows following each frame, counters of each "
                    "stage's utilization and of the frames inside it; µs since the earliest "
                    "event). csv: one row per frame per stage.",
    )
    add_input_arguments(p)
    p.add_argument("--format", choices=("perfetto", "csv"), default="perfetto", help="output format (default perfetto)")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output file, - for stdout")
    p.add_argument("--bucket-ms", type=float, default=BUCKET_NS / 1e6, metavar="MS",
                   help=f"perfetto: width of the utilization counters' buckets (default {BUCKET_NS / 1e6:g})")
    p.set_defaults(func=run_export)
    return p


def run_export(args: argparse.Namespace) -> int:
    with user_errors() as failed:
        bucket_ns = _bucket_ns(args.bucket_ms)
        traces = read_inputs(args, "export")
        nodes, corrections = [(t.header, t.events) for t in traces], clocks(traces)
        with open_output(args.output) as out:
            if args.format == "csv":
                write_csv(out, nodes, corrections)
            else:
                json.dump(perfetto_document(nodes, bucket_ns, corrections), out, separators=(",", ":"), ensure_ascii=False)
                out.write("\n")
    return 2 if failed else 0


def _bucket_ns(ms: float) -> int:
    """--bucket-ms in whole ns; a bad value is the user's error."""
    ns = ms * 1e6
    if not math.isfinite(ns) or round(ns) < 1:
        raise DcuscopeError(f"export: --bucket-ms must be a positive number of milliseconds, got {ms:g}")
    return round(ns)
