"""Where a relay's CPU goes at the paper's pace: py-spy samples of one relay (SQLite) fed by N paced
simulated DCUs, with a /ui client showing every DCU (or none, ``--no-page``), grouped by what the work
is for, in µs of relay CPU per event and per batch.

Several checkouts side by side (``--checkout DIR``, the relay started from each in turn, the same
nodes each time, alternating ``--rounds`` times): these machines are shared and noisy, so compare
only figures of one run. A category's share is of py-spy's samples; its µs are that share of the
relay's CPU measured by the kernel. py-spy counts some of a thread's waits as samples (an event
loop in ``select``, the store thread on its queue): those are left out.

    .venv/bin/python benchmarks/profile_relay.py --nodes 8 --seconds 20 --checkout ../old
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_relay import (EVENTS_PER_FRAME, LOOPBACK, SOURCES, _proc_cpu, _received, _watch_ui,  # noqa: E402
                                    start_nodes)

ROOT = Path(__file__).resolve().parents[1]
RATE = 4300.0
CATEGORIES = (
    ("pairing (LiveRun.maintain)", ("LiveRun.maintain",)),
    ("push: frames built", ("frames_block", "columns_block")),
    ("push: encoded and sent", ("AsyncNamespace.emit", "AsyncServer.emit", "AsyncManager.emit")),
    ("statistics pushed", ("Ticker._push_stats",)),
    ("fleet rows", ("Ticker._push_fleet",)),
    ("ingest: receive, decode, check, acknowledge", ("Ingest.handle", "Ingest._serve", "Ingest._store", "Ingest._commit")),
    ("store writer thread", ("Storage._write_batches", "Storage._run_call")),
    ("socket writes (pushes, acknowledgements)", ("_SelectorSocketTransport.write", "WebSocketWriter.send_frame",
                                                  "AsyncSocket._websocket_handler")),
    ("clock exchanges", ("ClockUdp.",)),
)
"""What a sample is for: the first category one of whose functions (a name, or the start of one) is on its stack."""
OTHER = "other"
WAITING = ("EpollSelector.select", "Storage._worker")
"""A sample whose innermost function is one of these is a thread waiting (the event loop in
``select``, the store thread on its queue), which py-spy cannot always tell from work: not CPU."""


class Relay:
    """A relay started from ``checkout``, on a fresh SQLite file."""

    def __init__(self, checkout: Path, db: Path) -> None:
        env = dict(os.environ, PYTHONPATH=str(checkout))
        self.proc = subprocess.Popen([sys.executable, "-m", "relay", "--port", "0", "--db", str(db), *LOOPBACK],
                                     cwd=checkout, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        m = re.search(r"http://127\.0\.0\.1:(\d+)", self.proc.stdout.readline().decode())
        if not m:
            self.proc.kill()
            raise SystemExit(f"profile_relay: the relay of {checkout} did not start")
        self.url = f"http://127.0.0.1:{m.group(1)}"

    def get(self, path: str):
        with urllib.request.urlopen(self.url + path, timeout=30) as r:
            return json.loads(r.read())

    def counter(self, name: str) -> float:
        text = urllib.request.urlopen(self.url + "/metrics", timeout=30).read().decode()
        return float(re.search(rf"^{name}_total (\S+)", text, re.M).group(1))

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(30)


def categorise(raw: Path) -> tuple[collections.Counter, int]:
    """Samples per category of a py-spy ``--format raw`` file (collapsed stacks), and their total
    (waits left out, :data:`WAITING`)."""
    counts: collections.Counter = collections.Counter()
    total = 0
    for line in raw.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        if not n.isdigit():
            continue
        frames = [f.split(" (")[0] for f in stack.split(";")]
        if frames[-1] in WAITING:
            continue
        total += int(n)
        names = ";" + ";".join(frames)
        name = next((name for name, keys in CATEGORIES if any(";" + k in names for k in keys)), OTHER)
        counts[name] += int(n)
    return counts, total


def profile(checkout: Path, nodes: int, seconds: float, page: bool, spy: str, tmp: Path) -> dict:
    relay = Relay(checkout, tmp / f"{checkout.name}-{time.monotonic_ns()}.db")
    procs = start_nodes(relay.url, nodes, int(RATE * (seconds + 60)), paced=True, fps=RATE / (EVENTS_PER_FRAME * SOURCES))
    try:
        deadline = time.monotonic() + 120
        while len(_received([relay])[0]) < nodes and time.monotonic() < deadline:
            time.sleep(0.5)
        time.sleep(1)
        raw = tmp / "samples.txt"
        b0, e0, c0, w0 = relay.counter("dcuscope_relay_batches"), _received([relay])[1], _proc_cpu(relay.proc.pid), time.monotonic()
        n0 = sum(_proc_cpu(p.pid) for p in procs)
        sampler = subprocess.Popen([spy, "record", "--pid", str(relay.proc.pid), "--duration", str(round(seconds)), "--rate", "250",
                                    "--format", "raw", "--nonblocking", "-o", str(raw)],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if page:
            asyncio.run(_watch_ui(relay.url, seconds))
        else:
            time.sleep(seconds)
        sampler.wait(seconds + 60)
        b1, e1, c1, w1 = relay.counter("dcuscope_relay_batches"), _received([relay])[1], _proc_cpu(relay.proc.pid), time.monotonic()
        n1 = sum(_proc_cpu(p.pid) for p in procs)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(30)
        relay.stop()
    if not raw.exists():
        raise SystemExit("profile_relay: py-spy wrote no samples (it needs ptrace: run as root or with CAP_SYS_PTRACE)")
    counts, total = categorise(raw)
    events, batches, cpu = e1 - e0, b1 - b0, c1 - c0
    return {"events": events, "batches": batches, "cpu_s": cpu, "wall_s": w1 - w0, "nodes_cpu_s": n1 - n0,
            "shares": {name: counts[name] / max(total, 1) for name, _ in (*CATEGORIES, (OTHER, ()))}}


def report(label: str, runs: list[dict]) -> list[str]:
    events = sum(r["events"] for r in runs)
    batches = sum(r["batches"] for r in runs)
    cpu = sum(r["cpu_s"] for r in runs)
    wall = sum(r["wall_s"] for r in runs)
    per_event, per_batch = 1e6 * cpu / max(events, 1), 1e6 * cpu / max(batches, 1)
    lines = [f"{label}: {events / wall:,.0f} events/s in {batches / wall:,.0f} batches/s ({events / max(batches, 1):.0f} events a "
             f"batch); relay CPU {100 * cpu / wall:.0f} %, nodes' CPU {100 * sum(r['nodes_cpu_s'] for r in runs) / wall:.0f} %; "
             f"{per_event:.2f} µs per event, {per_batch:,.0f} µs per batch",
             f"  {'what the relay does':<46} {'share':>6} {'µs/event':>9} {'µs/batch':>9}"]
    for name, _ in (*CATEGORIES, (OTHER, ())):
        share = sum(r["shares"][name] * r["cpu_s"] for r in runs) / max(cpu, 1e-9)
        lines.append(f"  {name:<46} {100 * share:5.0f}% {share * per_event:9.2f} {share * per_batch:9.0f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--nodes", type=int, default=8, help="paced simulated DCUs (4,300 events/s each; default 8)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of each profile (default 20)")
    p.add_argument("--no-page", action="store_true", help="no /ui client: the relay pairs, stores and serves no push")
    p.add_argument("--checkout", action="append", type=Path, default=[],
                   help="another checkout to profile beside this one (repeatable), e.g. a `git worktree` of main")
    p.add_argument("--rounds", type=int, default=1, help="times each checkout is profiled, in turn (default 1)")
    args = p.parse_args(argv)
    spy = shutil.which("py-spy", path=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    if spy is None:
        p.error("py-spy not found: `make setup` installs it (a dev dependency), or `pip install py-spy`")
    checkouts = [ROOT, *(c.resolve() for c in args.checkout)]
    for c in checkouts[1:]:
        if not (c / "relay" / "__main__.py").exists():
            p.error(f"--checkout {c}: not a dcuscope checkout (no relay/__main__.py)")
    results: list[list[dict]] = [[] for _ in checkouts]
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.rounds):
            for c, runs in zip(checkouts, results):
                print(f"round {k + 1}/{args.rounds}: {c.name}, {args.nodes} DCUs, {args.seconds:g} s "
                      f"{'with no page' if args.no_page else 'with a page showing every DCU'}", file=sys.stderr, flush=True)
                runs.append(profile(c, args.nodes, args.seconds, not args.no_page, spy, Path(tmp)))
    for k, (c, runs) in enumerate(zip(checkouts, results)):
        print("\n".join(report("this checkout" if k == 0 else str(c), runs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
