"""What one push of a run costs the relay once the run's clock history is full, in-process: the
frames a push carries, clock-corrected (``RelayState.frames_columns``, as ``Ticker.push_frames``
builds them), and the run's statistics with their clock entry (``RelayState.stats``, as the stats
pushes ask).

A paced run's node reports its clock every 2 s and the relay keeps an estimate per report, at most
one every 1.5 s and 256 in all (``relay.clock.model.MAX_HISTORY``): a run older than ~9 minutes
holds a full history, which every timestamp the relay shows is corrected by. Here each of
``--runs`` runs gets ``--reports`` reports of a clock 3 ms ahead drifting 10 ppm, and 10 s of
paced frames; then each push is timed with nothing new between them, as a page showing a run of a
steady node sees them at 30 pushes a second.

Side by side with other checkouts (``--checkout DIR``, alternating ``--rounds`` times), since these
machines are shared and noisy.

    .venv/bin/python benchmarks/bench_push_clock.py --checkout ../old
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

T0 = 1_790_000_000_000_000_000
S = 1_000_000_000
SOURCES, FPS = 2, 179.0
"""The paper's pace: 4,300 events/s a DCU."""


def measure(runs: int, reports: int, pushes: int) -> dict:
    """The pushes on the checkout first on ``sys.path``."""
    import numpy as np

    from dcuscope.probes.ship.simnode import header_for, synth_events
    from dcuscope.relay.live.run import LiveRun
    from dcuscope.relay.live.seqset import SeqSet
    from dcuscope.relay.live.state import RelayState, RunState
    from dcuscope.relay.store.writer import Storage

    with tempfile.TemporaryDirectory() as tmp:
        state = RelayState(Storage(Path(tmp) / "r.db"), "estimate")
        held = []
        for r in range(runs):
            header = header_for(f"DCU-{r + 1}", SOURCES, T0)
            rs = RunState(run=f"run-{r}", node=f"DCU-{r + 1}", session=1, header=header, live=LiveRun(header), seqs=SeqSet())
            for k in range(reports):  # a clock 3 ms ahead, 10 ppm fast, read through 100 µs each way
                tau = k * 2 * S
                node = lambda t: int(T0 + t + 3_000_000 + 1e-5 * t)  # noqa: E731
                t2 = T0 + tau + 100_000
                rs.clock.add(node(tau), t2, t2 + 5_000, node(tau + 205_000))
            events = synth_events(int(FPS * 10), SOURCES, FPS, T0 + reports * 2 * S - 10 * S, seed=r)
            for i in range(0, len(events), 180):
                rs.live.add(events[i:i + 180])
            rs.live.maintain()
            state.runs[rs.run] = rs
            held.append(rs)
        since = [max(0, rs.live.visible - 25) for rs in held]
        out = {"history": len(held[0].clock.history)}
        for name, push in (("frames_us", lambda k, rs: state.frames_columns(rs, since[k], 25)),
                           ("stats_us", lambda k, rs: state.stats(rs, fresh=False))):
            took = []
            for _ in range(pushes):
                began = time.process_time()
                for k, rs in enumerate(held):
                    push(k, rs)
                took.append((time.process_time() - began) / runs)
            out[name] = 1e6 * float(np.median(took))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--runs", type=int, default=8, help="paced DCUs (default 8)")
    p.add_argument("--reports", type=int, default=300, help="clock reports per run, 2 s apart (default 300: a full history)")
    p.add_argument("--pushes", type=int, default=200, help="pushes of every run timed (default 200)")
    p.add_argument("--checkout", action="append", type=Path, default=[], help="another checkout beside this one (repeatable)")
    p.add_argument("--rounds", type=int, default=2, help="times each checkout runs, in turn (default 2)")
    p.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.inner:
        print(json.dumps(measure(args.runs, args.reports, args.pushes)))
        return 0
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # not in --inner: another checkout's code runs there
    from benchmarks.checkouts import alternate, checkouts as found

    checkouts = found(p, args.checkout, "relay/live/state.py")
    results = alternate(__file__, ["--runs", str(args.runs), "--reports", str(args.reports), "--pushes", str(args.pushes)],
                        checkouts, args.rounds)
    print(f"{args.runs} runs, {args.reports} clock reports each, {args.pushes} pushes timed, {args.rounds} rounds; "
          "µs per run and push (each round's median)")
    for k, (c, got) in enumerate(zip(checkouts, results)):
        frames = ", ".join(f"{x['frames_us']:.0f}" for x in got)
        stats = ", ".join(f"{x['stats_us']:.0f}" for x in got)
        print(f"{'this checkout' if k == 0 else str(c)}: clock history {got[-1]['history']} estimates; "
              f"frames pushed {frames}; statistics pushed {stats}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
