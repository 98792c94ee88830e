"""Rollups (relay/rollup): the sketch's quantiles within its stated error of the exact order statistics,
merges exact; a run's rollups against exact statistics over the same raw events (counts, means, min,
max exact); gaps stay gaps; `dcuscope stats --node --since` and /api/history answer from them;
retention keeps them apart from raw events."""

from __future__ import annotations

import asyncio
import json
import math
import re
import signal
import time

import numpy as np
import pytest

from dcuscope.model.delays import frame_delays, node_stats, series
from dcuscope.model.frametable import frame_table
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.relay.rollup.compute import HOUR_NS, MINUTE_NS
from dcuscope.relay.rollup.sketch import ALPHA, Sketch, SketchError
from dcuscope.relay.store.compaction import compact
from dcuscope.relay.store.engines import open_database
from dcuscope.relay.store.history import history, summary
from dcuscope.relay.store.writer import Storage
from tests.conftest import run_cli
from tests.relay.helpers import RelayProcess, finish_node, get_json, start_node, wait_for
from tests.relay.store.test_compaction import table_rows, write_run
from tests.relay.store.test_store_engines import store  # noqa: F401 - the engines' fixture

QS = (0.0, 0.01, 0.25, 0.5, 0.9, 0.99, 0.999, 1.0)


def assert_within_bound(sketch: Sketch, values: np.ndarray) -> None:
    """Each quantile within ALPHA of the order statistic of its rank (floor(q * (n - 1)))."""
    ordered = np.sort(np.rint(values))
    for q in QS:
        exact = ordered[math.floor(q * (len(ordered) - 1))]
        got = sketch.quantile(q)
        assert abs(got - exact) <= ALPHA * abs(exact) + 1e-9, (q, got, exact)


@pytest.mark.parametrize("shape", ["lognormal", "uniform", "two modes", "with zeros", "one value"])
def test_sketch_quantiles_are_within_the_stated_error_and_merges_are_exact(shape):
    rng = np.random.default_rng(hash(shape) % 2**32)
    values = {"lognormal": rng.lognormal(16, 1.5, 20_000), "uniform": rng.uniform(1e3, 5e7, 20_000),
              "two modes": np.r_[rng.normal(2e6, 1e5, 15_000), rng.normal(4e7, 2e6, 5_000)],
              "with zeros": np.r_[np.zeros(500), rng.exponential(3e5, 9_500)],
              "one value": np.full(100, 33_000_000.0)}[shape]
    whole = Sketch.of(values)
    assert whole.count == len(values) and whole.total_ns == int(np.rint(values).sum())
    assert (whole.min_ns, whole.max_ns) == (int(np.rint(values).min()), int(np.rint(values).max()))
    assert_within_bound(whole, values)
    parts = np.array_split(rng.permutation(values), 7)
    merged = Sketch()
    for p in parts:
        merged = merged.merge(Sketch.decode(Sketch.of(p).encode()))
    assert merged.encode() == whole.encode()  # any order, any grouping: the same sketch


def test_a_damaged_sketch_is_refused():
    data = Sketch.of(np.arange(1, 1000) * 1e4).encode()
    for bad in (data[:10], data[:-1], data + b"\0", b"\x09" + data[1:]):
        with pytest.raises(SketchError):
            Sketch.decode(bad)
    assert Sketch.decode(b"").count == 0


def test_rollups_agree_with_exact_statistics_over_the_same_raw_events(store):
    """Two runs of one DCU, an hour apart, each compacted in several ranges (frames cross their
    boundaries): counts, means, min and max as the exact statistics; percentiles within the sketch's
    error of the exact order statistics; the hour between them a gap."""
    t0 = (time.time_ns() - 3 * HOUR_NS) // HOUR_NS * HOUR_NS + 30 * 10**9
    a = synth_events(6000, 2, 50.0, t0, seed=1, drop_rate=0.03)  # 2 minutes
    b = synth_events(6000, 2, 50.0, t0 + HOUR_NS, seed=2, drop_rate=0.03)
    for events in (a, b):
        write_run(store, events)
    database = open_database(store)
    try:
        done = compact(database, time.time_ns(), min_events=1)
        assert done.segments == 2
        # A range a sixth of a run: the first run again, its frames crossing six boundaries.
        c, _ = write_run(store, a)
        database.conn.execute(database._sql("UPDATE runs SET node = 'c' WHERE id = %s"), (c,))
        assert compact(database, time.time_ns(), min_events=1, max_events=len(a) // 6 + 1).segments >= 6
    finally:
        database.close()
    header = header_for("a", 2)
    for node, runs in (("a", (a, b)), ("c", (a,))):
        # Exact, over the same raw events: each run paired alone (the runs' frame numbers overlap).
        each = [series(frame_delays(frame_table(header, events))) for events in runs]
        stats = [node_stats(header, events) for events in runs]
        got = summary(store, node, t0 - HOUR_NS, time.time_ns())
        assert got["frame"]["count"] == sum(st["frames"]["complete"] for st in stats)
        assert got["frame"]["incomplete"] == sum(st["frames"]["incomplete"] for st in stats)
        assert list(got["stages"]) == list(stats[0]["stages"])  # pipeline order
        for name in stats[0]["stages"]:
            values = np.concatenate([s.stages[name] for s in each])
            r = got["stages"][name]
            assert r["count"] == len(values)
            assert r["mean_ms"] == pytest.approx(np.rint(values).sum() / len(values) / 1e6, rel=1e-12)
            assert (r["min_ms"], r["max_ms"]) == (values.min() / 1e6, values.max() / 1e6)
            sketch = Sketch.of(values)
            assert [r[k] for k in ("p50_ms", "p90_ms", "p99_ms")] == [sketch.quantile(q) / 1e6 for q in (.5, .9, .99)]
            assert_within_bound(sketch, values)
            assert r["service"]["count"] == sum(len(s.service.get(name, ())) for s in each)
        frames = np.concatenate([s.frame for s in each])
        assert got["frame"]["mean_ms"] == pytest.approx(np.rint(frames).sum() / len(frames) / 1e6, rel=1e-12)
    h = history(store, "a", t0 - HOUR_NS, time.time_ns())
    assert h["width_ns"] == MINUTE_NS
    times = [p["t_ns"] for p in h["frame"]]
    assert len(times) == 6  # 2 minutes and a bit, twice
    assert times[3] - times[2] > 50 * MINUTE_NS  # the gap between the runs: no points
    assert sum(p["frames"] for p in h["frame"]) == summary(store, "a", t0 - HOUR_NS, time.time_ns())["frame"]["count"]


def test_stats_cli_answers_from_rollups_and_says_what_is_exact(tmp_path):
    path = str(tmp_path / "r.db")
    t0 = time.time_ns() - 2 * HOUR_NS
    events = synth_events(3000, 2, 50.0, t0, seed=3)
    write_run(path, events)
    run_cli("db", "compact", path)
    result = run_cli("stats", "--db", path, "--node", "a", "--since", "30d")
    assert result.returncode == 0, result.stderr
    assert "frame (end to end)" in result.stdout and "from the sketch, within 1% of the value" in result.stdout
    doc = json.loads(run_cli("stats", "--db", path, "--node", "a", "--since", "30d", "--json").stdout)
    assert doc["frame"]["count"] == node_stats(header_for("a", 2), events)["frames"]["complete"]
    assert doc["exact"] and doc["from_sketch"] == ["p50_ms", "p90_ms", "p99_ms"] and doc["relative_error"] == ALPHA
    # Nothing stored of that node: which nodes have something.
    nobody = ("nothing stored of node 'nobody' since 1d", "(nodes with data: a)")
    for args, said in ((["--node", "nobody"], nobody), (["--node", "a", "--since", "3q"], ("duration",)),
                       (["--since", "1d"], ("--db PATH|URL --node NAME",))):
        bad = run_cli("stats", "--db", path, *args)
        assert bad.returncode == 2 and all(s in bad.stderr for s in said), bad.stderr


def test_retention_deletes_old_rollups_apart_from_raw_events(store):
    from dcuscope.relay.store.retention import expire_rollups

    events = synth_events(500, 2, 50.0, time.time_ns() - 3 * 86_400 * 10**9, seed=4)
    new = synth_events(500, 2, 50.0, time.time_ns() - HOUR_NS, seed=5)
    write_run(store, events)
    write_run(store, new)
    database = open_database(store)
    compact(database, time.time_ns(), min_events=1)
    database.close()
    before = table_rows(store, "rollups")

    async def scenario():
        s = Storage(store)
        s.start(asyncio.get_running_loop())
        try:
            return await expire_rollups(s, days=2)
        finally:
            s.stop()

    deleted = asyncio.run(scenario())
    assert 0 < deleted < before and table_rows(store, "rollups") == before - deleted
    assert table_rows(store, "segments") == 2  # raw events are raw retention's
    assert summary(store, "a", 0, time.time_ns())["first_ns"] >= time.time_ns() - 2 * HOUR_NS


def _session_and_since(db, nodes) -> tuple[dict, dict]:
    """Per node, the complete frames `stats --session 1` counts and `stats --node --since 1h`'s answer."""
    session = run_cli("stats", "--db", db, "--session", "1", "--json")
    assert session.returncode == 0, session.stderr
    counts = {n: v["frames"]["complete"] for n, v in json.loads(session.stdout)["nodes"].items()}
    since = {}
    for node in nodes:
        answer = run_cli("stats", "--db", db, "--node", node, "--since", "1h", "--json")
        assert answer.returncode == 0, answer.stderr
        since[node] = json.loads(answer.stdout)
    return counts, since


def _two_nodes(relay, tmp_path) -> None:
    """Two paced nodes, 3 s of frames each, finished (every event acknowledged)."""
    nodes = [start_node(relay.url, name, tmp_path / f"{name}.npz", frames=150, fps=50.0, sources=2, paced=True,
                        seed=k) for k, name in enumerate(NODES)]
    for node in nodes:
        finish_node(node)


NODES = ("DCU-1", "DCU-2")


def test_a_relay_stopped_by_ctrl_c_leaves_rollups_that_count_what_its_session_counts(tmp_path):
    """The default --compact-after (60 s): nothing of a few seconds' run is compacted while the relay
    runs. Stopped by SIGINT, it rolls its runs up and says so; `stats --since` and History (a relay
    started again on the store) then count every frame `stats --session` counts."""
    from tests.ui.helpers import RelayThread

    db = tmp_path / "r.db"
    relay = RelayProcess(db)
    _two_nodes(relay, tmp_path)
    relay.proc.send_signal(signal.SIGINT)
    assert relay.proc.wait(30) == 0
    relay.stop()
    last = relay.log.read_text().strip().splitlines()[-2:]
    assert re.fullmatch(r"dcuscope relay: rolled up its runs at stop: [\d,]+ events of [\d,]+ batches into 2 segments "
                        r"in [\d.]+ s \(bound 10 s\); nothing left raw", last[0]), last
    assert last[1] == "dcuscope relay: stopped"
    assert table_rows(str(db), "batches") == 0
    counts, since = _session_and_since(db, NODES)
    again = RelayThread(db)
    try:
        history = {n: get_json(f"{again.url}/api/history?node={n}&since=1h") for n in NODES}
    finally:
        again.stop()
    for node in NODES:
        assert since[node]["frame"]["count"] == counts[node] == 300, (node, since[node]["frame"], counts)
        assert since[node]["raw"]["events"] == 0 and since[node]["raw"]["said"] == ""
        assert history[node]["summary"]["frame"]["count"] == counts[node]
        assert sum(p["frames"] for p in history[node]["history"]["frame"]) == counts[node]


def test_a_killed_relays_raw_tail_is_counted_by_stats_since_and_rolled_up_by_the_next_relay(tmp_path):
    """A relay killed outright (SIGKILL) leaves its runs raw: `stats --since` counts their frames from the
    batches and says which minutes were raw; the next relay rolls them up as it starts, and says so."""
    db = tmp_path / "r.db"
    relay = RelayProcess(db)
    _two_nodes(relay, tmp_path)
    relay.kill9()
    counts, since = _session_and_since(db, NODES)
    for node in NODES:
        raw = since[node]["raw"]
        assert since[node]["frame"]["count"] == counts[node] == 300 and since[node]["rows"] == 0
        assert raw["included"] and raw["events"] > 0 and raw["minutes"] >= 1, raw
        assert re.fullmatch(r"minutes \d\d:\d\d to \d\d:\d\d UTC were still raw \([\d,]+ events not rolled up yet\): "
                            r"counted from the stored batches", raw["said"]), raw
    table = run_cli("stats", "--db", db, "--node", "DCU-1", "--since", "1h")
    assert "  raw: minutes " in table.stdout, table.stdout
    nxt = RelayProcess(db, log=tmp_path / "next.log")
    try:
        wait_for(lambda: table_rows(str(db), "batches") == 0, 30, what="the next relay to roll up what was raw")
    finally:
        nxt.stop()
    assert "rolled up what an earlier relay left raw" in nxt.log.read_text()
    counts_after, since_after = _session_and_since(db, NODES)
    for node in NODES:
        assert since_after[node]["frame"]["count"] == counts_after[node] == counts[node]
        assert since_after[node]["raw"]["events"] == 0 and since_after[node]["rows"] > 0
