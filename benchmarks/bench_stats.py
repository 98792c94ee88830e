"""Throughput of the analysis side: node_stats, trace file write/read, exports, in events/s.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_stats.py [--events 1000000] [--sources 4]

Events come from the synthetic 4-source run of the tests (12 events per frame: origin, enter
and exit at mux, infer, tiler, convert, osd, enter at the sink), shuffled.
"""

from __future__ import annotations

import argparse
import io
import json
import tempfile
import time
from pathlib import Path

from probes.delays import node_stats
from probes.export import perfetto_document, write_csv
from probes.tracefile import read_trace, write_trace
from tests.probes.synth import pipeline_run

EVENTS_PER_FRAME = 12


def timed(label: str, n_events: int, fn, repeat: int = 1):
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t)
    print(f"{label:<28} {best * 1e3:9.1f} ms  {n_events / best / 1e6:7.2f} M events/s")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--sources", type=int, default=4)
    parser.add_argument("--export-events", type=int, default=100_000, help="events for the (slower) exports")
    args = parser.parse_args()

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
