"""``dcuscope sessions`` and ``dcuscope runs`` over a real store of each engine, written as a relay
writes it (tests/relay/store/test_store_engines.py's way): ids, names, times, frames, states, and one name
per stored run in ``runs``, ``stats --session``, ``compare``'s label and the page's session API."""

from __future__ import annotations

import json
import sqlite3
import time
import uuid

import pytest

from dcuscope.cli import main
from dcuscope.commands.sessions import listing
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.relay.api.sessions import load_session_nodes
from dcuscope.relay.store.base import BatchRow
from dcuscope.relay.store.engines import open_database
from dcuscope.relay.store.runs import run_label
from tests.probes.synth import run_commands
from tests.relay.store.test_store_engines import payload, store  # noqa: F401  (the engines' fixture)

T0 = 1_700_000_000_000_000_000


def write_store(db: str) -> dict[str, str]:
    """Session 1: two ended runs of vm and a run of DCU-1 without an end; session 2: an ended DCU-2.
    Returns the run ids by role."""
    runs = {k: uuid.uuid4().hex for k in ("vm1", "vm2", "dcu1", "dcu2")}
    nodes = {"vm1": "vm", "vm2": "vm", "dcu1": "DCU-1", "dcu2": "DCU-2"}
    database = open_database(db)
    try:
        session = None
        for key in ("vm1", "vm2", "dcu1", "dcu2"):
            if key == "dcu2":  # session 1's runs end (but DCU-1's) and leave: the next run opens session 2
                for k in ("vm1", "vm2"):
                    database.update_run(runs[k], ended_ns=time.time_ns())
                for k in ("vm1", "vm2", "dcu1"):
                    database.disown_run(runs[k])
                session = None
            run = runs[key]
            assert database.own_run(run)
            session = database.register_run(run, nodes[key], header_for(nodes[key], 2).to_dict(), session, None)[0]
            events = synth_events(40, 2, 25.0, T0, drop_rate=0.1, seed=len(key) + ord(key[-1]))
            assert database.put_batches([BatchRow(run, 0, len(events), False, payload(run, 0, events, False))],
                                        time.time_ns()) == [True]
        database.update_run(runs["dcu2"], ended_ns=time.time_ns())
        database.disown_run(runs["dcu2"])
    finally:
        database.close()
    return runs


def test_runs_and_sessions_list_ids_names_times_frames_and_state_and_name_a_run_as_stats_and_the_page(store, capsys):  # noqa: F811
    runs = write_store(store)
    vm1, vm2 = f"vm · run {runs['vm1'][:8]}", f"vm · run {runs['vm2'][:8]}"

    assert main(["runs", "--db", store, "--session", "1", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["run"], r["name"], r["state"]) for r in rows] == [
        (runs["vm1"], vm1, "ended"), (runs["vm2"], vm2, "ended"), (runs["dcu1"], "DCU-1", "live")]
    # frames as `stats --session` counts them, under the same names
    rc, out, err = run_commands("stats", "--db", store, "--session", "1", "--json")
    assert rc == 0, err
    stats = json.loads(out)["nodes"]
    assert list(stats) == [vm1, vm2, "DCU-1"]
    assert [r["frames"] for r in rows] == [stats[r["name"]]["frames"]["complete"] for r in rows]
    assert all(0 < r["frames"] < 80 for r in rows) and all(r["events"] > 0 for r in rows)
    assert all(r["start_ns"] <= r["end_ns"] <= time.time_ns() for r in rows)
    # one run asked for by its id keeps its name; the page's session API and compare's label agree
    rc, out, err = run_commands("stats", "--db", store, "--session", runs["vm2"][:8], "--json")
    assert rc == 0 and list(json.loads(out)["nodes"]) == [vm2], err
    assert [n.node for n in load_session_nodes(store, 1)] == [vm1, vm2, "DCU-1"]
    assert run_label(1, "vm", runs["vm2"], True) == f"session 1 · {vm2}"

    assert main(["sessions", "--db", store, "--json"]) == 0
    sessions = json.loads(capsys.readouterr().out)
    assert [(s["session"], s["nodes"], s["state"], len(s["runs"])) for s in sessions] == [
        (2, ["DCU-2"], "ended", 1), (1, ["vm", "DCU-1"], "live", 3)]
    assert sessions[1]["frames"] == sum(r["frames"] for r in rows)
    # no word from DCU-1 for a minute, and no end: its session was interrupted
    assert listing(store, now_ns=time.time_ns() + 60 * 10**9)[1]["state"] == "interrupted"

    assert main(["sessions", "--db", store]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split()[:3] == ["session", "start", f"({time.strftime('%Z')})"]
    assert table[2].split()[0] == "1" and "vm, DCU-1" in table[2] and table[2].endswith("live")
    assert main(["runs", "--db", store]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[1].split()[:2] == ["2", runs["dcu2"][:8]] and f"  {vm2}  " in table[3]
    assert "run:ID in dcuscope compare" in table[-1]


def test_a_missing_or_foreign_database_or_an_unknown_session_is_one_line_and_exit_2(tmp_path, capsys):
    foreign = tmp_path / "other.sqlite"
    with sqlite3.connect(foreign) as conn:
        conn.execute("CREATE TABLE notes (text)")
    (tmp_path / "text.db").write_text("not a database\n")
    store = str(tmp_path / "r.db")
    write_store(store)
    for argv, says in [(["sessions", "--db", str(tmp_path / "none.db")], "none.db: no such database"),
                       (["runs", "--db", str(foreign)], "not a dcuscope relay database"),
                       (["sessions", "--db", str(tmp_path / "text.db")], "not a usable relay database"),
                       (["runs", "--db", store, "--session", "7"], "has no session 7 (dcuscope sessions --db DB lists"),
                       (["runs", "--db", store, "--session", "x1"], "a session is a number")]:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("dcuscope: error: ") and says in err and err.count("\n") == 1, err
    # the foreign file was read, not written to
    with sqlite3.connect(foreign) as conn:
        assert [r[0] for r in conn.execute("SELECT name FROM sqlite_master")] == ["notes"]
