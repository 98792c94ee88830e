"""A store that survives a server: two relays on a PostgreSQL primary whose commits wait for a
synchronous standby (made with ``pg_basebackup -R``, tests/pgserver.py), reached by a multi-host URL
(``target_session_attrs=read-write``), four paced nodes.

- The standby killed: commits wait for it; each relay cancels them after ``--store-timeout``, holds its
  nodes' batches back ("not stored, retry") without hanging, and says so in /api/health and /metrics;
  the standby back, writes go on.
- The primary killed (``kill -9``) and the standby promoted as docs/store-failover.md's promotion by
  hand says (the SQL of its steps, read from the page and run as written): every node is stored
  again within ``FAILOVER_S`` of the promotion, the time printed. Promoted, the standby still names a
  synchronous standby (it has the primary's postgresql.conf, tests/pgserver.py): until step 4 clears
  it, the relay waits for one and refuses the node's hellos.
- Every run ends stored == sent, nothing stored twice, in one session.

And, on the relay's writer alone: a write whose commit was cancelled (committed on the primary, never
confirmed) is stored once, new to the relay once, and a new run's secret still reaches its node.

docs/store-failover.md says what this guarantees."""

from __future__ import annotations

import asyncio
import re
import time
import urllib.request
import uuid

import psycopg
import pytest

from dcuscope.cli import main as cli_main
from dcuscope.probes.ship.simnode import header_for
from dcuscope.relay.errors import RelayError
from dcuscope.relay.store.base import StoreTimeout
from dcuscope.relay.store.postgres import PostgresDatabase
from dcuscope.relay.store.runs import list_sessions
from dcuscope.relay.store.writer import Storage
from tests.conftest import REPO
from tests.pgserver import STANDBY, PostgresServer
from tests.relay.helpers import (RelayProcess, connected, finish_node, get_json, kill_all, load_node, start_node,
                                 stored_equals_sent, wait_for)

FAILOVER_S = 10
"""The longest from the standby's promotion to every node's events stored again (the issue's goal)."""
STORE_TIMEOUT_S = 1.0
NAMES = [f"DCU-{i}" for i in range(1, 5)]
DOC = REPO / "docs" / "store-failover.md"
BY_HAND = "### Promotion by hand"


def documented_sql() -> dict[int, list[str]]:
    """The SQL of each numbered step of docs/store-failover.md's promotion by hand, as written there
    (its ``sql`` blocks, comments dropped): step -> statements."""
    lines = iter(DOC.read_text(encoding="utf-8").splitlines())
    if BY_HAND not in lines:
        raise AssertionError(f"{DOC.name} has no {BY_HAND!r}")
    steps: dict[int, list[str]] = {}
    step = 0
    for line in lines:
        if line.startswith("#"):
            break  # the next section
        if m := re.match(r"(\d+)\. ", line):
            step = int(m[1])
        elif line.strip().startswith("```"):
            block = []
            for code in lines:
                if code.strip() == "```":
                    break
                block.append(re.sub(r"--.*", "", code))
            if line.strip() == "```sql":
                steps.setdefault(step, []).extend(s.strip() for s in " ".join(block).split(";") if s.strip())
    return steps


def run_sql(server: PostgresServer, statements: list[str]) -> list[tuple]:
    """``statements`` run on ``server`` one after the other in one session, as psql runs them: the
    last one's rows."""
    with psycopg.connect(server.url(), autocommit=True, connect_timeout=3) as conn:
        for statement in statements:
            cursor = conn.execute(statement)
        return cursor.fetchall() if cursor.description else []


def standby_names_set(statements: list[str]) -> str:
    """The ``synchronous_standby_names`` a step's ``ALTER SYSTEM`` sets."""
    setting = re.compile(r"ALTER SYSTEM SET synchronous_standby_names = '(.*)'")
    (value,) = [m[1] for statement in statements if (m := setting.fullmatch(statement))]
    return value


def standby_names(server: PostgresServer, value: str) -> None:
    """``SHOW synchronous_standby_names`` says ``value`` on ``server`` (within a moment: a backend reads
    the file again when the postmaster passes on ``pg_reload_conf()``'s signal, as a person typing
    would not notice)."""
    wait_for(lambda: run_sql(server, ["SHOW synchronous_standby_names"]) == [(value,)], 5,
             what=f"synchronous_standby_names {value!r}")


def stored_counts(server: PostgresServer, database: str) -> dict[str, int]:
    """Each node's events stored, as ``server`` has them."""
    with psycopg.connect(server.url(database), autocommit=True, connect_timeout=3) as conn:
        return dict(conn.execute("SELECT node, events FROM runs").fetchall())


def store_metrics(relay: RelayProcess) -> list[str]:
    with urllib.request.urlopen(f"{relay.url}/metrics", timeout=5) as answer:
        return [line for line in answer.read().decode().splitlines() if line.startswith("dcuscope_relay_store_")]


def health(relay: RelayProcess) -> dict:
    return get_json(f"{relay.url}/api/health", timeout=5)


@pytest.mark.long
def test_a_lost_standby_holds_writes_back_and_a_promoted_one_takes_over_losing_nothing(tmp_path, synchronous_store):
    primary, standby = synchronous_store
    database = primary.new_database().rsplit("/", 1)[1]
    store = (f"postgresql://postgres@127.0.0.1:{primary.port},127.0.0.1:{standby.port}/{database}"
             "?target_session_attrs=read-write")
    relays = [RelayProcess(store, log=tmp_path / f"relay-{n}.log", args=["--store-timeout", str(STORE_TIMEOUT_S)])
              for n in "ab"]
    a, b = relays
    nodes = {}
    try:
        for i, name in enumerate(NAMES):
            order = f"{a.url},{b.url}" if i % 2 == 0 else f"{b.url},{a.url}"  # two on each relay
            nodes[name] = start_node(order, name, tmp_path / f"{name}.npz", frames=3000, fps=20, paced=True, seed=i,
                                     until_stdin=True)
        wait_for(lambda: connected(a) | connected(b) == set(NAMES), 30, what="four nodes streaming")

        # The standby gone: commits wait for it; the relays hold their nodes back, and say why.
        standby.kill9()
        for relay in relays:
            waiting = wait_for(lambda r=relay: (h := health(r))["storage"]["waiting_for_standby"] and h, 15,
                               what="the relay waiting for the store's synchronous standby")
            storage = waiting["storage"]
            assert waiting["ok"] is False and "waiting for the store's synchronous standby" in storage["error"], storage
            print(f"\n{relay.url} /api/health while the standby is gone: ok {waiting['ok']}, storage error "
                  f"{storage['error']!r}, failed writes {storage['failed_writes']}, timeouts {storage['timeouts']}")
        lines = store_metrics(a)
        print("\n".join(["/metrics:", *lines]))
        assert "dcuscope_relay_store_up 0.0" in lines and "dcuscope_relay_store_waiting_for_standby 1.0" in lines
        (standby_timeouts,) = [line for line in lines if 'cause="synchronous_standby"' in line]
        assert float(standby_timeouts.split()[-1]) >= 1, lines
        assert all(relay.alive() for relay in relays) and connected(a) | connected(b) == set(NAMES)  # held, not let go
        time.sleep(1)
        back = time.monotonic()
        standby.resume()
        wait_for(lambda: all(health(r)["ok"] for r in relays), 30, what="both relays storing again")
        print(f"standby back: both relays storing again after {time.monotonic() - back:.1f} s")
        assert "dcuscope_relay_store_waiting_for_standby 0.0" in store_metrics(a)

        # The primary killed as a machine dies, the standby promoted.
        time.sleep(1)
        primary.kill9()
        killed = time.monotonic()
        time.sleep(1)
        steps = documented_sql()
        assert run_sql(standby, steps[3]) == [(True,)]  # SELECT pg_promote()
        promoted = time.monotonic()
        run_sql(standby, steps[4])  # it commits alone: no standby named
        before = stored_counts(standby, database)
        wait_for(lambda: all(stored_counts(standby, database).get(n, 0) > before.get(n, 0) for n in NAMES),
                 FAILOVER_S, what="every node stored again on the promoted standby")
        print(f"failover: primary killed, standby promoted {promoted - killed:.1f} s later; every node stored again "
              f"{time.monotonic() - promoted:.1f} s after the promotion")
        time.sleep(1)
        counters = {name: finish_node(proc, 60) for name, proc in nodes.items()}
    finally:
        kill_all(nodes.values())
        for relay in relays:
            relay.stop()
    for name, c in counters.items():
        assert c["acked"] == c["events"] and c["lost"] == 0, (name, c)
        _, sent = load_node(tmp_path / f"{name}.npz")
        stored_equals_sent(store, name, sent)  # read through the multi-host URL: from the new primary
        print(f"{name}: {len(sent)} events sent, stored once each")
    sessions = list_sessions(store)
    assert len(sessions) == 1 and {r["node"] for r in sessions[0]["runs"]} == set(NAMES)
    for relay in relays:
        log = relay.log.read_text()
        assert "Traceback" not in log, log[-3000:]
        assert "waiting for the store's synchronous standby" in log, log[-3000:]
        # One line when writes start failing and one when they work again, per outage (the standby's, the primary's).
        assert log.count("storage failing") == log.count("storage works again") == 2, log[-3000:]


@pytest.mark.long
def test_the_promotion_by_hand_run_as_documented_stores_every_event_once_and_needs_its_step_4(tmp_path, synchronous_store):
    steps = documented_sql()
    assert {1, 3, 4, 6} <= steps.keys(), f"{DOC.name}, {BY_HAND!r}: SQL for steps {sorted(steps)} only"
    db1, db2 = synchronous_store
    database = db1.new_database().rsplit("/", 1)[1]
    store = (f"postgresql://postgres@127.0.0.1:{db1.port},127.0.0.1:{db2.port}/{database}"
             "?target_session_attrs=read-write")
    relay = RelayProcess(store, log=tmp_path / "relay.log", args=["--store-timeout", str(STORE_TIMEOUT_S)])
    node = start_node(relay.url, "DCU-1", tmp_path / "DCU-1.npz", frames=3000, fps=20, paced=True, until_stdin=True)
    new_db1 = None
    try:
        wait_for(lambda: connected(relay) == {"DCU-1"}, 30, what="the node streaming")
        wait_for(lambda: stored_counts(db1, database).get("DCU-1", 0) > 0, 10, what="the node stored")
        db1.kill9()

        # 1. The primary is gone: nothing streams to db2.
        assert all(status != "streaming" for status, _ in run_sql(db2, steps[1]))
        # 2. Fenced: killed, it stays down. 3. Promoted, db2 takes writes, but holds every commit.
        promoting = time.monotonic()
        assert run_sql(db2, steps[3]) == [(True,)]
        cancelled = wait_for(lambda: health(relay)["storage"]["timeouts"]["synchronous_standby"], 15,
                             what="the relay's commits cancelled, waiting for the promoted server's standby")
        # Said as such, and kept so: the relay's once-a-second probe commits, and waits too (a probe
        # that wrote no WAL came back at once, and said the store worked again).
        wait_for(lambda: health(relay)["storage"]["waiting_for_standby"], 5, what="/api/health: waiting for the standby")
        for _ in range(4):
            h = health(relay)
            assert not h["ok"] and h["storage"]["waiting_for_standby"], h["storage"]
            assert "waiting for the store's synchronous standby" in h["storage"]["error"], h["storage"]
            time.sleep(0.5)
        print(f"\nstep 3 (promoted): a commit cancelled for the synchronous standby after "
              f"{time.monotonic() - promoting:.1f} s")
        assert run_sql(db2, ["SHOW synchronous_standby_names"]) == [(STANDBY,)]  # db1's, copied
        # The node's hellos meanwhile: each one's commit waits, and is cancelled; the node holds its events.
        wait_for(lambda: health(relay)["storage"]["timeouts"]["synchronous_standby"] > cancelled, 10,
                 what="the node's next hello refused, its commit cancelled too")
        assert connected(relay) == set()
        before = stored_counts(db2, database)["DCU-1"]

        # 4. db2 commits alone: the relay takes the node's hello, and stores what it held.
        clearing = time.monotonic()
        run_sql(db2, steps[4])
        standby_names(db2, "")
        wait_for(lambda: stored_counts(db2, database)["DCU-1"] > before, FAILOVER_S, interval=0.05,
                 what="the node stored again on the promoted server")
        stored_again = time.monotonic()
        wait_for(lambda: health(relay)["ok"] and connected(relay) == {"DCU-1"}, 10, what="the relay healthy again")
        print(f"step 4 (synchronous_standby_names cleared): the node stored again {stored_again - clearing:.1f} s "
              f"later, {stored_again - promoting:.1f} s after the promotion")

        # 5. A new standby, named db1 as the page names it; 6. it becomes db2's synchronous standby.
        new_db1 = db2.standby(name="db1")
        run_sql(db2, steps[6])
        standby_names(db2, standby_names_set(steps[6]))
        wait_for(lambda: run_sql(db2, ["SELECT application_name, sync_state FROM pg_stat_replication"])
                 == [("db1", "sync")], 10, what="db1 the synchronous standby")
        synchronous = stored_counts(db2, database)["DCU-1"]
        wait_for(lambda: stored_counts(db2, database)["DCU-1"] > synchronous, 10,
                 what="the node stored, each commit confirmed by db1")
        assert health(relay)["ok"]
        counters = finish_node(node, 60)
    finally:
        kill_all([node])
        relay.stop()
        if new_db1 is not None:
            new_db1.close()
    assert counters["acked"] == counters["events"] and counters["lost"] == 0, counters
    _, sent = load_node(tmp_path / "DCU-1.npz")
    stored_equals_sent(store, "DCU-1", sent)  # read through the multi-host URL: from db2
    print(f"DCU-1: {len(sent)} events sent, stored once each")
    log = relay.log.read_text()
    assert "Traceback" not in log and "waiting for the store's synchronous standby" in log, log[-3000:]


def test_a_cancelled_commit_is_stored_once_new_once_and_a_new_runs_secret_still_reaches_its_node(synchronous_store):
    primary, standby = synchronous_store
    store = primary.new_database()
    header = header_for("N", 1).to_dict()

    async def scenario() -> None:
        storage = Storage(store, name="t", timeout_s=STORE_TIMEOUT_S)
        storage.start(asyncio.get_running_loop())
        try:
            run = uuid.uuid4().hex
            await storage.call("register_run", run, "N", header, None, None)
            assert await storage.call("own_run", run)
            assert await storage.put_batch(run, 0, 3, False, b"abc") is True
            standby.kill9()
            with pytest.raises(RelayError, match="waiting for the store's synchronous standby"):
                await storage.put_batch(run, 1, 3, False, b"def")  # committed on the primary, not confirmed
            assert storage.waiting and storage.timeouts["synchronous_standby"] == 1
            started = time.monotonic()
            for seq in range(2, 6):
                with pytest.raises(RelayError, match="waiting for the store's synchronous standby"):
                    await storage.put_batch(run, seq, 3, False, b"ghi")
            # Refused at once, not each waited out (4 s), though the renewals still try the store.
            assert time.monotonic() - started < 3 * STORE_TIMEOUT_S
            standby.resume()
            while not storage.health()["ok"]:  # the lease renewal's commit came back
                await asyncio.sleep(0.1)
            assert not storage.waiting
            assert await storage.put_batch(run, 1, 3, False, b"def") is True  # found stored: new to the relay, once
            assert await storage.put_batch(run, 1, 3, False, b"def") is False
            assert await storage.put_batch(run, 2, 3, False, b"ghi") is True
        finally:
            storage.stop()

    asyncio.run(scenario())
    with psycopg.connect(store, autocommit=True) as conn:
        assert conn.execute("SELECT events FROM runs").fetchall() == [(9,)]
        assert conn.execute("SELECT seq FROM batches ORDER BY seq").fetchall() == [(0,), (1,), (2,)]

    # A new run's hello whose commit was cancelled: its node, asking again without a secret, gets it.
    database = PostgresDatabase(store, owner="t", timeout_s=STORE_TIMEOUT_S)
    try:
        standby.kill9()
        run = uuid.uuid4().hex
        with pytest.raises(StoreTimeout):
            database.register_run(run, "M", header, None, None)
        standby.resume()
        session, _, secret = wait_for(lambda: _registered(database, run, header), 15, what="the hello again")
        assert secret is not None and database.register_run(run, "M", header, None, secret)[2] is None  # resumes
        with pytest.raises(RelayError, match="takes the secret"):
            database.register_run(run, "M", header, None, None)  # once heard, the secret is needed
    finally:
        database.close()


def _registered(database: PostgresDatabase, run: str, header: dict):
    try:
        return database.register_run(run, "M", header, None, None)
    except StoreTimeout:
        return None


@pytest.mark.parametrize("args, says", [
    (["--store-timeout", "0.1"], "--store-timeout takes 0.5 to 600 seconds, not 0.1"),
    (["--redis", "redis+sentinel://127.0.0.1:26379/0"], "name the Sentinels' service"),
    (["--redis", "redis+sentinel://127.0.0.1/0/dcuscope"], "give each as HOST:PORT"),
    (["--redis", "http://127.0.0.1:6379/0"], "not a Redis URL"),
])
def test_bad_store_and_redis_options_get_a_one_line_error(tmp_path, capsys, args, says):
    assert cli_main(["relay", "--port", "0", "--db", str(tmp_path / "r.db"), *args]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1 and "Traceback" not in err, err
