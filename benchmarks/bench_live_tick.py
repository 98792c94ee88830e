"""The live engine's cost per push tick, in-process: N runs at the paper's pace (4,300 events/s each,
in batches of ~180 events), a tick every 1/HZ s of node time that merges each run's batches, shows
its complete frames and builds their pushed columns (clock-corrected), as the relay's pusher does
for a page showing every DCU (all runs' frames judged together where the checkout's pusher does so,
``relay.live.run.maintain_all``). No network, no store: the part of a relay's CPU that grows with
pushes, measured by process CPU time. Then what the statistics a stats push asks for cost a run
(``window_stats``, ``run_stats``) at the end, and the bytes the engine holds a run.

Side by side with other checkouts (``--checkout DIR``: this script run there, alternating
``--rounds`` times), since these machines are shared and noisy.

    .venv/bin/python benchmarks/bench_live_tick.py --runs 8 --seconds 8 --checkout ../old
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

RATE = 4300.0
SOURCES = 2
BATCH = 180
"""Events a batch (a paced DCU's adaptive batches at the relay, docs/benchmarks-log.md, issue 31)."""
T0 = 1_700_000_000_000_000_000


def measure(runs: int, seconds: float, hz: float) -> dict:
    """The tick loop on the checkout first on ``sys.path``."""
    import numpy as np

    from dcuscope.probes.ship.simnode import EVENTS_PER_FRAME, header_for, synth_events
    from dcuscope.relay.clock.correction import Correction, Segment
    from dcuscope.relay.live import framepack
    from dcuscope.relay.live import run as live_run
    from dcuscope.relay.live.run import LiveRun

    fps = RATE / (EVENTS_PER_FRAME * SOURCES)
    corr = Correction("estimate", "bench", (Segment(from_ns=0, ref_ns=T0, offset_ns=1000, drift_ppb=20, uncertainty_ns=20000),))
    live, events = [], []
    for r in range(runs):
        live.append(LiveRun(header_for(f"DCU-{r + 1}", SOURCES, T0), budget=64 << 20))
        events.append(synth_events(int(fps * (seconds + 2)), SOURCES, fps, T0 + r * 1_000_000, seed=r))
    t = T0 + 1_000_000_000  # a second of warm-up: the open table and the rings fill
    at = []
    for run, ev in zip(live, events):
        j = int(np.searchsorted(ev["ts"], t))
        run.add(ev[:j])
        run.maintain()
        at.append(j)
    pushed = [run.visible for run in live]

    def push(k: int, run: LiveRun) -> None:
        if hasattr(run, "recent_columns"):
            framepack.corrected(*run.recent_columns(pushed[k], 300), corr, len(run.stages))
        else:  # before the engine kept its pushed columns
            framepack.columns(*run.recent(pushed[k], 300, True), corr)
        pushed[k] = run.visible

    together = getattr(live_run, "maintain_all", None)  # as the pusher pairs (one pass per graph since it exists)
    step, end, total, ticks = int(1e9 / hz), t + int(seconds * 1e9), 0, 0
    cpu = time.process_time()
    while t < end:
        t += step
        ticks += 1
        for k, (run, ev) in enumerate(zip(live, events)):
            j = int(np.searchsorted(ev["ts"], t))
            for i in range(at[k], j, BATCH):
                run.add(ev[i:min(i + BATCH, j)])
            total += j - at[k]
            at[k] = j
        if together is not None:
            together(live)
        for k, run in enumerate(live):
            run.maintain()
            if run.visible > pushed[k]:
                push(k, run)
    cpu = time.process_time() - cpu
    # What a stats push costs a run at the end (the window full once --seconds is past its 10 s), and what it holds.
    stats_ms = {}
    for name in ("window_stats", "run_stats"):
        took = []
        for run in live:
            for _ in range(10):
                began = time.process_time()
                getattr(run, name)()
                took.append(time.process_time() - began)
        stats_ms[name] = 1e3 * float(np.median(took))
    return {"events": total, "cpu_s": cpu, "run_ticks": runs * ticks, "frames": sum(run.visible for run in live),
            "stats_ms": stats_ms, "run_mb": sum(run.nbytes for run in live) / runs / 2**20}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--runs", type=int, default=8, help="paced DCUs (default 8)")
    p.add_argument("--seconds", type=float, default=8.0, help="node time ticked through (default 8)")
    p.add_argument("--hz", type=float, default=30.0, help="push ticks a second (the relay's --push-hz; default 30)")
    p.add_argument("--checkout", action="append", type=Path, default=[], help="another checkout beside this one (repeatable)")
    p.add_argument("--rounds", type=int, default=2, help="times each checkout runs, in turn (default 2)")
    p.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.inner:
        print(json.dumps(measure(args.runs, args.seconds, args.hz)))
        return 0
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # not in --inner: another checkout's code runs there
    from benchmarks.checkouts import alternate, checkouts as found

    checkouts = found(p, args.checkout, "relay/live/run.py")
    results = alternate(__file__, ["--runs", str(args.runs), "--seconds", str(args.seconds), "--hz", str(args.hz)],
                        checkouts, args.rounds)
    base = None
    print(f"{args.runs} paced runs, {args.hz:g} ticks/s, {args.seconds:g} s of node time, {args.rounds} rounds")
    for k, (c, r) in enumerate(zip(checkouts, results)):
        cpu, events, ticks = sum(x["cpu_s"] for x in r), sum(x["events"] for x in r), sum(x["run_ticks"] for x in r)
        per_event = 1e6 * cpu / events
        base = base or per_event
        print(f"{'this checkout' if k == 0 else str(c)}: {per_event:.2f} µs per event, {1e6 * cpu / ticks:.0f} µs per run "
              f"and tick, {r[-1]['frames']:,} frames shown ({per_event / base:.2f}× this checkout)")
        window, whole = (sorted(x["stats_ms"][name] for x in r) for name in ("window_stats", "run_stats"))
        print(f"  statistics of a run at the end, ms (each round's median): window {', '.join(f'{v:.2f}' for v in window)}; "
              f"whole run {', '.join(f'{v:.2f}' for v in whole)}; the engine holds {r[-1]['run_mb']:.1f} MB a run")
    return 0


if __name__ == "__main__":
    sys.exit(main())
