"""Throughput of the analysis side: node_stats, trace file write/read, exports, in events/s.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_stats.py [--events 1000000] [--sources 4] [--quick]

Events come from the synthetic 4-source run of the tests (12 events per frame: origin, enter
and exit at mux, infer, tiler, convert, osd, enter at the sink), shuffled. A rate it cannot
give (a step too quick for the clock) is ``n/a (reason)`` (benchmarks/figures.py).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import fmt, ratio  # noqa: E402
from dcuscope.model.delays import node_stats  # noqa: E402
from dcuscope.probes.trace.export import perfetto_document, write_csv  # noqa: E402
from dcuscope.probes.trace.tracefile import read_trace, write_trace  # noqa: E402
from tests.probes.synth import pipeline_run  # noqa: E402

EVENTS_PER_FRAME = 12


def timed(label: str, n_events: int, fn, repeat: int = 1):
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t)
    rate = ratio(n_events, best, "too quick for the clock") / 1e6
    print(f"{label:<28} {best * 1e3:9.1f} ms  {fmt(rate, '7.2f', ' M events/s')}")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--sources", type=int, default=4)
    parser.add_argument("--export-events", type=int, default=100_000, help="events for the (slower) exports")
    parser.add_argument("--quick", action="store_true", help="a smoke test: 20,000 events, 2,000 for the exports")
    args = parser.parse_args()
    if args.quick:
        args.events, args.export_events = 20_000, 2_000
    if args.events < 1 or args.export_events < 1 or args.sources < 1:
        parser.error("--events, --export-events and --sources must be at least 1")

    frames = max(1, args.events // (EVENTS_PER_FRAME * args.sources))
    header, events, _ = pipeline_run(frames, n_sources=args.sources, period_ns=33_333_333, jitter_ns=5_000_000)
    n = len(events)
    print(f"{n} events, {frames * args.sources} frames, {args.sources} sources")
    st = timed("node_stats", n, lambda: node_stats(header, events), repeat=3)
    assert st["frames"]["complete"] == frames * args.sources

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.trace"
        timed("write_trace", n, lambda: write_trace(path, header, events))
        print(f"{'trace file size':<28} {path.stat().st_size / n:9.1f} bytes/event")
        timed("read_trace", n, lambda: read_trace(path))

    small_frames = max(1, args.export_events // (EVENTS_PER_FRAME * args.sources))
    h2, e2, _ = pipeline_run(small_frames, n_sources=args.sources, period_ns=33_333_333, jitter_ns=5_000_000)
    timed("export perfetto (to JSON)", len(e2), lambda: json.dumps(perfetto_document([(h2, e2)])))
    timed("export csv", len(e2), lambda: write_csv(io.StringIO(), [(h2, e2)]))


if __name__ == "__main__":
    main()
