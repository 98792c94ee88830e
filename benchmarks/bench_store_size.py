"""Bytes per event on disk, and the relay's CPU per event, with and without compaction, side by side.

N paced simulated DCUs (``probes.ship.simnode --paced``, the paper's 4,300 events/s each) feed one
relay for ``--seconds``; the relay is then left until its compaction is done (every batch stored
more than ``--compact-after`` ago moved into segments) and the store is measured from its own sizes:

- SQLite: the file, with its WAL, once the relay stopped, and what of it are free pages (the relay
  gives them back once a quarter of the file or more, keeping 4 MiB for new rows: relay/store/sqlite.py
  ``give_back_space``; ``dcuscope db compact`` gives back all);
- PostgreSQL: ``pg_total_relation_size`` of the tables of events (heap, TOAST and indexes; the
  other tables, of runs and sessions, apart: they do not grow with events), after
  ``VACUUM (INDEX_CLEANUP ON, TRUNCATE ON)`` (what autovacuum does in its own time: the space of deleted batches is reused by new
  ones, and an empty table's tail is given back).

Phases alternate, ``--rounds`` times: this checkout with ``--compact-after 0`` (the layout of
before: batches as they arrived), this checkout compacting, and each ``--checkout DIR`` (another
tree, e.g. a ``git worktree`` of the commit before; its relay runs as it does). Relay CPU is the
relay process's, from the nodes' start until every event is stored and, when compacting, every
due batch compacted; the compaction process's (relay/store/compactor.py, a child of the relay) is
measured over the same time and shown apart.

    .venv/bin/python benchmarks/bench_store_size.py [--nodes 4] [--seconds 60] [--store sqlite,postgresql]
        [--compact-after 5] [--rounds 1] [--checkout DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_relay import EVENTS_PER_FRAME, SOURCES, Relay, Stores, _proc_cpu, start_nodes, wait_nodes  # noqa: E402
from benchmarks.figures import CannotRun  # noqa: E402

RATE = 4300.0
EVENT_TABLES = ("batches", "segments")
"""What is counted per event: PostgreSQL's tables of events; SQLite's file less its free pages, and its WAL."""
"""PostgreSQL's: the others (runs, sessions, leases, the fleet's
rows, each a few pages whatever the events: 1.1 MB in all after a 60 s run of 4 DCUs) are shown apart."""
DAY_S = 86_400


def uncompacted(db: str) -> int:
    """Batches still in the store's ``batches`` table."""
    from dcuscope.relay.store.engines import open_database

    database = open_database(db, create=False)
    try:
        return int(database._rows("SELECT count(*) FROM batches")[0][0])
    finally:
        database.close()


def store_bytes(store: str, db: str) -> dict:
    """The store's size on disk, by part."""
    if store == "sqlite":
        import sqlite3

        conn = sqlite3.connect(db)
        try:
            free = conn.execute("PRAGMA freelist_count").fetchone()[0] * conn.execute("PRAGMA page_size").fetchone()[0]
        finally:
            conn.close()
        wal = Path(db + "-wal")
        return {"file": Path(db).stat().st_size - free, "free_pages": free, "wal": wal.stat().st_size if wal.exists() else 0}
    import psycopg

    with psycopg.connect(db, autocommit=True) as conn:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and conn.execute(  # the relay's backends ending after it did
                "SELECT count(*) FROM pg_stat_activity WHERE datname = current_database() "
                "AND pid <> pg_backend_pid()").fetchone()[0]:
            time.sleep(0.2)
        conn.execute("VACUUM (INDEX_CLEANUP ON, TRUNCATE ON)")  # autovacuum may have left dead items
        rows = conn.execute("SELECT tablename, pg_total_relation_size(quote_ident(tablename)) FROM pg_tables "
                            "WHERE schemaname = 'public'").fetchall()
    return {name: int(size) for name, size in rows}


def phase(label: str, checkout: Path, stores: Stores, store: str, nodes: int, seconds: float, args: list[str],
          compacting: bool) -> dict:
    db = stores.fresh(store)
    relay = Relay(db, args, checkout=checkout)
    try:
        fps = RATE / (EVENTS_PER_FRAME * SOURCES)
        per_node = int(RATE * seconds)
        expected = nodes * (per_node // (EVENTS_PER_FRAME * SOURCES)) * EVENTS_PER_FRAME * SOURCES
        cpu0, own0, t0 = relay.cpu_s(), _proc_cpu(relay.proc.pid), time.monotonic()
        wait_nodes(start_nodes(relay.url, nodes, per_node, paced=True, fps=fps), seconds + 120)
        deadline = time.monotonic() + 120
        while relay.stored() < expected and time.monotonic() < deadline:
            time.sleep(0.2)
        fed_s = time.monotonic() - t0
        if compacting:
            while uncompacted(db) and time.monotonic() < deadline + 300:
                time.sleep(0.5)
        cpu, own = relay.cpu_s() - cpu0, _proc_cpu(relay.proc.pid) - own0
        left = uncompacted(db)
        stored = relay.stored()
    finally:
        relay.stop()
    try:
        sizes = store_bytes(store, db)
    finally:
        stores.done(store, db)
    total = sum(sizes.get(t, 0) for t in (EVENT_TABLES if store == "postgresql" else ("file", "wal")))
    return {"phase": label, "store": store, "events": stored, "expected": expected, "batches_left": left,
            "bytes": sizes, "bytes_per_event": total / max(stored, 1), "relay_cpu_s": own, "fed_s": fed_s,
            "compactor_us_per_event": (cpu - own) / max(stored, 1) * 1e6,
            "all_bytes_per_event": sum(sizes.values()) / max(stored, 1), "relay_us_per_event": own / max(stored, 1) * 1e6,
            "gb_per_dcu_day": total / max(stored, 1) * RATE * DAY_S / 1e9}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--nodes", type=int, default=4)
    p.add_argument("--seconds", type=float, default=60.0, help="how long the DCUs ship (default 60)")
    p.add_argument("--store", default="sqlite,postgresql", help="sqlite, postgresql or both (default both)")
    p.add_argument("--compact-after", type=float, default=5.0,
                   help="the compacting relay's --compact-after (default 5: the run ends soon after)")
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--checkout", action="append", type=Path, default=[],
                   help="another checkout to run beside this one (repeatable), e.g. a `git worktree` of the commit before")
    p.add_argument("--pg-not-durable", action="store_true", help="PostgreSQL without fsync (as the tests run it)")
    p.add_argument("--json", action="store_true", help="also print each phase as a JSON line")
    args = p.parse_args(argv)
    names = [s.strip() for s in args.store.split(",") if s.strip()]
    if not names or set(names) - {"sqlite", "postgresql"}:
        p.error("--store takes sqlite, postgresql or both")
    for c in args.checkout:
        if not (c / "relay" / "__main__.py").is_file():
            p.error(f"--checkout {c}: not a dcuscope checkout")
    runs = [("this, --compact-after 0", ROOT, ["--compact-after", "0"], False),
            (f"this, --compact-after {args.compact_after:g}", ROOT, ["--compact-after", str(args.compact_after)], True),
            *((str(c), c.resolve(), [], False) for c in args.checkout)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        stores = Stores(names, Path(tmp), durable=not args.pg_not_durable)
        try:
            for store in names:
                print(f"{store}: {stores.settings(store)}", flush=True)
                for r in range(args.rounds):
                    for label, checkout, relay_args, compacting in runs:
                        row = phase(label, checkout, stores, store, args.nodes, args.seconds, relay_args, compacting)
                        row["round"] = r + 1
                        rows.append(row)
                        print(f"  {store:10} {label:28} round {r + 1}: {row['events']:>9,} events "
                              f"{row['bytes_per_event']:6.2f} B/event ({row['gb_per_dcu_day']:.2f} GB per DCU-day; "
                              f"all tables {row['all_bytes_per_event']:.2f}), "
                              f"relay {row['relay_us_per_event']:.2f} us/event, compaction process "
                              f"{row['compactor_us_per_event']:.2f}, {row['batches_left']} batches left "
                              f"{'' if row['events'] == row['expected'] else '(expected %d)' % row['expected']}",
                              flush=True)
                        if args.json:
                            print(json.dumps(row), flush=True)
        except CannotRun as exc:
            print(f"cannot run: {exc}", file=sys.stderr)
            return 2
        finally:
            stores.close()
    for store in names:
        base = [x for x in rows if x["store"] == store and x["phase"] == runs[0][0]]
        for label, *_ in runs[1:]:
            mine = [x for x in rows if x["store"] == store and x["phase"] == label]
            b = sum(x["bytes_per_event"] for x in base) / len(base)
            m = sum(x["bytes_per_event"] for x in mine) / len(mine)
            cb = sum(x["relay_us_per_event"] for x in base) / len(base)
            cm = sum(x["relay_us_per_event"] for x in mine) / len(mine)
            cc = sum(x["compactor_us_per_event"] for x in mine) / len(mine)
            print(f"{store}: {label} against --compact-after 0: bytes {m / b:.3f}x ({b:.2f} -> {m:.2f}), "
                  f"relay process CPU {cm / cb:.3f}x ({cb:.2f} -> {cm:.2f} us/event), compaction process "
                  f"{cc:.2f} us/event")
    return 0


if __name__ == "__main__":
    sys.exit(main())
