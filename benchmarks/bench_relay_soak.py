"""Relay soak: the resident memory of a relay whose node restarts again and again.

One relay process (``python -m dcuscope.relay``, as ``dcuscope relay``, on a fresh store: an SQLite file, or
with ``--store postgresql`` a database on a PostgreSQL server of the benchmark's own) and one node
driven by hand over the ingest WebSocket (:class:`dcuscope.probes.ship.relaylink.Link`). Each run of the
node says hello, ships ``--events`` events (synthetic frames of ``probes.ship.simnode``) in
compressed batches of ``--batch-events``, all in flight at once as a node keeps them, waits for
every acknowledgement, and falls silent with its connection left open: the node "crashed". It
then restarts as a new run under the same node name; the relay refuses the new run while the old
one holds the name (``--limit silent_s``, shortened here so that a restart takes a second, not
eight), then hands the name over and closes the silent connection, and the old run's live state
leaves memory. This is the case of tests/relay/guard/test_hostile_identity.py, at a realistic batch size
and many times over.

After each restart's run is stored and merged, and the node was silent for ``silent_s``, the
relay's resident memory (``VmRSS`` of /proc/PID/status, and its high-water mark ``VmHWM``) is
sampled beside what the relay itself says it holds (``/api/health``: ``memory.live_bytes``,
``runs``; ``heap``: what malloc holds in use and free inside its arenas, and the reclaim passes of
:mod:`dcuscope.relay.heap`) and its thread count (each thread may get a malloc arena of its own). The
verdict, over restarts 5..N (allocator arenas and caches warmed up before): the RSS after restart
5, the maximum, a Theil-Sen slope (robust to a sample taken just after a reclaim pass), and how much the high-water mark rose after restart 5 (the
peak of one restart's transients is the same each time: it rises only when memory is kept across
restarts, and where a sample falls between the relay's reclaim passes does not move it). A relay
that releases what each run held stays flat; one that keeps something per run grows by about that
much per restart. Both are also given in runs' raw payloads (events x 24 B), so that they mean the
same whatever ``--events``.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_relay_soak.py [--restarts 100] [--events 240000]
        [--batch-events 60000] [--silent-s 1.0] [--env NAME=VALUE ...] [--quick] [--json]

``--env`` runs the relay with an environment variable set, to compare allocator settings run
against run (``MALLOC_ARENA_MAX=1``, ``MALLOC_MMAP_THRESHOLD_=131072``: glibc reads them at start).
The last line is a JSON object of the verdict (``--json``: every sample too), with the store.

``--store postgresql`` soaks the relay on the shared store's engine (relay/store/postgres.py: a
writer connection that owns each run by an advisory lock, released as the run is handed over):
Debian's PostgreSQL 15 started for the run in a temporary folder (benchmarks/stores.py), durable
as users run it (fsync, synchronous_commit, full_page_writes on) unless ``--pg-not-durable``; the
first line printed says which, as the server reports it. Only the relay's memory is sampled, not
the server's.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import aiohttp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import NA, CannotRun, Notes, dumps, fmt, last_line, run  # noqa: E402
from benchmarks.stores import SQLITE_SETTINGS, STORES, PostgresStore  # noqa: E402
from dcuscope.probes.ship.relaylink import Link  # noqa: E402
from dcuscope.probes.ship.simnode import EVENTS_PER_FRAME, header_for, synth_events  # noqa: E402
from dcuscope.protocol.events import EVENT_DTYPE  # noqa: E402
from dcuscope.protocol.wire import PROTOCOL_VERSION, encode_batch  # noqa: E402

NODE = "restarter"
SOURCES = 2
FPS = 25.0
T0 = 1_700_000_000_000_000_000
WARM = 5
"""Restarts after which the relay's memory should be flat (allocator arenas, caches, imports warmed up)."""
MIN_RESTARTS = 10
"""Fewest restarts that leave a slope over restarts WARM..N worth fitting."""
REFUSED = "a second live run under the same name is refused"


def _env(extra: dict[str, str]) -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + os.pathsep + e.get("PYTHONPATH", "")
    e.update(extra)
    return e


class Relay:
    """``python -m dcuscope.relay`` on a free port; ``url`` once it listens."""

    def __init__(self, db: Path | str, silent_s: float, env: dict[str, str]) -> None:
        """``db``: an SQLite file or a PostgreSQL URL."""
        self._errors = tempfile.TemporaryFile()  # not a pipe: nobody reads it while the relay runs
        cmd = [sys.executable, "-m", "dcuscope.relay", "--port", "0", "--db", str(db), "--clock-port", "0",
               "--limit", f"silent_s={silent_s:g}"]
        self.proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(env), stdout=subprocess.PIPE, stderr=self._errors)
        line = self.proc.stdout.readline().decode()
        m = re.search(r"http://127\.0\.0\.1:(\d+)", line)
        if not m:
            self.proc.kill()
            self.proc.wait(15)
            why = self.last_error()
            self._errors.close()
            raise CannotRun(f"the relay did not start: {why}")
        self.url = f"http://127.0.0.1:{m.group(1)}"

    def status(self) -> dict[str, int]:
        """VmRSS, VmHWM (kB) and Threads of the relay process now."""
        out = {}
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM", "Threads"):
                out[key] = int(value.split()[0])
        return out

    def last_error(self) -> str:
        self._errors.seek(0)
        return last_line(self._errors.read())

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._errors.close()


class Node:
    """One run of the node on its own ingest connection."""

    def __init__(self, session: aiohttp.ClientSession, link: Link, acks: asyncio.Queue, run_id: str) -> None:
        self.session, self.link, self.acks, self.run = session, link, acks, run_id

    @classmethod
    async def hello(cls, url: str, run_id: str) -> "Node":
        """Say hello for a new run; ConnectionError (the relay's reason) when it is refused."""
        session = aiohttp.ClientSession()
        acks: asyncio.Queue = asyncio.Queue()
        try:
            link = await Link.open(session, url, None, acks.put_nowait)
            hello = {"proto": PROTOCOL_VERSION, "run": run_id, "header": header_for(NODE, SOURCES).to_dict(), "lost": 0}
            reply = await link.call("hello", hello, 10)
            if not reply.get("ok"):
                raise ConnectionError(str(reply))
        except BaseException:
            await session.close()
            raise
        return cls(session, link, acks, run_id)

    async def ship(self, events: np.ndarray, batch_events: int) -> None:
        """Every batch in flight at once, then every acknowledgement (a node keeps 64 in flight)."""
        batches = [encode_batch(self.run, seq, events[i:i + batch_events], compress=True)
                   for seq, i in enumerate(range(0, len(events), batch_events))]
        for data in batches:
            await self.link.send_batch(data)
        for _ in batches:
            ack = await asyncio.wait_for(self.acks.get(), 60)
            if not ack.get("ok"):
                raise CannotRun(f"the relay refused a batch: {ack}")

    async def close(self) -> None:
        await self.link.close()
        await self.session.close()


async def restart(url: str, deadline_s: float) -> Node:
    """A new run of the node; refused while the former run still holds the node's name (silent_s)."""
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            return await Node.hello(url, uuid.uuid4().hex)
        except ConnectionError as exc:
            if REFUSED not in str(exc) or time.monotonic() > deadline:
                raise CannotRun(f"the relay refused the restarted node: {exc}") from None
        await asyncio.sleep(0.1)


async def soak(relay: Relay, restarts: int, events: np.ndarray, batch_events: int, silent_s: float,
               on_row) -> list[dict]:
    rows = []
    previous: Node | None = None
    async with aiohttp.ClientSession() as http:
        for k in range(restarts + 1):  # run 0 is the node's first start, then ``restarts`` restarts
            t = time.monotonic()
            node = await restart(relay.url, 30 + 4 * silent_s)
            if previous is not None:
                # The relay closed the silent connection as the new run took the name: let go of ours.
                await previous.close()
            await node.ship(events, batch_events)
            # Silent from here on, its connection open: the relay's tick merges what it got meanwhile.
            await asyncio.sleep(silent_s)
            async with http.get(relay.url + "/api/health") as r:
                health = await r.json()
            st = relay.status()
            heap = health.get("heap") or {}
            no_heap = NA("the relay reports no malloc figures: not glibc, or a relay before relay.heap")
            row = {"restart": k, "rss_mb": st["VmRSS"] / 1024, "hwm_mb": st["VmHWM"] / 1024, "threads": st["Threads"],
                   "live_mb": health["memory"]["live_bytes"] / 2**20, "runs": health["runs"],
                   "heap_used_mb": heap["in_use"] / 2**20 if heap.get("available") else no_heap,
                   "heap_free_mb": heap["free"] / 2**20 if heap.get("available") else no_heap,
                   "reclaims": heap.get("reclaims", no_heap), "reclaim_ms": heap.get("last_reclaim_ms", no_heap),
                   "trim_ms": heap.get("last_trim_ms", no_heap),
                   "released": health["released_runs"],
                   "seconds": time.monotonic() - t}
            rows.append(row)
            on_row(row)
            previous = node
        if previous is not None:
            await previous.close()
    return rows


def slope(xs: list[float], ys: list[float]) -> float:
    """Theil-Sen slope of ys over xs: the median of the slopes between every two samples. Memory
    kept across restarts gives it as a least-squares line does; a few samples taken just after a
    reclaim pass (RSS ~12 MB lower for that sample alone) do not tilt it, as they tilt a
    least-squares line when they happen to fall early in the window."""
    x, y = np.asarray(xs, float), np.asarray(ys, float)
    i, j = np.triu_indices(len(x), 1)
    return float(np.median((y[j] - y[i]) / (x[j] - x[i])))


def verdict(rows: list[dict], run_mb: float) -> dict:
    """RSS after restart WARM, the max over WARM..N, growth per restart over WARM..N (Theil-Sen;
    MB and as a share of one run's raw payload), and how much the kernel's high-water mark of the
    relay's RSS rose after restart WARM: the peak of one restart's transients is the same every time,
    so it rises only when memory is kept across restarts, and where a sample falls between the
    relay's reclaim passes (just after a malloc_trim or not) does not move it."""
    after = rows[WARM:]
    rss = [r["rss_mb"] for r in after]
    growth = slope([r["restart"] for r in after], rss)
    hwm = after[-1]["hwm_mb"] - after[0]["hwm_mb"]
    reclaim = [r["reclaim_ms"] for r in rows if not isinstance(r["reclaim_ms"], NA)]
    return {"restarts": rows[-1]["restart"], "rss_start_mb": round(rows[0]["rss_mb"], 1),
            "rss_at_warm_mb": round(rss[0], 1), "rss_max_mb": round(max(rss), 1), "rss_end_mb": round(rss[-1], 1),
            "max_over_warm": round(max(rss) / rss[0], 3),
            "growth_mb_per_restart": round(growth, 3), "run_payload_mb": round(run_mb, 2),
            "growth_per_run_payload": round(growth / run_mb, 4),
            "hwm_growth_mb": round(hwm, 1), "hwm_growth_payloads": round(hwm / run_mb, 2),
            "live_mb_max": round(max(r["live_mb"] for r in rows), 2), "runs_max": max(r["runs"] for r in after),
            "threads_max": max(r["threads"] for r in rows),
            "reclaim_ms_max": max(reclaim) if reclaim else NA("the relay reports no reclaim passes: a relay before "
                                                              "relay.heap")}


HEAD = (f"{'restart':>7} {'RSS MB':>8} {'HWM MB':>8} {'live MB':>8} {'runs':>5} {'malloc used':>11} "
        f"{'malloc free':>11} {'reclaims':>8} {'threads':>7} {'s':>5}")


def _print_row(r: dict, notes: Notes) -> None:
    print(f"{r['restart']:>7} {r['rss_mb']:>8.1f} {r['hwm_mb']:>8.1f} {r['live_mb']:>8.2f} {r['runs']:>5} "
          f"{notes.cell(r['heap_used_mb'], '.1f'):>11} {notes.cell(r['heap_free_mb'], '.1f'):>11} "
          f"{notes.cell(r['reclaims']):>8} {r['threads']:>7} {r['seconds']:>5.1f}", flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--restarts", type=int, default=100, help="times the node restarts (after its first run)")
    p.add_argument("--events", type=int, default=240_000, help="events shipped by each run")
    p.add_argument("--batch-events", type=int, default=60_000, help="events per batch (at most 65,536)")
    p.add_argument("--silent-s", type=float, default=1.0,
                   help="the relay's silent_s: how long the old run holds the node's name (relay default 8)")
    p.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                   help="run the relay with this environment variable (repeatable), e.g. MALLOC_ARENA_MAX=1")
    p.add_argument("--store", choices=STORES, default="sqlite",
                   help="storage engine: an SQLite file, or a PostgreSQL server of the benchmark's own (default sqlite)")
    p.add_argument("--pg-not-durable", action="store_true",
                   help="PostgreSQL with fsync, synchronous_commit and full_page_writes off (as the tests run it), "
                        "not PostgreSQL's defaults; said in the output")
    p.add_argument("--quick", action="store_true", help="a smoke test: 20 restarts of 60,000 events in 15,000-event "
                                                        "batches, silent_s 0.3")
    p.add_argument("--json", action="store_true", help="also print every sample as a JSON line")
    args = p.parse_args(argv)
    if args.quick:
        args.restarts, args.events, args.batch_events, args.silent_s = 20, 60_000, 15_000, 0.3
    if args.restarts < MIN_RESTARTS or args.events < 1 or not 0 < args.batch_events <= 65_536 or args.silent_s <= 0:
        p.error(f"--restarts must be at least {MIN_RESTARTS}, --events and --silent-s positive, --batch-events "
                "within 1..65536")
    env = {}
    for item in args.env:
        name, sep, value = item.partition("=")
        if not sep or not name:
            p.error(f"--env takes NAME=VALUE, not {item!r}")
        env[name] = value
    frames = max(1, args.events // (EVENTS_PER_FRAME * SOURCES))
    events = synth_events(frames, SOURCES, FPS, T0)
    run_mb = len(events) * EVENT_DTYPE.itemsize / 2**20
    print(f"relay soak: {args.restarts} restarts of node {NODE!r}, {len(events)} events a run "
          f"({run_mb:.1f} MiB raw) in batches of {args.batch_events}, compressed; silent_s {args.silent_s:g}"
          + (f"; relay env {' '.join(args.env)}" if args.env else ""), flush=True)
    notes = Notes()
    with tempfile.TemporaryDirectory() as tmp:
        pg = PostgresStore(durable=not args.pg_not_durable) if args.store == "postgresql" else None
        try:
            print(f"store {args.store}: {pg.describe() if pg else SQLITE_SETTINGS}", flush=True)
            print(f"machine: {os.cpu_count()} CPUs, 1-min load {os.getloadavg()[0]:.1f} at start", flush=True)
            print(HEAD, flush=True)
            relay = Relay(pg.new_database() if pg else Path(tmp) / "soak.db", args.silent_s, env)
            try:
                rows = asyncio.run(soak(relay, args.restarts, events, args.batch_events, args.silent_s,
                                        lambda r: (_print_row(r, notes), args.json and print(dumps(r), flush=True))))
            except (OSError, aiohttp.ClientError, asyncio.TimeoutError) as exc:
                raise CannotRun(f"{type(exc).__name__}: {exc}; relay: {relay.last_error()}") from None
            finally:
                relay.stop()
        finally:
            if pg:
                pg.close()
    for line in notes.lines():
        print(line)
    v = verdict(rows, run_mb)
    n = v["restarts"]
    print(f"verdict: RSS {v['rss_start_mb']} MB at start, {v['rss_at_warm_mb']} MB after restart {WARM}, "
          f"max {v['rss_max_mb']} MB over restarts {WARM}..{n} ({v['max_over_warm']} x); growth "
          f"{v['growth_mb_per_restart']} MB/restart (Theil-Sen over {WARM}..{n}) = "
          f"{v['growth_per_run_payload']} x one run's raw payload ({v['run_payload_mb']} MiB); RSS high-water mark "
          f"rose {v['hwm_growth_mb']} MB after restart {WARM} = {v['hwm_growth_payloads']} payloads; the relay counted at most {v['live_mb_max']} MB of live state "
          f"in {v['runs_max']} run(s); longest reclaim pass {fmt(v['reclaim_ms_max'], '.1f', ' ms')}", flush=True)
    print(dumps({"verdict": v, "env": env, "store": args.store}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run(main))
