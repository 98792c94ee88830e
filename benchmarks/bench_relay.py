"""Relay benchmark: sustained ingest (storage + live statistics) and UI-visible lag, per store and relay count.

For each store (``--store``: sqlite, postgresql), number of relay processes (``--relays``), node
count (``--nodes``, default 2, 8, 32) and settings (``--settings``, default both), on 127.0.0.1,
both phases one after the other:

1. throughput: R relay processes on a fresh store, N simulated node processes (``python -m
   probes.ship.simnode``) each shipping its share of ``--events`` as fast as the relays acknowledge;
   the rate is events committed to the store per second between 10 % and 90 % of the total
   (every one of them also went through the live pairing), counted from the store itself (the
   runs of ``/api/sessions``, which every relay on a shared store lists alike);
   ``events_per_batch``: the nodes' events written / batches cut;
2. lag: N nodes paced at ``--rate`` events/s each (the paper's DCU: ~4,300; simnode writes what
   came every 10 ms), a browser-side Socket.IO client on the first relay's ``/ui`` (with several
   relays it receives every relay's frames, through their Redis); lag = arrival of a ``frames``
   push - the timestamp of the frame's last event (its sink enter), ``nodes_seen``: the nodes
   whose frames came. The window opens once every node is listed by a relay with an event, or after
   120 s; ``not_streaming`` names those that were not (and stderr says so). The node stamps an event
   when it happens, so the lag includes the node's batching and the relay's push rate (the
   settings); ``push_transit`` is the part from the relay sending a push to the client handling it.
   The client shows every DCU (a page with all of them opened), or with ``--watch N`` DCU-1..DCU-N
   only (a page with N opened from the fleet overview: the relays then build and push those only);
   ``watched`` says which.

Settings (``--settings``), each combination run once with each, on adjacent rows of the table:
``today``, the settings before adaptive batching (nodes with ``--fixed-flush``: a batch every
50 ms; relays with ``--push-hz 10``), and ``adaptive``, the defaults (nodes ship at once while
their link is idle, at most one batch per ``min_flush_s``, probes/ship/relayexport.py; relays push a
DCU's frames as they complete, at most their default ``--push-hz`` times a second).

With several relays the nodes are dealt round-robin (node k to relay k mod R), each given the
whole list starting at its own relay (``--relay URL_k,URL_k+1,...``: the others are its failover,
as a fleet configures them), and the relays share a Redis server of the benchmark's own
(``--redis``, tests/redisserver.py), as a fleet runs them. With ``--workers`` the R relays are one
``python -m dcuscope.relay --workers R`` instead, the processes of one host sharing one port: every node is
given that one URL, and the kernel deals their connections among the workers. SQLite is one relay per file: a
combination of SQLite and more than one relay is not run, its figures are ``n/a (SQLite is one
relay per file)``. PostgreSQL is a server of the benchmark's own (benchmarks/stores.py), a fresh
database per phase, durable as users run it (fsync, synchronous_commit, full_page_writes on)
unless ``--pg-not-durable``; the first lines printed say what each store runs with, as the
server reports it.

The relays and the node processes share this machine's cores (and the PostgreSQL server's
processes too): on a 2-core machine the nodes take CPU from the relays, so the rates are a
floor. Each phase reports the relays' CPU summed over the relay processes (% of one core:
``relay_cpu_pct``; in the throughput phase also within the 10-90 % window; in the lag phase each
relay's too, ``relay_cpu_pct_each``, the first one's holding the /ui client) and per event
received (``relay_cpu_us_per_event``: relay CPU seconds / events received x 1e6; in the
throughput phase over the 10-90 % window, in the lag phase over its window, and
``relay_cpu_us_per_event_no_ui`` over as long again with the same nodes and no browser: the live
view's pushes are the difference), which other work
on the machine moves less than a rate; the same for the PostgreSQL server
(``store_cpu_us_per_event``: the work the relay hands it; with SQLite the writes are the
relay's own, in its CPU); that of all node processes (``nodes_cpu_pct``), and ``load_before``
(1-min load average when the combination started: other work on the machine), and that of the
/ui client (``client_cpu_pct``, this process: at 100 % it is the client that falls behind, and the
lag is its own). Prints one JSON
line per combination and settings, then a table of them side by side; a figure a run could not
produce is ``"n/a (reason)"`` in the JSON, ``n/a [k]`` with its reason below in the table
(benchmarks/figures.py). Last, the compiled floor (benchmarks/floor.py): what decoding and pairing
alone cost per event, beside the relay's figures.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_relay.py [--store sqlite postgresql] [--relays 1 2]
        [--nodes 2 8 32] [--settings today adaptive] [--events 2000000] [--batch-events 8192]
        [--rate 4300] [--seconds 12] [--watch N] [--workers] [--lag-only | --bulk-only] [--pg-not-durable] [--quick]

``--tls`` measures what TLS costs the relay instead: for each store and node count, N nodes paced at
``--rate`` stream for ``--seconds`` to one relay over plaintext, and as long to a fresh relay over
TLS (``--tls-cert``, a certificate of a CA made for the run, tests/tlscerts.py; the nodes verify it
with ``--relay-ca``), no browser, ``--repeats`` rounds in alternating order; relay CPU per event
received on each (the median of its rounds), and their ratio (the goal: within 1.15x).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import resource
import ssl
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import socketio

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks import floor  # noqa: E402
from benchmarks.figures import NA, CannotRun, Notes, dumps, last_line, one_line, percentile, ratio, run  # noqa: E402
from benchmarks.stores import ONE_RELAY, SQLITE_SETTINGS, STORES, PostgresStore  # noqa: E402
from dcuscope.relay.live.framepack import MISSING, columns_of  # noqa: E402

SOURCES = 2
EVENTS_PER_FRAME = 12  # origin, 5 stages x enter/exit, sink enter
# Every simulated node connects from 127.0.0.1, where real DCUs each have their own address:
# the per-address cap (16 by default) would refuse the 17th node and the benchmark's own requests.
LOOPBACK = ("--limit", "connections_per_peer=256")


class Settings(NamedTuple):
    """How the nodes batch and the relays push: the options each is started with."""

    nodes: tuple[str, ...]
    relay: tuple[str, ...]
    about: str


SETTINGS = {
    "today": Settings(("--fixed-flush",), ("--push-hz", "10"),
                      "the settings before adaptive batching: nodes cut a batch every 50 ms (simnode --fixed-flush), "
                      "a relay pushes a DCU's frames at most 10 times a second (--push-hz 10)"),
    "adaptive": Settings((), (), "the defaults: nodes ship at once while their link is idle (at most one batch per "
                                 "min_flush_s), a relay pushes frames as they complete (its default --push-hz)"),
}


def _env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + os.pathsep + e.get("PYTHONPATH", "")
    return e


class Relay:
    def __init__(self, db: Path | str, args: Sequence[str] = (), workers: int = 1, checkout: Path = ROOT,
                 context: ssl.SSLContext | None = None) -> None:
        """``db``: an SQLite file or a PostgreSQL URL; ``args``: more ``python -m dcuscope.relay`` options
        (bench_exporters: --otlp, --frame-limit); ``workers`` above 1: ``python -m dcuscope.relay --workers
        N`` on one port, ready once every worker listens; ``checkout``: the tree whose relay runs
        (another one beside this: bench_store_size's --checkout); ``context``: how this process
        verifies a relay started with ``--tls-cert``.
        Raises CannotRun, with the relay's last line of error, when it does not start."""
        self.workers = workers
        self.context = context
        port = "0"
        if workers > 1:
            from tests.ports import free_port

            port, args = str(free_port()), [*args, "--workers", str(workers)]
        self._errors = tempfile.TemporaryFile()  # not a pipe: nobody reads it while the relay runs
        self.proc = subprocess.Popen([sys.executable, "-m", "dcuscope.relay", "--port", port, "--db", str(db), *LOOPBACK, *args],
                                     cwd=checkout, env=dict(_env(), PYTHONPATH=str(checkout)), stdout=subprocess.PIPE,
                                     stderr=self._errors)
        listening = []
        while len(listening) < workers:
            m = re.search(r"(https?)://127\.0\.0\.1:(\d+)", self.proc.stdout.readline().decode())
            if not m:
                self.proc.kill()
                self.proc.wait(15)
                self._errors.seek(0)
                raise CannotRun(f"the relay did not start: {last_line(self._errors.read())}")
            listening.append(m.groups())
        self.url = f"{listening[0][0]}://127.0.0.1:{listening[0][1]}"

    def get(self, path: str):
        with urllib.request.urlopen(self.url + path, timeout=30, context=self.context) as r:
            return json.loads(r.read())

    def cpu_s(self) -> float:
        """CPU seconds the relay process used so far (user + system), its workers' included."""
        return sum(_proc_cpu(pid) for pid in _process_tree(self.proc.pid))

    def stored(self) -> int:
        return sum(run["events"] for s in self.get("/api/sessions") for run in s["runs"])

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(30)
        self._errors.close()


def _relays(relay: Relay | Sequence[Relay]) -> list[Relay]:
    return [relay] if isinstance(relay, Relay) else list(relay)


def relay_list(urls: str | Sequence[str], k: int) -> str:
    """Node k's ``--relay``: the relays' URLs from relay k mod R on, round the list."""
    urls = [urls] if isinstance(urls, str) else list(urls)
    i = k % len(urls)
    return ",".join(urls[i:] + urls[:i])


def start_nodes(url: str | Sequence[str], n: int, per_node_events: int, paced: bool, fps: float,
                batch_events: int = 8192, node_args: Sequence[str] = ()) -> list[subprocess.Popen]:
    """N simulated nodes; with several relays' URLs, dealt round-robin (:func:`relay_list`).
    ``node_args``: more ``python -m dcuscope.probes.ship.simnode`` options (a settings' ``--fixed-flush``)."""
    frames = max(1, per_node_events // (EVENTS_PER_FRAME * SOURCES))
    procs = []
    for k in range(n):
        cmd = [sys.executable, "-m", "dcuscope.probes.ship.simnode", "--relay", relay_list(url, k), "--node", f"DCU-{k + 1}",
               "--sources", str(SOURCES), "--frames", str(frames), "--fps", str(fps), "--seed", str(k),
               "--close-timeout", "120", "--batch-events", str(batch_events), *node_args]
        if paced:
            cmd.append("--paced")
        procs.append(subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE))
    return procs


def wait_nodes(procs: list[subprocess.Popen], timeout: float) -> list[dict]:
    """Each node's counters (its last line of output); CannotRun with its error if one failed."""
    out = []
    for k, p in enumerate(procs):
        try:
            stdout, stderr = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            raise CannotRun(f"simulated node DCU-{k + 1} did not finish within {timeout:g} s") from None
        if p.returncode != 0 or not stdout.strip():
            raise CannotRun(f"simulated node DCU-{k + 1} failed (exit status {p.returncode}): {last_line(stderr)}")
        out.append(json.loads(stdout.decode().strip().splitlines()[-1]))
    return out


class Stores:
    """The stores of one benchmark run: a fresh SQLite file or PostgreSQL database per phase, and
    the Redis that relays sharing a store push through (:meth:`fanout`)."""

    def __init__(self, names: Sequence[str], tmp: Path, durable: bool) -> None:
        self.tmp = tmp
        self.pg = PostgresStore(durable) if "postgresql" in names else None
        self.redis = None
        self._made = 0

    def fanout(self, relays: int) -> list[str]:
        """The relay options of ``relays`` relays sharing a store: with several, ``--redis`` to one
        Redis server (started at the first call), so that each relay's pushes reach the browsers
        of all. Raises CannotRun when Redis is not installed or does not start."""
        if relays == 1:
            return []
        if self.redis is None:
            try:
                from tests.redisserver import RedisServer

                self.redis = RedisServer()
            except (ImportError, RuntimeError) as exc:
                raise CannotRun(f"no Redis server for {relays} relays: {exc}") from None
            try:
                self.redis.start()
            except (RuntimeError, OSError) as exc:
                self.redis.close()
                self.redis = None
                raise CannotRun(f"the Redis server did not start: {one_line(str(exc))[-400:]}") from None
        return ["--redis", self.redis.url]

    def settings(self, name: str) -> str:
        return self.pg.describe() if name == "postgresql" else SQLITE_SETTINGS

    def fresh_count(self) -> int:
        """Stores made so far (a name for what a phase makes beside its store)."""
        return self._made

    def fresh(self, name: str) -> str:
        self._made += 1
        return self.pg.new_database() if name == "postgresql" else str(self.tmp / f"relay{self._made}.db")

    def done(self, name: str, db: str) -> None:
        if name == "postgresql":
            self.pg.drop(db)

    def server(self, name: str) -> PostgresStore | None:
        return self.pg if name == "postgresql" else None

    def close(self) -> None:
        if self.pg is not None:
            self.pg.close()
        if self.redis is not None:
            self.redis.close()


def _phase(stores: Stores, store: str, relays: int, settings: Settings,
           measure: Callable[[list[Relay], PostgresStore | None], dict], workers: bool = False) -> dict:
    """``measure(relays, server)`` on ``relays`` fresh relay processes sharing a fresh store,
    started with ``settings`` (and a Redis between them: :meth:`Stores.fanout`); ``workers``: as
    one ``relay --workers`` on one port, not each on a port of its own."""
    args = [*settings.relay, *stores.fanout(relays)]
    db = stores.fresh(store)
    started: list[Relay] = []
    try:
        if workers and relays > 1:
            started.append(Relay(db, args, workers=relays))
        else:
            for _ in range(relays):
                started.append(Relay(db, args))
        return measure(started, stores.server(store))
    finally:
        for relay in started:
            relay.stop()
        stores.done(store, db)


def throughput(n: int, total: int, stores: Stores, batch_events: int, store: str, relays: int,
               settings: Settings, workers: bool = False) -> dict:
    return _phase(stores, store, relays, settings, lambda rs, server: measure_throughput(
        rs, n, total, batch_events, server, settings.nodes), workers)


def measure_throughput(relay: Relay | Sequence[Relay], n: int, total: int, batch_events: int,
                       server: PostgresStore | None = None, node_args: Sequence[str] = ()) -> dict:
    """The throughput phase on ``relay``, a fresh one (or fresh relays sharing a fresh store):
    every event stored is counted. ``server``: the PostgreSQL server under them, whose CPU is
    measured too; ``node_args``: more options of the nodes (:func:`start_nodes`)."""
    relays = _relays(relay)
    per_node = total // n
    expected = n * (per_node // (EVENTS_PER_FRAME * SOURCES)) * EVENTS_PER_FRAME * SOURCES
    children = _children_cpu()

    def cpu() -> float:
        return sum(r.cpu_s() for r in relays)

    def server_cpu() -> float:
        return server.cpu_s() if server else 0.0

    cpu0, wall0 = cpu(), time.monotonic()
    procs = start_nodes([r.url for r in relays], n, per_node, paced=False, fps=1000.0, batch_events=batch_events,
                        node_args=node_args)
    samples = []
    deadline = time.monotonic() + 600
    ended = None  # when every node had exited: the relays get 2 s more to store what they sent, not 600
    while time.monotonic() < deadline:
        # Any relay lists every run of a shared store: the first one counts them.
        samples.append((time.monotonic(), relays[0].stored(), cpu(), server_cpu()))
        if samples[-1][1] >= expected or (ended is not None and time.monotonic() - ended > 2.0):
            break
        if ended is None and all(p.poll() is not None for p in procs):
            ended = time.monotonic()
        time.sleep(0.1)
    relay_cpu = cpu() - cpu0
    wall = time.monotonic() - wall0
    counters = wait_nodes(procs, 120)
    t = np.array([s[0] for s in samples])
    v = np.array([s[1] for s in samples], float)
    c = np.array([s[2] for s in samples])
    sc = np.array([s[3] for s in samples])
    lo, hi = np.searchsorted(v, 0.1 * expected), min(np.searchsorted(v, 0.9 * expected), len(v) - 1)
    if v[-1] < 0.9 * expected:
        why = NA(f"the relay stored {int(v[-1])} of {expected} events")
    elif hi > lo and t[hi] > t[lo]:
        why = None
    else:  # the run was shorter than two of the 0.1 s samples inside 10-90 %
        why = NA("no two samples of the stored count inside 10-90 % of the events: the run was too short")
    if why is None:
        span, stored = float(t[hi] - t[lo]), float(v[hi] - v[lo])
        rate, window_s, window_cpu = round(stored / span), round(span, 2), round(100 * (c[hi] - c[lo]) / span)
        us_per_event = round(1e6 * (c[hi] - c[lo]) / stored, 2)
        store_us = round(1e6 * (sc[hi] - sc[lo]) / stored, 2) if server else NO_SERVER
    else:
        rate = window_s = window_cpu = us_per_event = store_us = why
    return {"batch_events": batch_events, "events": int(v[-1]), "events_per_s": rate,
            "events_per_batch": round(sum(c["written"] for c in counters)
                                      / max(1, sum(c["batches"] for c in counters))),
            "lost": sum(c["lost"] for c in counters), "window_s": window_s, "relay_cpu_pct_in_window": window_cpu,
            "relay_cpu_us_per_event": us_per_event, "store_cpu_us_per_event": store_us,
            "relay_cpu_pct": round(100 * relay_cpu / wall),
            "nodes_cpu_pct": round(100 * (_children_cpu() - children) / wall)}


async def _watch_ui(url: str, seconds: float, watch: int | None = None) -> tuple[list[float], list[float], set[str]]:
    """Lags of the frames pushed (ms), of the pushes themselves (arrival - relay send), and the
    nodes whose frames came; ``watch``: the client shows DCU-1 .. DCU-watch only, as a page with
    those opened from the overview (None: every DCU, as a page with all of them opened)."""
    lags: list[float] = []
    transit: list[float] = []
    nodes: set[str] = set()
    sio = socketio.AsyncClient(reconnection=False)

    def on_frames(data: dict) -> None:
        now = time.clock_gettime_ns(time.CLOCK_REALTIME)
        transit.append((now - data["t_ns"]) / 1e6)
        for node, block in data["nodes"].items():
            nodes.add(node)
            lags.extend(((now - last_times(block) - block["correction_ns"]) / 1e6).tolist())

    sio.on("frames", on_frames, namespace="/ui")
    try:
        shown = None if watch is None else [f"DCU-{k + 1}" for k in range(watch)]
        await sio.connect(url, namespaces=["/ui"], transports=["websocket"], wait_timeout=10,
                          auth={"subscribe": {"nodes": shown}})
    except socketio.exceptions.ConnectionError as exc:
        raise CannotRun(f"the /ui client could not connect to the relay: {exc}") from exc
    await asyncio.sleep(seconds)
    # Shown nothing first, then gone: python-socketio's client drops a binary push it is still
    # assembling when it disconnects, and then reads its remaining attachments as packets (a
    # ValueError in a task nobody awaits). Once the relay answered, every push sent before the
    # answer was taken in whole.
    try:
        await sio.call("subscribe", {"nodes": [], "overview": False}, namespace="/ui", timeout=10)
    except socketio.exceptions.TimeoutError:
        pass
    await sio.disconnect()
    return lags, transit, nodes


def last_times(block: dict) -> np.ndarray:
    """Per frame of a pushed block, its last time (enter or exit of any stage): read from the packed
    columns, so that the client keeps up with every DCU's pushes."""
    ints, _ = columns_of(block["packed"])
    times = np.concatenate([ints["enter"], ints["exit"]])
    return np.where(times == MISSING, np.iinfo(np.int64).min, times).max(axis=0)


def lag(n: int, rate: float, seconds: float, stores: Stores, store: str, relays: int, settings: Settings,
        watch: int | None = None, workers: bool = False) -> dict:
    return _phase(stores, store, relays, settings, lambda rs, server: measure_lag(
        rs, n, rate, seconds, server=server, node_args=settings.nodes, watch=watch), workers)


def _received(relays: list[Relay]) -> tuple[set[str], int]:
    """The nodes streaming to ``relays`` (with an event received), and the events all of them received.
    Relays sharing a store each list every node of the fleet: a node counts once, with the highest
    count listed (its own relay's, live; the others' come from the store, up to a second old).
    Workers sharing a port answer in turn, as the kernel deals the connections: each is asked
    three times per worker, so that the owners' live counts are most likely among the answers."""
    events: dict[str, int] = {}
    for relay in relays:
        for _ in range(1 if relay.workers == 1 else 3 * relay.workers):
            for node in relay.get("/api/nodes"):
                events[node["node"]] = max(events.get(node["node"], 0), node["events"])
    return {name for name, n in events.items() if n > 0}, sum(events.values())


def measure_lag(relay: Relay | Sequence[Relay], n: int, rate: float, seconds: float,
                on_window: Callable[[str], None] | None = None, server: PostgresStore | None = None,
                node_args: Sequence[str] = (), watch: int | None = None) -> dict:
    """The lag phase on ``relay`` (or relays sharing a store and a Redis: the /ui client watches
    the first, which pushes every relay's frames); ``on_window("start")`` / ``("end")`` are called
    as the measured window opens and closes (bench_exporters samples the exporters' counters
    there). ``server``: the PostgreSQL server under them, whose CPU is measured too;
    ``node_args``: more options of the nodes (:func:`start_nodes`); ``watch``: the DCUs the /ui client
    shows (:func:`_watch_ui`)."""
    relays = _relays(relay)
    fps = rate / (EVENTS_PER_FRAME * SOURCES)
    # Nodes run long enough to outlast their own start-up (Python imports: ~0.5 CPU-s
    # each, which on 2 cores and 32 nodes is seconds); measured only once all stream.
    procs = start_nodes([r.url for r in relays], n, int(rate * (seconds + 60)), paced=True, fps=fps,
                        node_args=node_args)
    deadline = time.monotonic() + 120
    not_streaming: list[str] = []
    while time.monotonic() < deadline:
        if len(streaming := _received(relays)[0]) == n:
            break
        time.sleep(0.5)
    else:  # measured all the same, and said: nodes that ran out before the window opened leave it empty
        not_streaming = sorted(set(f"DCU-{k + 1}" for k in range(n)) - streaming, key=lambda name: int(name[4:]))
        print(f"bench_relay: {len(not_streaming)} of {n} nodes listed by no relay with an event after 120 s "
              f"({', '.join(not_streaming[:8])}); exit statuses {[p.poll() for p in procs]}; measuring anyway",
              file=sys.stderr)
    settle = min(1.0, seconds / 3)  # once all stream (a quick run's short window: shorter)
    time.sleep(settle)
    if on_window:
        on_window("start")

    def cpu() -> float:
        return sum(r.cpu_s() for r in relays)

    _, events0 = _received(relays)
    cpu0, server0, wall0 = cpu(), server.cpu_s() if server else 0.0, time.monotonic()
    nodes_cpu0 = sum(_proc_cpu(p.pid) for p in procs)
    each0 = [r.cpu_s() for r in relays]
    client0 = time.process_time()
    lags, transit, seen = asyncio.run(_watch_ui(relays[0].url, seconds, watch))
    relay_cpu, wall = cpu() - cpu0, time.monotonic() - wall0
    each = [round(100 * (r.cpu_s() - c) / wall) for r, c in zip(relays, each0)]
    client_cpu = time.process_time() - client0
    server_cpu = server.cpu_s() - server0 if server else 0.0
    _, received = _received(relays)
    if on_window:
        on_window("end")
    nodes_cpu = sum(_proc_cpu(p.pid) for p in procs) - nodes_cpu0
    in_window = received - events0
    none = f"the relays received no event in the {seconds:g} s window"
    # The same nodes for as long again with no browser: what the live view's pushes cost.
    time.sleep(settle)
    cpu1, (_, events1) = cpu(), _received(relays)
    time.sleep(seconds)
    quiet_cpu, (_, events2) = cpu() - cpu1, _received(relays)
    for p in procs:
        p.terminate()
    for p in procs:
        p.wait(30)
    no_frame = f"no frame reached the /ui client in the {seconds:g} s window"
    no_push = f"no push reached the /ui client in the {seconds:g} s window"
    return {"rate_per_node": rate, "seconds": seconds, "watched": "all" if watch is None else min(watch, n),
            "frames_seen": len(lags), "nodes_seen": len(seen), "not_streaming": not_streaming,
            "events_received": received,
            "events_in_window": in_window,
            "relay_cpu_us_per_event": round(1e6 * ratio(relay_cpu, in_window, none), 2),
            "relay_cpu_us_per_event_no_ui": round(1e6 * ratio(quiet_cpu, events2 - events1, none), 2),
            "store_cpu_us_per_event": round(1e6 * ratio(server_cpu, in_window, none), 2) if server else NO_SERVER,
            "lag_p50_ms": round(percentile(lags, 50, no_frame), 1),
            "lag_p99_ms": round(percentile(lags, 99, no_frame), 1),
            "push_transit_p50_ms": round(percentile(transit, 50, no_push), 1),
            "push_transit_p99_ms": round(percentile(transit, 99, no_push), 1),
            "relay_cpu_pct": round(100 * relay_cpu / wall), "nodes_cpu_pct": round(100 * nodes_cpu / wall),
            "client_cpu_pct": round(100 * client_cpu / wall), "relay_cpu_pct_each": each}


def tls_cost(n: int, rate: float, seconds: float, stores: Stores, store: str, repeats: int = 3) -> dict:
    """Relay CPU per event of ``n`` nodes paced at ``rate``, over plaintext and over TLS, each on a
    fresh relay and store; ``repeats`` rounds, the order alternating (plain then TLS, TLS then plain,
    ...) so that a machine getting busier or quieter weighs on both sides alike. Each side's figure
    is the median of its rounds; the ratio TLS / plaintext is of the medians."""
    from tests.tlscerts import TestCA

    ca = TestCA(stores.tmp, f"pki{stores.fresh_count()}")
    server = ca.issue("relay")
    ways = {"plain": ((), (), None),
            "tls": (("--tls-cert", str(server.cert), "--tls-key", str(server.key)), ("--relay-ca", str(ca.cert)),
                    ssl.create_default_context(cafile=str(ca.cert)))}
    result: dict = {"rate_per_node": rate, "seconds": seconds, "repeats": repeats}
    runs: dict[str, list] = {"plain": [], "tls": []}
    for round_ in range(repeats):
        for name in ("plain", "tls") if round_ % 2 == 0 else ("tls", "plain"):
            relay_args, node_args, context = ways[name]
            db = stores.fresh(store)
            relay = None
            try:
                relay = Relay(db, relay_args, context=context)
                runs[name].append(measure_paced_cpu(relay, n, rate, seconds, node_args))
            except CannotRun as exc:
                runs[name].append(NA(str(exc)))
            finally:
                if relay is not None:
                    relay.stop()
                stores.done(store, db)
    for name, measured in runs.items():
        failed = [m for m in measured if isinstance(m, NA)]
        result[name] = failed[0] if failed else {
            "events_in_window": sum(m["events_in_window"] for m in measured),
            "rounds_us_per_event": [m["relay_cpu_us_per_event"] for m in measured],
            "relay_cpu_us_per_event": round(statistics.median(m["relay_cpu_us_per_event"] for m in measured), 2)}
    plain, tls = (_figure(result, name, "relay_cpu_us_per_event") for name in ("plain", "tls"))
    result["ratio"] = (round(tls / plain, 3) if not isinstance(plain, NA) and not isinstance(tls, NA) and plain > 0
                       else NA("a side has no figure"))
    return result


def measure_paced_cpu(relay: Relay, n: int, rate: float, seconds: float, node_args: Sequence[str] = ()) -> dict:
    """Relay CPU per event received from ``n`` nodes paced at ``rate`` events/s, over ``seconds``
    once all of them stream (no browser)."""
    fps = rate / (EVENTS_PER_FRAME * SOURCES)
    procs = start_nodes(relay.url, n, int(rate * (seconds + 60)), paced=True, fps=fps, node_args=node_args)
    try:
        deadline = time.monotonic() + 120
        while len(_received([relay])[0]) < n:
            if time.monotonic() > deadline:
                raise CannotRun(f"not all {n} nodes streamed within 120 s")
            time.sleep(0.5)
        time.sleep(min(1.0, seconds / 3))
        cpu0, (_, events0) = relay.cpu_s(), _received([relay])
        time.sleep(seconds)
        cpu1, (_, events1) = relay.cpu_s(), _received([relay])
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(30)
    none = f"the relay received no event in the {seconds:g} s window"
    return {"events_in_window": events1 - events0,
            "relay_cpu_us_per_event": round(1e6 * ratio(cpu1 - cpu0, events1 - events0, none), 2)}


def _cost(line: dict, side: str):
    """Relay CPU per event of one side (plain, tls) of a ``--tls`` line, or why there is none."""
    part = line["tls_cost"]
    part = part if isinstance(part, NA) else part[side]
    return part if isinstance(part, NA) else part["relay_cpu_us_per_event"]


def tls_table(lines: list[dict]) -> list[str]:
    notes = Notes()
    rows = [f"{'store':<10} {'nodes':>5} {'µs/event':>10} {'µs/event':>10} {'TLS /':>8}",
            f"{'':<10} {'':>5} {'plain':>10} {'TLS':>10} {'plain':>8}"]
    for line in lines:
        rows.append(f"{line['store']:<10} {line['nodes']:>5} {notes.cell(_cost(line, 'plain'), '.1f'):>10} "
                    f"{notes.cell(_cost(line, 'tls'), '.1f'):>10} "
                    f"{notes.cell(_figure(line, 'tls_cost', 'ratio'), '.3f'):>8}")
    legend = (f"µs/event: relay CPU per event received, nodes paced at {lines[0]['tls_cost']['rate_per_node']:g} "
              f"events/s each, no browser; over plaintext and over TLS (a fresh relay each), "
              f"median of {lines[0]['tls_cost']['repeats']} rounds in alternating order; goal: TLS / plain within 1.15") if lines and not isinstance(lines[0]["tls_cost"], NA) else "µs/event: relay CPU per event"
    return rows + [legend] + notes.lines()


NO_SERVER = NA("no store server: SQLite writes run in the relay process, their CPU is in relay_cpu")


def _process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants (a relay with ``--workers``: the parent and its workers)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            todo.extend(int(c) for c in Path(f"/proc/{p}/task/{p}/children").read_text().split())
        except OSError:
            pass
    return out


def _proc_cpu(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except FileNotFoundError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _choices(values: list[str], allowed: Sequence[str] | None, kind: type, what: str, p) -> list:
    """``values`` (each possibly a comma list) as a list of ``kind``, each once, in the order given."""
    out = []
    for value in values:
        for item in value.split(","):
            item = item.strip()
            if not item:
                continue
            try:
                x = kind(item)
            except ValueError:
                p.error(f"{what}: not a {kind.__name__}: {item!r}")
            if allowed is not None and x not in allowed:
                p.error(f"{what}: {item!r} is none of {', '.join(allowed)}")
            if x not in out:
                out.append(x)
    return out


def combination(stores: Stores, store: str, relays: int, n: int, settings: str, args: argparse.Namespace) -> dict:
    """One JSON line: both phases of ``n`` nodes on ``relays`` relays sharing a ``store``, with ``settings``."""
    workers = args.workers and relays > 1
    result = {"store": store, "relays": relays, "nodes": n, "settings": settings, "cpus": os.cpu_count(),
              "load_before": round(os.getloadavg()[0], 1)} | ({"workers": True} if workers else {})
    if store == "sqlite" and relays > 1:
        return result | {"throughput": NA(ONE_RELAY), "lag": NA(ONE_RELAY)}
    chosen = SETTINGS[settings]
    phases = {"throughput": lambda: throughput(n, args.events, stores, args.batch_events, store, relays, chosen,
                                               workers),
              "lag": lambda: lag(n, args.rate, args.seconds, stores, store, relays, chosen, args.watch, workers)}
    for phase, flag, skipped in (("throughput", "--lag-only", args.lag_only), ("lag", "--bulk-only", args.bulk_only)):
        if skipped:
            result[phase] = NA(f"not run ({flag})")
            del phases[phase]
    for name, measure in phases.items():
        try:
            result[name] = measure()
        except CannotRun as exc:  # a node or relay failed in this phase: its figures are n/a, the others run
            result[name] = NA(str(exc))
    return result


def _figure(line: dict, phase: str, key: str):
    part = line[phase]
    return part if isinstance(part, NA) else part[key]


def table(lines: list[dict], rate: float) -> list[str]:
    """The combinations side by side (the settings of one combination on adjacent rows), and the
    reasons of their n/a cells."""
    notes = Notes()
    head = (f"{'store':<10} {'relays':>6} {'nodes':>5} {'settings':<8} {'events/s':>10} {'µs/event':>10} "
            f"{'µs/event':>10} {'µs/event':>10} {'lag p50':>9} {'lag p99':>9} {'PG µs/ev':>9} {'PG µs/ev':>9}")
    sub = (f"{'':<10} {'':>6} {'':>5} {'':<8} {'bulk':>10} {'paced':>10} {'no /ui':>10} {'bulk':>10} "
           f"{'ms':>9} {'ms':>9} {'paced':>9} {'bulk':>9}")
    rows = [head, sub]
    for line in lines:
        relays = f"{line['relays']}w" if line.get("workers") else line["relays"]
        rows.append(f"{line['store']:<10} {relays:>6} {line['nodes']:>5} {line['settings']:<8} "
                    f"{notes.cell(_figure(line, 'throughput', 'events_per_s'), ',d'):>10} "
                    f"{notes.cell(_figure(line, 'lag', 'relay_cpu_us_per_event'), '.1f'):>10} "
                    f"{notes.cell(_figure(line, 'lag', 'relay_cpu_us_per_event_no_ui'), '.1f'):>10} "
                    f"{notes.cell(_figure(line, 'throughput', 'relay_cpu_us_per_event'), '.1f'):>10} "
                    f"{notes.cell(_figure(line, 'lag', 'lag_p50_ms'), '.0f'):>9} "
                    f"{notes.cell(_figure(line, 'lag', 'lag_p99_ms'), '.0f'):>9} "
                    f"{notes.cell(_figure(line, 'lag', 'store_cpu_us_per_event'), '.1f'):>9} "
                    f"{notes.cell(_figure(line, 'throughput', 'store_cpu_us_per_event'), '.1f'):>9}")
    legend = (f"settings: {', '.join(SETTINGS)} (above); events/s: stored per second in bulk (10-90 % window); "
              f"µs/event: relay CPU (all relay processes) per event received, paced at {rate:g} events/s a node "
              "(the paper's pace: with a /ui client on the first relay, and as long again with none) and in bulk; "
              "lag p50/p99: frame end to its push reaching the /ui client, paced; PG µs/ev: the PostgreSQL "
              "server's CPU per event; relays Nw: one relay --workers N on one port")
    return rows + [legend] + notes.lines()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", nargs="+", action="extend", metavar="{sqlite,postgresql}",
                   help="stores to run the relays on (repeatable, or a list; default sqlite)")
    p.add_argument("--relays", nargs="+", action="extend", metavar="R",
                   help="numbers of relay processes sharing the store (repeatable, or a list; default 1)")
    p.add_argument("--pg-not-durable", action="store_true",
                   help="PostgreSQL with fsync, synchronous_commit and full_page_writes off (as the tests run it), "
                        "not PostgreSQL's defaults; said in the output")
    p.add_argument("--nodes", type=int, nargs="+", default=[2, 8, 32])
    p.add_argument("--events", type=int, default=2_000_000, help="events in all for the throughput phase")
    p.add_argument("--batch-events", type=int, default=8192,
                   help="most events per batch in the throughput phase (a paced DCU at 4,300/s sends ~215 with "
                        "the 50 ms fixed flush, fewer adaptively)")
    p.add_argument("--rate", type=float, default=4300.0, help="events/s per node in the lag phase")
    p.add_argument("--seconds", type=float, default=12.0, help="length of the lag phase")
    p.add_argument("--settings", nargs="+", action="extend", metavar="{today,adaptive}",
                   help="the node and relay settings to run each combination with (repeatable, or a list; "
                        "default both, side by side: today adaptive)")
    p.add_argument("--watch", type=int, metavar="N",
                   help="the lag phase's /ui client shows DCU-1..DCU-N only, as a page with N DCUs opened from the "
                        "fleet overview (default: every DCU, as a page with all of them opened)")
    p.add_argument("--workers", action="store_true",
                   help="run each combination's R relays as one `relay --workers R` on one port, the kernel dealing "
                        "the nodes' connections among them (one host's relay processes), not R relays on ports of "
                        "their own with the nodes dealt round-robin; PostgreSQL only")
    only = p.add_mutually_exclusive_group()
    only.add_argument("--lag-only", action="store_true", help="run the lag phase only (its throughput figures n/a)")
    only.add_argument("--bulk-only", action="store_true",
                      help="run the throughput phase only (its lag figures n/a)")
    p.add_argument("--quick", action="store_true", help="a smoke test: 2 nodes, 100,000 events, a 1 s lag phase")
    p.add_argument("--tls", action="store_true",
                   help="instead of the phases above: relay CPU per paced event over plaintext and over TLS, side by "
                        "side, and their ratio (one relay; each --store and --nodes)")
    p.add_argument("--repeats", type=int, default=3, metavar="N",
                   help="with --tls: rounds of each side, in alternating order; the medians are compared (default 3; "
                        "--quick: 1)")
    args = p.parse_args(argv)
    if args.quick:
        args.nodes, args.events, args.seconds, args.repeats = [2], 100_000, 1.0, 1
    if args.repeats < 1:
        p.error("--repeats takes 1 or more")
    stores = _choices(args.store or ["sqlite"], STORES, str, "--store", p)
    relay_counts = _choices(args.relays or ["1"], None, int, "--relays", p)
    settings = _choices(args.settings or list(SETTINGS), SETTINGS, str, "--settings", p)
    if min(args.nodes) < 1 or min(relay_counts) < 1 or args.events < 1 or args.seconds <= 0 or args.rate <= 0:
        p.error("--nodes, --relays, --events, --seconds and --rate must be positive")
    if args.workers and "sqlite" in stores:
        p.error("--workers runs several relays on one store: --store postgresql")
    if args.watch is not None and args.watch < 1:
        p.error("--watch takes a number of DCUs, at least 1")
    lines = []
    with tempfile.TemporaryDirectory() as tmp:
        rig = Stores(stores, Path(tmp), durable=not args.pg_not_durable)
        try:
            for store in stores:
                print(f"store {store}: {rig.settings(store)}", flush=True)
            for name in [] if args.tls else settings:
                print(f"settings {name}: {SETTINGS[name].about}", flush=True)
            print(f"machine: {os.cpu_count()} CPUs, 1-min load {os.getloadavg()[0]:.1f} at start", flush=True)
            for store in stores:
                if args.tls:
                    for n in args.nodes:
                        lines.append({"store": store, "relays": 1, "nodes": n, "cpus": os.cpu_count(),
                                      "load_before": round(os.getloadavg()[0], 1),
                                      "tls_cost": tls_cost(n, args.rate, args.seconds, rig, store, args.repeats)})
                        print(dumps(lines[-1]), flush=True)
                    continue
                for relays in relay_counts:
                    for n in args.nodes:
                        for name in settings:
                            lines.append(combination(rig, store, relays, n, name, args))
                            print(dumps(lines[-1]), flush=True)
        finally:
            rig.close()
    print("\n".join(tls_table(lines) if args.tls else table(lines, args.rate)), flush=True)
    if not args.tls:  # beside the relay's figures: what the compiled core alone costs of them
        print(floor.describe(floor.compiled_floor()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run(main))
