"""Values that are checked, faults that degrade: a hostile node's clock samples, a database poisoned
by an older relay, a full disk and a compressed flood, each on a real relay process with a
well-behaved node streaming beside (its stored events equal what it sent, its statistics exact)."""

from __future__ import annotations

import asyncio
import errno
import json
import os
import sqlite3
import subprocess
import sys
import time
import uuid

import numpy as np
import pytest

from dcuscope.model.delays import node_stats
from dcuscope.probes.ship.simnode import synth_events
from dcuscope.protocol.wire import HEADER_SIZE, MAX_BATCH_EVENTS, encode_batch
from tests.relay.helpers import (ROOT, HandNode, RelayProcess, assert_stats_equal, env, finish_node, get_json,
                                 http_status, load_node, start_node, wait_for)

I64 = (1 << 63) - 1
MIB = 1024 * 1024


def _good_node_ok(relay: RelayProcess, out, counters: dict, stored_session: int | None = None) -> None:
    """The good node lost nothing and its live (and stored) statistics are exact."""
    assert counters["acked"] == counters["events"] and counters["lost"] == 0, counters
    header, events = load_node(out)
    expected = node_stats(header, events)
    assert_stats_equal(expected, get_json(f"{relay.url}/api/stats?node=good"))
    live = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}["good"]
    assert live["events"] == len(events), live  # not inflated by resends
    if stored_session is not None:
        stored = {n["node"]: n for n in get_json(f"{relay.url}/api/sessions/{stored_session}/nodes")}["good"]
        assert stored["events"] == len(events)  # every event stored, once
        assert_stats_equal(expected, get_json(f"{relay.url}/api/sessions/{stored_session}/stats?node=good"))


def _export(db, session: int, out) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dcuscope", "export", "--db", str(db), "--session", str(session),
                           "-o", str(out)], cwd=ROOT, env=env(), capture_output=True, text=True, timeout=60)


def _session_readable(relay: RelayProcess, session: int) -> dict:
    """Every stored-session route answers 200; returns the session's runs by node."""
    base = f"{relay.url}/api/sessions/{session}"
    for route in ("nodes", "stats?node=good", "frames?node=good&limit=50"):
        assert http_status(f"{base}/{route}") == 200, route
    return {n["node"]: n for n in get_json(f"{base}/nodes")}


async def _forge_clock(url: str) -> None:
    """A hostile node: absurd samples, forged relay times, a replayed pair, an out-of-bounds
    offset on real relay times, and one honest sample (which must count)."""
    evil = await HandNode.open(url, "evil", uuid.uuid4().hex)
    try:
        honest, replayed, far = [await evil.link.call("sync", None, 5) for _ in range(3)]
        now = time.time_ns()
        samples = [
            [-I64, I64, I64, -I64], [-I64, -I64, I64, I64], [I64 - 1, -I64, -I64, I64],
            [now, now + 5_000_000, now + 5_000_001, now + 1_000_000],       # t2/t3 never sent
            [far["t2"] - 10**15, far["t2"], far["t3"], far["t3"] - 10**15 + 1000],   # offset 1e6 s
            [honest["t2"] - 1000, honest["t2"], honest["t3"], honest["t3"] + 1000],  # honest
            [honest["t2"] - 1000, honest["t2"], honest["t3"], honest["t3"] + 1000],  # replayed
        ]
        await evil.link.tell("clock", {"samples": samples, "lost": 0, "floor": 0})
        t2, t3 = replayed["t2"], replayed["t3"]
        await evil.link.tell("clock", {"samples": [[t2 - 10, t2, t3 + 1, t3 + 20]]})  # t3 not the one sent
        assert (await evil.link.call("sync", None, 5))["t2"] > 0 and evil.connected
    finally:
        await evil.close()


def test_forged_clock_samples_are_rejected_and_the_session_stays_readable(tmp_path):
    relay = RelayProcess(tmp_path / "r.db", clock="estimate")
    try:
        good = start_node(relay.url, "good", tmp_path / "good.npz", frames=150, fps=50, paced=True)
        wait_for(lambda: any(n["node"] == "good" for n in get_json(f"{relay.url}/api/nodes")), 20, what="good node")
        asyncio.run(_forge_clock(relay.url))
        nodes = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}
        clock = nodes["evil"]["clock"]
        assert clock["samples"] == 1 and clock["rejected"] == 7 and clock["applied"] == "estimate", clock
        assert abs(clock["correction_ns"]) < 10**9
        health = get_json(f"{relay.url}/api/health")
        assert health["clock_rejected"] == 7 and health["ok"]
        _good_node_ok(relay, tmp_path / "good.npz", finish_node(good, 60), nodes["good"]["session"])
        session = nodes["good"]["session"]
        assert nodes["evil"]["session"] == session
        assert set(_session_readable(relay, session)) == {"good", "evil"}
        done = _export(tmp_path / "r.db", session, tmp_path / "out.json")
        assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
        assert json.loads((tmp_path / "out.json").read_text())
        print(f"\nforged clock: relay peak RSS {relay.peak_rss_mb():.0f} MiB")
    finally:
        relay.stop()
    assert "Traceback" not in relay.log.read_text()


def test_a_database_poisoned_by_an_older_relay_still_loads(tmp_path):
    db = tmp_path / "r.db"
    relay = RelayProcess(db, clock="estimate")
    try:
        procs = [start_node(relay.url, name, tmp_path / f"{name}.npz", frames=60, fps=50, paced=True, seed=k)
                 for k, name in enumerate(("good", "victim"))]
        results = [finish_node(p, 60) for p in procs]
        assert all(r["acked"] == r["events"] for r in results)
    finally:
        relay.stop()
    # What an older relay wrote after a forged sample: a correction beyond int64, and another
    # that fits int64 but would move timestamps out of it.
    with sqlite3.connect(db) as conn:
        run = conn.execute("SELECT id FROM runs WHERE node = 'victim'").fetchone()[0]
        conn.execute("UPDATE runs SET clock = ? WHERE id = ?",
                     (json.dumps({"applied": "estimate", "correction_ns": 2 * I64, "offset_ns": 2 * I64}), run))
    relay = RelayProcess(db, clock="estimate")
    try:
        runs = _session_readable(relay, 1)
        assert runs["victim"]["clock"]["applied"] == "ignored" and "beyond" in runs["victim"]["clock"]["ignored"]
        assert runs["good"]["clock"]["applied"] == "estimate"
        header, events = load_node(tmp_path / "good.npz")
        assert_stats_equal(node_stats(header, events), get_json(f"{relay.url}/api/sessions/1/stats?node=good"))
    finally:
        relay.stop()
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE runs SET clock = ? WHERE id = ?", (json.dumps({"correction_ns": -I64}), run))
    done = _export(db, 1, tmp_path / "out.json")
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    warnings = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(warnings) == 1 and run in warnings[0] and "ignored" in warnings[0], done.stderr


def _fill(path, limit_mb: int) -> None:
    """Write ``path`` until the file system is full (ENOSPC), at most ``limit_mb`` MiB."""
    chunk = b"\xa5" * MIB
    with open(path, "wb", buffering=0) as f:
        for _ in range(limit_mb):
            try:
                f.write(chunk)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
                return
    raise AssertionError(f"{path}: still not full after {limit_mb} MiB")


def test_a_full_disk_degrades_and_nothing_is_lost(tmp_path):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    size_mb = 24
    # The relay's own mount namespace: a small tmpfs over mnt that the host never sees.
    prefix = ["unshare", "-m", "sh", "-c", f'mount -t tmpfs -o size={size_mb}M tmpfs "$0" && exec "$@"', str(mnt)]
    relay = RelayProcess(mnt / "r.db", prefix=prefix, log=tmp_path / "relay.log")
    inside = f"/proc/{relay.proc.pid}/root{mnt}"
    try:
        good = start_node(relay.url, "good", tmp_path / "good.npz", frames=400, fps=50, paced=True)
        wait_for(lambda: {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}.get("good", {}).get("events"),
                 20, what="good node streaming")
        _fill(f"{inside}/fill", size_mb + 1)
        # Batches fail, and a clock report (the node sends one every 2 s) fails to be written too.
        failing = wait_for(lambda: (h := get_json(f"{relay.url}/api/health")).get("storage", {}).get("failed", {})
                           .get("update_run") and h, 20, what="a clock write failing")
        assert failing["ok"] is False and "full" in failing["storage"]["error"], failing
        assert failing["storage"]["failed"]["store batches"] > 0, failing
        live = wait_for(lambda: (n := {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}["good"])["connected"]
                        and n, 5, what="node still connected")
        os.unlink(f"{inside}/fill")
        wait_for(lambda: get_json(f"{relay.url}/api/health")["ok"], 20, what="storage working again")
        counters = finish_node(good, 60)
        assert counters["connects"] == 1, counters  # no reconnect storm
        assert counters["retries"] > 0 and live["events"] < counters["events"]  # held while full
        nodes = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}
        _good_node_ok(relay, tmp_path / "good.npz", counters, nodes["good"]["session"])
        assert nodes["good"]["duplicates"] == 0
        print(f"\ndisk full: relay peak RSS {relay.peak_rss_mb():.0f} MiB, node retries {counters['retries']}")
    finally:
        relay.stop()
    log = relay.log.read_text()
    assert "Traceback" not in log and len(log.splitlines()) <= 10, log[-3000:]


async def _flood(url: str, seconds: float) -> tuple[int, float]:
    """Compressed batches of 65,536 identical events (~1,000:1) on one connection, 4 in flight,
    for ``seconds``; returns the batches acknowledged and the time from first send to last ack."""
    run = uuid.uuid4().hex
    node = await HandNode.open(url, "flood", run, stages=2)
    one = synth_events(1, 1, 25.0, time.time_ns())[:1]
    events = np.repeat(one, MAX_BATCH_EVENTS)
    acked, seq, inflight = 0, 0, 0
    start = last = time.monotonic()
    try:
        while time.monotonic() - start < seconds or inflight:
            while inflight < 4 and time.monotonic() - start < seconds:
                await node.link.send_batch(encode_batch(run, seq, events, compress=True))
                seq, inflight = seq + 1, inflight + 1
            ack = await asyncio.wait_for(node.acks.get(), 30)
            assert ack["ok"], ack
            acked, inflight, last = acked + 1, inflight - 1, time.monotonic()
        assert node.connected
    finally:
        await node.close()
    return acked, last - start


@pytest.mark.parametrize("limits", [("bytes_per_s", "byte_burst"), ("total_bytes_per_s",)])
def test_a_compressed_flood_is_held_to_the_decompressed_byte_rate(tmp_path, limits):
    """One connection's rate, or all connections' together (whose burst is one second of it)."""
    rate = 4 * MIB
    relay = RelayProcess(tmp_path / "r.db", args=[a for name in limits for a in ("--limit", f"{name}={rate}")])
    try:
        good = start_node(relay.url, "good", tmp_path / "good.npz", frames=150, fps=50, paced=True)
        batches, elapsed = asyncio.run(_flood(relay.url, 4.0))
        accepted = batches * (HEADER_SIZE + MAX_BATCH_EVENTS * 24)
        # The burst, the rate over the time measured, and the batch that ran into debt.
        bound = rate + rate * elapsed + HEADER_SIZE + MAX_BATCH_EVENTS * 24
        print(f"\nflood: {accepted / MIB:.1f} MiB accepted in {elapsed:.2f} s (bound {bound / MIB:.1f} MiB); "
              f"relay peak RSS {relay.peak_rss_mb():.0f} MiB")
        assert accepted <= bound and accepted >= rate * elapsed / 2
        assert get_json(f"{relay.url}/api/health")["paused"] > 0
        _good_node_ok(relay, tmp_path / "good.npz", finish_node(good, 60))
    finally:
        relay.stop()
