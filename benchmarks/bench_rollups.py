"""A month of one DCU answered from rollups: how long ``dcuscope stats --node --since 30d`` takes, and
what rollups cost on disk per DCU-day, on SQLite and on PostgreSQL.

The store is filled with ``--days`` of rollups of one DCU as compaction writes them: per minute and
per hour, a row per stage and one per frame, at the paper's pace (4,300 events/s: 358 frames a
second, 21,500 a minute). Each minute's sketches are those of one real minute of simulated frames
(``probes.ship.simnode``'s stage delays, each stage's service and wait sketches as large as its
delay's, as a real pipeline's ready points give), drawn from a pool of ``--pool`` minutes; the hours
merge their 60 minutes. Then :func:`dcuscope.relay.store.history.summary` over the last 30 days is timed
(``--repeat`` times, median) in this process, and the CLI as a user runs it (a new process:
Python's start included).

    .venv/bin/python benchmarks/bench_rollups.py [--days 30] [--store sqlite,postgresql] [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.stores import PostgresStore  # noqa: E402
from dcuscope.probes.ship.simnode import header_for, synth_events  # noqa: E402
from dcuscope.relay.rollup.compute import HOUR_NS, MINUTE_NS, rollups_of  # noqa: E402
from dcuscope.relay.store.history import summary  # noqa: E402
from dcuscope.relay.store.base import ROLLUP_VALUES, rollup_values  # noqa: E402
from dcuscope.relay.store.engines import open_database  # noqa: E402

RATE = 4300.0
NODE = "DCU-7"
RUN = "0" * 32


def pool(n: int) -> list[dict]:
    """``n`` minutes of rollups (stage -> Rollup) of simulated frames at the paper's pace."""
    fps = RATE / (12 * 2)
    out = []
    for k in range(n):
        events = synth_events(int(fps * 60), 2, fps, 0, seed=k, drop_rate=0.001)
        rolls = rollups_of(header_for(NODE, 2), events, np.ones(len(events), bool))
        minute = {stage: r for (stage, w, t), r in rolls.items() if w == MINUTE_NS and t == 0}
        for stage, r in minute.items():
            # simnode's frames have no ready point, a real pipeline's do: service and wait sketches
            # as large as the delay's, so that the rows weigh what a real DCU's do.
            if stage and not r.service.count:
                r.service, r.wait = r.delay.copy(), r.delay.copy()
        out.append(minute)
    return out


def fill(db: str, days: int, minutes: list[dict], end_ns: int) -> int:
    """``days`` of rollups ending at ``end_ns`` into ``db``; the rows written."""
    database = open_database(db)
    rng = np.random.default_rng(0)
    sql = database._sql(f"INSERT INTO rollups (node, width_ns, start_ns, stage, run, {', '.join(ROLLUP_VALUES)}) "
                        f"VALUES (%s, %s, %s, %s, %s{', %s' * len(ROLLUP_VALUES)})")
    start = (end_ns - days * 86_400 * 10**9) // HOUR_NS * HOUR_NS
    rows = 0
    try:
        for hour in range(start, end_ns, HOUR_NS):
            batch, merged = [], {}
            for m in range(60):
                t = hour + m * MINUTE_NS
                for stage, r in minutes[int(rng.integers(len(minutes)))].items():
                    batch.append((NODE, MINUTE_NS, t, stage, RUN, *rollup_values(r)))
                    merged[stage] = merged[stage].merge(r) if stage in merged else r
            batch += [(NODE, HOUR_NS, hour, stage, RUN, *rollup_values(r)) for stage, r in merged.items()]
            database._transaction(lambda x: x.executemany(sql, batch))
            rows += len(batch)
    finally:
        database.close()
    return rows


def rollup_bytes(store: str, db: str) -> int:
    if store == "sqlite":
        import sqlite3

        conn = sqlite3.connect(db)
        try:
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            used = conn.execute("SELECT sum(pgsize) FROM dbstat WHERE name LIKE '%rollups%'").fetchone()[0]
        except sqlite3.OperationalError:  # no dbstat: the whole file
            used = Path(db).stat().st_size
        finally:
            conn.close()
        return int(used)
    import psycopg

    with psycopg.connect(db, autocommit=True) as conn:
        conn.execute("VACUUM ANALYZE rollups")
        return int(conn.execute("SELECT pg_total_relation_size('rollups')").fetchone()[0])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--days", type=int, default=30)
    p.add_argument("--store", default="sqlite,postgresql")
    p.add_argument("--pool", type=int, default=20, help="real minutes the rows are drawn from (default 20)")
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args(argv)
    names = [s.strip() for s in args.store.split(",") if s.strip()]
    print(f"simulating {args.pool} minutes at {RATE:g} events/s ...", flush=True)
    minutes = pool(args.pool)
    end = time.time_ns()
    with tempfile.TemporaryDirectory() as tmp:
        pg = PostgresStore() if "postgresql" in names else None
        try:
            for store in names:
                db = pg.new_database() if store == "postgresql" else str(Path(tmp) / "rollups.db")
                t = time.monotonic()
                rows = fill(db, args.days, minutes, end)
                print(f"{store}: {rows:,} rows ({args.days} days of one DCU) written in {time.monotonic() - t:.1f} s",
                      flush=True)
                size = rollup_bytes(store, db)
                times = []
                for _ in range(args.repeat):
                    t = time.perf_counter()
                    doc = summary(db, NODE, end - 30 * 86_400 * 10**9, end)
                    times.append(time.perf_counter() - t)
                frames = doc["frame"]["count"]
                cli = []
                for _ in range(max(1, args.repeat // 2)):
                    t = time.perf_counter()
                    out = subprocess.run([sys.executable, "-m", "dcuscope", "stats", "--db", db, "--node", NODE,
                                          "--since", "30d"], cwd=ROOT, capture_output=True, text=True)
                    cli.append(time.perf_counter() - t)
                    if out.returncode != 0:
                        print(out.stderr, file=sys.stderr)
                        return 1
                print(f"  30 days: {doc['rows']} rows, {frames:,} frames; summary {statistics.median(times):.3f} s "
                      f"(median of {len(times)}), `dcuscope stats --node --since 30d` {statistics.median(cli):.2f} s "
                      f"with Python's start", flush=True)
                print(f"  rollups on disk: {size / 1e6:.1f} MB, {size / args.days / 1e6:.2f} MB per DCU-day", flush=True)
        finally:
            if pg is not None:
                pg.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
