"""A DCU offline for longer than its close timeout loses nothing (docs/relay.md, "A DCU offline for a
day"): real node processes (``dcuscope run``, the simulated node) spool what no relay acknowledged,
exit, and a later drain (``dcuscope ship --drain``, or the next run in the background) stores every
event once, in the run's own session, at its own times, never shown as the node's live run.

Times are scaled down from the issue's (a relay down for 2 minutes, a run of 30 s): what matters is
that the relay is down for longer than the node's close timeout, which is 1 s here."""

from __future__ import annotations

import asyncio
import json
import re
import urllib.request
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.probes.ship.simnode import synth_events
from dcuscope.probes.ship.spool import Spool
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.protocol.wire import decode_batch
from dcuscope.relay.store.runs import list_sessions, load_runs
from tests.conftest import run_cli
from tests.ports import free_port
from tests.relay.helpers import (HandNode, RelayProcess, finish_node, get_json, load_node, sort_events, start_node,
                                 stored_equals_sent, wait_for)

T0 = 1_790_000_000_000_000_000


def drain(spool: Path, *extra: str) -> subprocess.CompletedProcess:
    return run_cli("ship", "--drain", "--spool", spool, "--close-timeout", "5", *extra, timeout=120)


def drained(db: Path, port: int, spool: Path, node: str) -> tuple[dict, np.ndarray]:
    """Start a relay on ``port`` (store ``db``), drain ``spool`` into it, stop it: ``node``'s stored run
    and its events."""
    relay = RelayProcess(db, port=port)
    try:
        done = drain(spool)
        assert done.returncode == 0, done.stdout + done.stderr
    finally:
        relay.stop()
    assert "Traceback" not in relay.log.read_text()
    run = the_run(db, node)
    (stored,) = load_runs(db, run["run"], corrected=False)
    return run, stored.events


def the_run(db: Path, node: str) -> dict:
    (run,) = [r for s in list_sessions(db) for r in s["runs"] if r["node"] == node]
    return run


def spooled_events(spool: Path) -> np.ndarray:
    """Every event the spool's records hold now (read as a drain reads them; torn tails cut)."""
    s = Spool(spool)
    out = []
    for info in s.runs():
        rs = s.open_run(info.run)
        stages = len(rs.meta["header"]["stages"])
        out += [decode_batch(rs.read(seq), stages).events for seq, _ in rs.pending()]
        rs.close(end_heard=False)
    return np.concatenate(out) if out else np.empty(0)


def test_a_relay_down_longer_than_the_close_timeout_loses_nothing_once_it_is_back(tmp_path):
    """(a) A real pipeline's run ends while its relay is down; it exits saying where its events wait; the
    relay starts; the drain stores every event once, stored == sent event by event (the --trace file)."""
    port, spool, db = free_port(), tmp_path / "spool", tmp_path / "relay.db"
    url = f"http://127.0.0.1:{port}"
    started = time.time_ns()
    result = run_cli("run", "vtest", "-n", "20", "--probes", "--relay", url, "--close-timeout", "1",
                     "--spool", spool, "--trace", tmp_path / "t.jsonl", "--node", "CAR-7", cwd=tmp_path, timeout=180)
    ended = time.time_ns()
    sent = read_trace(tmp_path / "t.jsonl").events
    assert result.returncode == 0, result.stderr  # nothing lost: the events wait on disk
    assert f"0 not acknowledged; relays tried: {url}; {len(sent)} events kept in the spool ({spool}): they will " \
           "be sent when a relay stores again" in result.stderr
    assert "Traceback" not in result.stderr
    listed = run_cli("spool", "--spool", spool)
    assert listed.returncode == 0 and "CAR-7" in listed.stdout and f" {len(sent)} " in listed.stdout, listed.stdout
    time.sleep(1.5)  # the drain comes well after the run ended: its times must be the run's, not the drain's
    relay = RelayProcess(db, port=port)
    try:
        drained = drain(spool)
        assert drained.returncode == 0, drained.stdout + drained.stderr
        assert f"all {len(sent)} events stored" in drained.stdout and "its spool is deleted" in drained.stdout
        assert "the spool" in drained.stdout.splitlines()[-1] and "is empty" in drained.stdout.splitlines()[-1]
        assert [n["node"] for n in get_json(f"{relay.url}/api/nodes")] == []  # stored, not live
    finally:
        relay.stop()
    stored_equals_sent(db, "CAR-7", sent)
    run = the_run(db, "CAR-7")
    assert run["ended_ns"] is not None and started <= run["first_seen_ns"] and run["ended_ns"] <= ended
    assert run["lost"] == 0 and run["written"] == len(sent)
    assert not any(spool.iterdir())  # nothing left behind
    assert "Traceback" not in relay.log.read_text()


def test_a_node_killed_mid_run_has_what_reached_its_spool_delivered_by_the_next_drain(tmp_path):
    """(b) SIGKILL while streaming to a relay: the next drain resumes the run under its secret with a
    relay started again; every event that reached the spool is stored, once; batches stored before
    the kill are not stored twice; the rest (never cut into a batch) counted by the run's end."""
    port, spool, db = free_port(), tmp_path / "spool", tmp_path / "relay.db"
    relay = RelayProcess(db, port=port)
    t0 = time.time_ns() + 500_000_000  # paced from now on: 40 s of frames, killed long before their end
    node = start_node(relay.url, "DCU-K", tmp_path / "n.npz", frames=4000, sources=2, fps=100, paced=True, t0_ns=t0,
                      extra=["--spool", str(spool), "--close-timeout", "1"])
    try:
        wait_for(lambda: get_json(f"{relay.url}/api/nodes") and get_json(f"{relay.url}/api/nodes")[0]["events"] > 3000,
                 60, what="events stored before the kill")
        relay.kill9()  # acknowledgements stop: what follows waits in the spool
        time.sleep(1.0)
        node.send_signal(signal.SIGKILL)
        node.wait(10)
        time.sleep(1.5)  # the relay's port free again (as tests/relay/test_restart.py)
    finally:
        if node.poll() is None:
            node.kill()
    on_disk = spooled_events(spool)
    assert len(on_disk) > 0
    stored_before = the_run(db, "DCU-K")["events"]
    run, events = drained(db, port, spool, "DCU-K")  # a new relay process on the same store
    events = sort_events(events)
    assert len(np.unique(events)) == len(events)  # nothing stored twice
    expected = synth_events(4000, 2, 100.0, t0)
    assert np.isin(events, expected).all()  # nothing invented
    assert np.isin(on_disk, events).all()  # everything the spool held, delivered
    assert len(events) >= stored_before and len(events) > stored_before  # the drain added what the relay lacked
    assert run["ended_ns"] is not None and run["written"] == len(events) and run["lost"] == 0
    print(f"\nkilled node: {stored_before} events stored before the kill, {len(on_disk)} in its spool, "
          f"{len(events)} stored once each after the drain")


def test_a_spool_at_its_bound_drops_the_oldest_counts_them_and_tells_the_relay(tmp_path):
    """(c) 2.9 MB of events into a 1 MiB spool while the relay is down: the oldest are dropped and counted
    lost, the node says so (exit 3), and the drain tells the relay: stored + lost == written."""
    port, spool, db = free_port(), tmp_path / "spool", tmp_path / "relay.db"
    node = start_node(f"http://127.0.0.1:{port}", "DCU-C", tmp_path / "n.npz", frames=2500, sources=4, t0_ns=T0,
                      extra=["--spool", str(spool), "--spool-max", "1M", "--close-timeout", "1"])
    out, err = node.communicate(timeout=120)
    err = err.decode()
    assert node.returncode == UNACKNOWLEDGED_STATUS, err
    counters = json.loads(out.decode().splitlines()[-1])
    _, sent = load_node(tmp_path / "n.npz")
    assert counters["lost"] > 0 and counters["acked"] == 0, counters
    (full,) = [line for line in err.splitlines() if "spool full" in line]  # said once, counted at the end
    assert "the oldest events are dropped" in full and "--spool-max" in full, full
    assert f"{counters['lost']} not acknowledged" in err.splitlines()[-1]
    assert Spool(spool).bytes() <= 1 << 20
    kept = sum(r.events for r in Spool(spool).runs())
    assert kept + counters["lost"] == len(sent) == counters["events"], (kept, counters)
    run, stored = drained(db, port, spool, "DCU-C")
    assert run["lost"] == counters["lost"] and run["events"] == kept and run["written"] == len(sent)
    newest = sort_events(sent)[-1000:]
    assert np.isin(newest, stored).all()  # the newest kept, the oldest gone
    assert not np.isin(sort_events(sent)[:1000], stored).any()


def test_a_torn_tail_is_cut_said_and_the_rest_delivered(tmp_path):
    """(d) A crash mid-write leaves half a record: the drain cuts it, says so in one line, delivers the
    rest; a spooled run whose run.json is unreadable is one line, the others still go."""
    port, spool, db = free_port(), tmp_path / "spool", tmp_path / "relay.db"
    node = start_node(f"http://127.0.0.1:{port}", "DCU-T", tmp_path / "n.npz", frames=200, sources=2, t0_ns=T0,
                      extra=["--spool", str(spool), "--close-timeout", "1", "--batch-events", "500"])
    finish_node(node, 60)
    (folder,) = [p for p in spool.iterdir() if p.is_dir()]
    (segment,) = folder.glob("*.seg")
    whole = spooled_events(spool)
    segment.write_bytes(segment.read_bytes()[:-300])  # the last record torn
    kept = spooled_events(spool)
    assert 0 < len(kept) < len(whole) and np.array_equal(kept, whole[:len(kept)])
    junk = spool / ("e" * 32)
    junk.mkdir()
    (junk / "run.json").write_text("{not json")
    relay = RelayProcess(db, port=port)
    try:
        drained = drain(spool)
    finally:
        relay.stop()
    out = drained.stdout + drained.stderr
    assert "Traceback" not in out
    assert f"{junk / 'run.json'}" in out  # said, skipped
    assert drained.returncode == 0, out
    (stored,) = load_runs(db, the_run(db, "DCU-T")["run"], corrected=False)
    assert np.array_equal(sort_events(stored.events), sort_events(kept))


def test_the_next_run_drains_earlier_runs_in_the_background_and_says_so(tmp_path):
    port, spool, db = free_port(), tmp_path / "spool", tmp_path / "relay.db"
    first = start_node(f"http://127.0.0.1:{port}", "DCU-B", tmp_path / "a.npz", frames=100, sources=2, t0_ns=T0,
                       extra=["--spool", str(spool), "--close-timeout", "1"])
    finish_node(first, 60)
    _, earlier = load_node(tmp_path / "a.npz")
    relay = RelayProcess(db, port=port)
    try:
        # 8 s of frames, paced in real time: the drain (a daemon thread, cut when the node exits: what it did
        # not send stays spooled) has time to end on a loaded machine too (CI once saw the run end first).
        second = start_node(relay.url, "DCU-B", tmp_path / "b.npz", frames=400, sources=2, fps=50, paced=True,
                            t0_ns=time.time_ns() + 500_000_000, seed=1, extra=["--spool", str(spool), "--close-timeout", "10"])
        out, err = second.communicate(timeout=120)
        assert second.returncode == 0, err.decode()
        assert "spool: sending 1 earlier run(s), " in err.decode()
        runs = wait_for(lambda: (lambda runs: runs if len(runs) == 2 and all(r["ended_ns"] for r in runs) else None)(
            [r for s in list_sessions(db) for r in s["runs"]]), 30, what="both runs stored and ended")
        nodes = get_json(f"{relay.url}/api/nodes")
        assert [n["run"] for n in nodes] == [json.loads(out.decode().splitlines()[-1])["run"]]  # the live one
        assert isinstance(nodes[0]["spool_bytes"], int)  # it said what its spool holds
    finally:
        relay.stop()
    _, later = load_node(tmp_path / "b.npz")
    by_size = sorted(runs, key=lambda r: r["events"])
    assert [r["events"] for r in by_size] == [len(earlier), len(later)]
    (stored,) = load_runs(db, by_size[0]["run"], corrected=False)
    assert np.array_equal(sort_events(stored.events), sort_events(earlier))
    sessions = {r["run"]: s["session"] for s in list_sessions(db) for r in s["runs"]}
    assert sessions[by_size[0]["run"]] != sessions[by_size[1]["run"]]  # the drained run in a session of its own


def test_a_full_disk_is_one_line_and_the_run_goes_on_in_memory(tmp_path):
    """(bad input) The spool on a file system that fills: one line saying so, no traceback; what
    reached the disk is kept, the rest of the run in memory only (lost, with its relay down)."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    port = free_port()
    prefix = ["unshare", "-m", "sh", "-c", 'mount -t tmpfs -o size=256k tmpfs "$0" && exec "$@"', str(mnt)]
    node = start_node(f"http://127.0.0.1:{port}", "DCU-F", tmp_path / "n.npz", frames=2000, sources=2, t0_ns=T0,
                      prefix=prefix, extra=["--spool", str(mnt / "spool"), "--spool-max", "64M", "--close-timeout", "1"])
    out, err = node.communicate(timeout=120)
    err = err.decode()
    assert node.returncode == UNACKNOWLEDGED_STATUS, err
    assert "Traceback" not in err
    full = [line for line in err.splitlines() if "could not be written: No space left on device" in line]
    assert len(full) == 1 and "goes on in memory only" in full[0], err
    counters = json.loads(out.decode().splitlines()[-1])
    m = re.search(r"relay: 0 events stored \(acknowledged\), (\d+) not acknowledged; .* (\d+) events kept in the spool",
                  err.splitlines()[-1])
    assert m and int(m[1]) > 0 and int(m[2]) > 0 and int(m[1]) + int(m[2]) == counters["events"], err


@pytest.mark.long
def test_a_store_whose_standby_is_gone_longer_than_the_close_timeout_loses_nothing_once_it_returns(
        tmp_path, synchronous_store):
    """(e) The store's synchronous standby gone while a node's run ends: its relay cannot commit, the node's
    close timeout passes, its events wait in the spool; the standby back, the run is drained through
    another relay of the store (the first one gone, its lease on the run expired): stored == sent."""
    primary, standby = synchronous_store
    store = primary.new_database()
    spool = tmp_path / "spool"
    first = RelayProcess(store, log=tmp_path / "a.log", args=["--store-timeout", "1"])
    # 12 s of frames: the standby goes at the first commit, long before the run ends, on a loaded machine too
    # (with 3 s, CI once saw every batch committed before the standby was gone).
    node = start_node(first.url, "DCU-S", tmp_path / "n.npz", frames=600, sources=2, fps=50, paced=True,
                      t0_ns=time.time_ns() + 500_000_000, extra=["--spool", str(spool), "--close-timeout", "1"])
    try:
        wait_for(lambda: get_json(f"{first.url}/api/nodes") and get_json(f"{first.url}/api/nodes")[0]["events"] > 0,
                 30, what="the node stored before the standby goes")
        standby.kill9()
        assert node.poll() is None, "the run ended before the standby went: nothing was left to spool"
        out, err = node.communicate(timeout=60)
        err = err.decode()
        assert node.returncode == 0, err
        counters = json.loads(out.decode().splitlines()[-1])
        assert 0 < counters["spooled"] and counters["acked"] + counters["spooled"] == counters["events"], counters
        assert f"{counters['spooled']} events kept in the spool ({spool})" in err.splitlines()[-1]
    finally:
        first.kill9()
        if node.poll() is None:
            node.kill()
    standby.resume()
    second = RelayProcess(store, log=tmp_path / "b.log")
    try:
        drained = run_cli("ship", "--drain", "--spool", spool, "--relay", second.url, "--close-timeout", "30",
                          timeout=120)
        assert drained.returncode == 0, drained.stdout + drained.stderr
    finally:
        second.stop()
    _, sent = load_node(tmp_path / "n.npz")
    stored_equals_sent(store, "DCU-S", sent)
    assert "Traceback" not in second.log.read_text()


def test_a_nodes_spool_shows_in_its_node_view_and_metrics_and_malformed_facts_are_dropped(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db")
    hour_ago = time.time_ns() - 3600 * 10**9

    async def nodes() -> tuple[dict, dict, str]:
        good = await HandNode.open(relay.url, "DCU-P", "f" * 32, extra={"spool": {"bytes": 123456, "oldest_ns": hour_ago}})
        bad = await HandNode.open(relay.url, "DCU-Q", "e" * 32, extra={"spool": {"bytes": "lots", "oldest_ns": -5}})
        try:
            views = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}
            with urllib.request.urlopen(f"{relay.url}/metrics", timeout=10) as answer:
                metrics = answer.read().decode()
            assert good.connected and bad.connected  # facts it cannot read are dropped, the node kept
        finally:
            await good.close()
            await bad.close()
        return views["DCU-P"], views["DCU-Q"], metrics

    try:
        good, bad, metrics = asyncio.run(nodes())
    finally:
        relay.stop()
    assert good["spool_bytes"] == 123456 and 3590 < good["spool_oldest_age_s"] < 3700, good
    assert bad["spool_bytes"] is None and bad["spool_oldest_age_s"] is None, bad
    assert 'dcuscope_node_spool_bytes{node="DCU-P"} 123456.0' in metrics
    (age,) = [line for line in metrics.splitlines() if line.startswith('dcuscope_node_spool_oldest_age_seconds{node="DCU-P"}')]
    assert 3590 < float(age.split()[-1]) < 3700
    assert 'node="DCU-Q"' not in "".join(line for line in metrics.splitlines() if "spool" in line)


def test_a_spool_folder_that_cannot_be_used_is_one_line_and_the_run_goes_on_in_memory(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    node = start_node(f"http://127.0.0.1:{free_port()}", "DCU-U", tmp_path / "n.npz", frames=20, sources=1,
                      extra=["--spool", str(tmp_path / "file" / "spool"), "--close-timeout", "1"])
    out, err = node.communicate(timeout=60)
    err = err.decode()
    assert node.returncode == UNACKNOWLEDGED_STATUS and "Traceback" not in err, err
    (said,) = [line for line in err.splitlines() if "spool" in line and "kept in memory only" in line]
    assert f"the spool folder {tmp_path / 'file' / 'spool'} cannot be used: Not a directory" in said
    counters = json.loads(out.decode().splitlines()[-1])
    assert f"{counters['events']} not acknowledged" in err.splitlines()[-1]
