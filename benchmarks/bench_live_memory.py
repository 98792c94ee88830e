"""Relay memory over a long run: one node's live engine fed hours of the paper's load.

Feeds ``relay.live.run.LiveRun`` synthetic events of one DCU (6 sources x 60 fps, 12 events a
frame) in 1-second batches, as the relay's tick does, and prints, every ``--every`` simulated
minutes, the bytes of numpy arrays the engine holds, the cost of its whole-run
statistics, and whether their percentiles are still exact. Side by side: the same feed with
the exact limit raised past the run (every value kept, as before the bounded series), so the
ratio of the two heaps is measured in one run.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_live_memory.py [--minutes 30] [--every 5] [--quick]

The last row is the end of the run, whether or not it falls on a multiple of ``--every``. A
figure it cannot produce is ``"n/a (reason)"`` in its JSON (benchmarks/figures.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import dumps, ratio  # noqa: E402
from dcuscope.probes.ship.simnode import header_for, synth_events  # noqa: E402
from dcuscope.relay.live.run import LiveConfig, LiveRun  # noqa: E402

SOURCES, FPS = 6, 60.0
T0 = 1_700_000_000_000_000_000


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=30.0, help="simulated minutes of one DCU")
    p.add_argument("--every", type=float, default=5.0, help="report every this many simulated minutes")
    p.add_argument("--quick", action="store_true", help="a smoke test: 20 simulated seconds, a row every 10")
    args = p.parse_args(argv)
    if args.quick:
        args.minutes, args.every = 20 / 60, 10 / 60
    seconds = int(args.minutes * 60)
    every_s = round(args.every * 60)
    if seconds < 1 or every_s < 1:
        p.error("--minutes and --every must each be at least one simulated second (1/60)")
    header = header_for("DCU-1", SOURCES)
    runs = {"bounded": LiveRun(header), "keep-all": LiveRun(header, LiveConfig(exact_values=1 << 40))}
    for second in range(seconds):
        events = synth_events(int(FPS), SOURCES, FPS, T0, seed=1, first_frame=second * int(FPS))
        for run in runs.values():
            run.add(events)
            run.maintain()
        if (second + 1) % every_s == 0 or second + 1 == seconds:
            row = {"minutes": round((second + 1) / 60, 1), "frames": (second + 1) * int(FPS) * SOURCES}
            held = {}
            for name, run in runs.items():
                t = time.perf_counter()
                stats = run.run_stats()
                held[name] = _held(run)
                row[name] = {"heap_mib": round(held[name] / 2**20, 1),
                             "stats_ms": round(1000 * (time.perf_counter() - t), 1),
                             "percentile_error": stats["percentile_error"]}
            row["heap_ratio_keep_all_vs_bounded"] = round(ratio(
                held["keep-all"], held["bounded"], "the bounded engine holds no array"), 2)
            print(dumps(row), flush=True)
    return 0


def _held(run: LiveRun) -> int:
    """Bytes of numpy arrays the engine holds (its buffers dominate its heap)."""
    seen, total, stack = set(), 0, [vars(run)]
    while stack:
        obj = stack.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if hasattr(obj, "nbytes") and hasattr(obj, "dtype"):
            total += obj.base.nbytes if getattr(obj, "base", None) is not None and hasattr(obj.base, "nbytes") else obj.nbytes
        elif isinstance(obj, dict):
            stack.extend(obj.values())
        elif isinstance(obj, (list, tuple)):
            stack.extend(obj)
        elif hasattr(obj, "__dict__") and not isinstance(obj, type):
            stack.append(vars(obj))
    return total


if __name__ == "__main__":
    raise SystemExit(main())
