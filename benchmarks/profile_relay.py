"""Where a relay's CPU goes at the paper's pace: py-spy samples of the relays fed by N paced
simulated DCUs, with a /ui client on the first relay showing every DCU (or none, ``--no-page``),
grouped by what the work is for, in µs of relay CPU per event and per batch. One relay on SQLite, or
``--relays R`` on a PostgreSQL of the benchmark's own with a Redis between them (the DCUs dealt
round-robin, as ``bench_relay.py`` does).

Several checkouts side by side (``--checkout DIR``, the relay started from each in turn, the same
nodes each time, alternating ``--rounds`` times): these machines are shared and noisy, so compare
only figures of one run. A category's share is of py-spy's samples; its µs are that share of the
relay's CPU measured by the kernel. py-spy counts some of a thread's waits as samples (an event
loop in ``select``, the store thread on its queue): those are left out.

    .venv/bin/python benchmarks/profile_relay.py --nodes 8 --seconds 20 --checkout ../old
    .venv/bin/python benchmarks/profile_relay.py --nodes 32 --relays 4 --store postgresql
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

from benchmarks.bench_relay import (EVENTS_PER_FRAME, LOOPBACK, SOURCES, Stores, _proc_cpu, _received,  # noqa: E402
                                    _watch_ui, start_nodes)
from benchmarks.figures import CannotRun  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RATE = 4300.0
CATEGORIES = (
    ("pairing (LiveRun.maintain, maintain_all)", ("LiveRun.maintain", "maintain_all")),
    ("push: frames built", ("frames_block", "columns_block")),
    ("fan-out: Redis publish and receive", ("FleetManager._publish", "AsyncPubSubManager._thread")),
    ("push: encoded and sent", ("AsyncNamespace.emit", "AsyncServer.emit", "AsyncManager.emit")),
    ("statistics pushed", ("Ticker._push_stats",)),
    ("fleet rows", ("Ticker._push_fleet",)),
    ("ingest: receive, decode, check, acknowledge", ("Ingest.handle", "Ingest._serve", "Ingest._store", "Ingest._commit",
                                                     "Ingest._send_acks")),
    ("store writer thread", ("Storage._write_batches", "Storage._run_call")),
    ("socket writes (pushes, acknowledgements)", ("_SelectorSocketTransport.write", "WebSocketWriter.send_frame",
                                                  "AsyncSocket._websocket_handler")),
    ("clock exchanges", ("ClockUdp.",)),
)
"""What a sample is for: the first category one of whose functions (a name, or the start of one) is on its stack."""
OTHER = "other"
WAITING = ("EpollSelector.select", "Storage._worker", "Storage._round")
"""A sample whose innermost function is one of these is a thread waiting (the event loop in
``select``, the store thread on its queue), which py-spy cannot always tell from work: not CPU."""


class Relay:
    """A relay started from ``checkout`` on ``db`` (an SQLite file or a PostgreSQL URL)."""

    workers = 1  # one process on a port of its own (bench_relay's ``_received`` asks it once)

    def __init__(self, checkout: Path, db: str, args: list[str]) -> None:
        env = dict(os.environ, PYTHONPATH=str(checkout))
        self.proc = subprocess.Popen([sys.executable, "-m", "dcuscope.relay", "--port", "0", "--db", db, *LOOPBACK, *args],
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


def categorise(raw: Path) -> tuple[collections.Counter, int, collections.Counter]:
    """Samples per category of a py-spy ``--format raw`` file (collapsed stacks), their total
    (waits left out, :data:`WAITING`), and samples per (category, place): the innermost dcuscope
    function on the stack, or the innermost function where none is."""
    counts: collections.Counter = collections.Counter()
    places: collections.Counter = collections.Counter()
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
        places[name, _place(stack.split(";"))] += int(n)
    return counts, total, places


def _place(stack: list[str]) -> str:
    """``function (file)`` of the innermost frame of dcuscope's own code, else of the innermost frame."""
    for frame in reversed(stack):
        where = frame.partition(" (")[2]
        if where and "site-packages" not in where and "/lib/python3" not in where and "<" not in where:
            break
    else:
        frame = stack[-1]
    func, _, where = frame.partition(" (")
    return f"{func} ({Path(where.split(':')[0]).name})" if where else func


def profile(checkout: Path, nodes: int, seconds: float, page: bool, spy: str, tmp: Path, stores: Stores, store: str,
            relays: int, warmup: float = 0.0) -> list[dict]:
    """One profile of ``relays`` relays of ``checkout`` on a fresh store, ``warmup`` seconds after the
    nodes are all in: each relay's figures."""
    db = stores.fresh(store)
    started: list[Relay] = []
    procs: list[subprocess.Popen] = []
    try:
        for _ in range(relays):
            started.append(Relay(checkout, db, stores.fanout(relays)))
        procs = start_nodes([r.url for r in started], nodes, int(RATE * (warmup + seconds + 60)), paced=True,
                            fps=RATE / (EVENTS_PER_FRAME * SOURCES))
        deadline = time.monotonic() + 120
        while len(_received(started)[0]) < nodes and time.monotonic() < deadline:
            time.sleep(0.5)
        time.sleep(1 + warmup)
        before = [_counters(r) for r in started]
        n0, w0 = sum(_proc_cpu(p.pid) for p in procs), time.monotonic()
        raws = [tmp / f"samples-{k}.txt" for k in range(relays)]
        samplers = [subprocess.Popen([spy, "record", "--pid", str(r.proc.pid), "--duration", str(round(seconds)), "--rate",
                                      "250", "--format", "raw", "--nonblocking", "-o", str(raw)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for r, raw in zip(started, raws)]
        if page:
            asyncio.run(_watch_ui(started[0].url, seconds))
        else:
            time.sleep(seconds)
        for sampler in samplers:
            sampler.wait(seconds + 60)
        after = [_counters(r) for r in started]
        wall, nodes_cpu = time.monotonic() - w0, sum(_proc_cpu(p.pid) for p in procs) - n0
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(30)
        for r in started:
            r.stop()
        stores.done(store, db)
    out = []
    for raw, b, a in zip(raws, before, after):
        if not raw.exists():
            raise SystemExit("profile_relay: py-spy wrote no samples (it needs ptrace: run as root or with CAP_SYS_PTRACE)")
        counts, total, places = categorise(raw)
        raw.unlink()
        out.append({"events": a[0] - b[0], "batches": a[1] - b[1], "cpu_s": a[2] - b[2], "wall_s": wall,
                    "nodes_cpu_s": nodes_cpu / relays,
                    "shares": {name: counts[name] / max(total, 1) for name, _ in (*CATEGORIES, (OTHER, ()))},
                    "places": {f"{c}\t{place}": n / max(total, 1) for (c, place), n in places.items()}})
    return out


def _counters(relay: Relay) -> tuple[float, float, float]:
    """Events and batches the relay took in, and its CPU seconds, so far."""
    return (relay.counter("dcuscope_relay_events"), relay.counter("dcuscope_relay_batches"), _proc_cpu(relay.proc.pid))


def report(label: str, runs: list[dict], together: int = 1, top: int = 0) -> list[str]:
    """The figures of ``runs`` (relays' profiles; ``together`` of them at a time: their walls overlap);
    with ``top``, under each category its ``top`` places (:func:`_place`) by µs per batch."""
    events = sum(r["events"] for r in runs)
    batches = sum(r["batches"] for r in runs)
    cpu = sum(r["cpu_s"] for r in runs)
    wall = sum(r["wall_s"] for r in runs) / together
    per_event, per_batch = 1e6 * cpu / max(events, 1), 1e6 * cpu / max(batches, 1)
    lines = [f"{label}: {events / wall:,.0f} events/s in {batches / wall:,.0f} batches/s ({events / max(batches, 1):.0f} events a "
             f"batch); relay CPU {100 * cpu / wall:.0f} %, nodes' CPU {100 * sum(r['nodes_cpu_s'] for r in runs) / wall:.0f} %; "
             f"{per_event:.2f} µs per event, {per_batch:,.0f} µs per batch",
             f"  {'what the relay does':<46} {'share':>6} {'µs/event':>9} {'µs/batch':>9}"]
    for name, _ in (*CATEGORIES, (OTHER, ())):
        share = sum(r["shares"][name] * r["cpu_s"] for r in runs) / max(cpu, 1e-9)
        lines.append(f"  {name:<46} {100 * share:5.0f}% {share * per_event:9.2f} {share * per_batch:9.0f}")
        if top:
            places: collections.Counter = collections.Counter()
            for r in runs:
                for key, sh in r["places"].items():
                    c, _, place = key.partition("\t")
                    if c == name:
                        places[place] += sh * r["cpu_s"] / max(cpu, 1e-9)
            for place, sh in places.most_common(top):
                lines.append(f"    {place[:70]:<70} {sh * per_event:6.2f} {sh * per_batch:9.0f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--nodes", type=int, default=8, help="paced simulated DCUs (4,300 events/s each; default 8)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of each profile (default 20)")
    p.add_argument("--warmup", type=float, default=0.0, metavar="S",
                   help="profile S seconds after the nodes are all in (default 0): a run's clock history, one estimate a "
                        "report, is full (256) after ~9 minutes, the steady state of a long-running fleet")
    p.add_argument("--no-page", action="store_true", help="no /ui client: the relays pair, store and serve no push")
    p.add_argument("--relays", type=int, default=1, help="relay processes sharing the store (default 1; more need "
                                                       "--store postgresql)")
    p.add_argument("--store", choices=("sqlite", "postgresql"), default="sqlite",
                   help="the relays' store (default sqlite; postgresql: a durable server of the benchmark's own)")
    p.add_argument("--checkout", action="append", type=Path, default=[],
                   help="another checkout to profile beside this one (repeatable), e.g. a `git worktree` of main")
    p.add_argument("--rounds", type=int, default=1, help="times each checkout is profiled, in turn (default 1)")
    p.add_argument("--top", type=int, default=0, metavar="N",
                   help="under each category, its N costliest places: the innermost dcuscope function on the stack "
                        "(µs per event and per batch)")
    args = p.parse_args(argv)
    spy = shutil.which("py-spy", path=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    if spy is None:
        p.error("py-spy not found: `make setup` installs it (a dev dependency), or `pip install py-spy`")
    if args.relays < 1 or (args.relays > 1 and args.store == "sqlite"):
        p.error("--relays: at least 1, and several only with --store postgresql (SQLite is one relay per file)")
    checkouts = [ROOT, *(c.resolve() for c in args.checkout)]
    for c in checkouts[1:]:
        if not (c / "relay" / "__main__.py").exists():
            p.error(f"--checkout {c}: not a dcuscope checkout (no relay/__main__.py)")
    results: list[list[list[dict]]] = [[] for _ in checkouts]  # checkout, round, relay
    with tempfile.TemporaryDirectory() as tmp:
        try:
            stores = Stores([args.store], Path(tmp), durable=True)
        except CannotRun as exc:
            sys.exit(f"profile_relay: {exc}")
        try:
            for k in range(args.rounds):
                for c, runs in zip(checkouts, results):
                    print(f"round {k + 1}/{args.rounds}: {c.name}, {args.relays} relay(s) on {args.store}, {args.nodes} DCUs, "
                          f"{args.seconds:g} s {'with no page' if args.no_page else 'with a page showing every DCU'}"
                          + (f", after {args.warmup:g} s of warm-up" if args.warmup else ""),
                          file=sys.stderr, flush=True)
                    runs.append(profile(c, args.nodes, args.seconds, not args.no_page, spy, Path(tmp), stores, args.store,
                                        args.relays, args.warmup))
        except CannotRun as exc:
            sys.exit(f"profile_relay: {exc}")
        finally:
            stores.close()
    for k, (c, runs) in enumerate(zip(checkouts, results)):
        label = "this checkout" if k == 0 else str(c)
        print("\n".join(report(f"{label}, all relays", [r for rnd in runs for r in rnd], args.relays, args.top)))
        if args.relays > 1:
            for i in range(args.relays):
                print("\n".join(report(f"{label}, relay {i + 1}{' (the page is on it)' if i == 0 and not args.no_page else ''}",
                                        [rnd[i] for rnd in runs])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
