"""Relays sharing one PostgreSQL store: failover without loss, one owner per run, one session.
Real relays, real PostgreSQL (tests/pgserver.py), real nodes (``dcuscope run`` pipelines and
simulated nodes). A PostgreSQL restart: tests/relay/test_relay_faults.py; the store's own failover
(a standby promoted, a standby gone): tests/relay/store/test_store_failover.py."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
import uuid

import aiohttp
import pytest

from dcuscope.probes.ship.relaylink import Link
from dcuscope.probes.ship.simnode import header_for
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.relay.store.runs import list_sessions
from tests.conftest import cli_env
from tests.relay.helpers import RelayProcess, connected, get_json, kill_all, stored_equals_sent, wait_for

FAILOVER_S = 10


def node_config(tmp_path, name: str):
    """Two live 15 fps test cameras. (Not live, they ran as fast as the CPU allows: four such nodes
    starved the relays, PostgreSQL and the browser of a 2-core machine for seconds.)"""
    path = tmp_path / f"{name}.yaml"
    path.write_text(f"node: {name}\nsources:\n  - {{test: smpte, width: 160, height: 120, rate: 15, live: true}}\n"
                    "  - {test: ball, width: 160, height: 120, rate: 15, live: true}\n"
                    "stages:\n  - mux: {batch-size: 2, width: 160, height: 120}\n"
                    "  - tiler: {width: 320, height: 120}\n  - convert: {}\n  - osd: {}\n")
    return path


@pytest.mark.long
def test_a_killed_relays_nodes_resume_on_the_other_and_nothing_is_lost_or_stored_twice(tmp_path, pg_url):
    a = RelayProcess(pg_url, log=tmp_path / "a.log")
    b = RelayProcess(pg_url, log=tmp_path / "b.log")
    names = [f"DCU-{i}" for i in range(1, 5)]
    nodes = {}
    try:
        for i, name in enumerate(names):
            order = f"{a.url},{b.url}" if i % 2 == 0 else f"{b.url},{a.url}"  # two on each relay
            cmd = [sys.executable, "-m", "dcuscope.cli", "run", str(node_config(tmp_path, name)), "--probes",
                   "--relay", order, "--trace", str(tmp_path / f"{name}.jsonl"), "--duration", "16", "-q"]
            nodes[name] = subprocess.Popen(cmd, cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True)
        wait_for(lambda: connected(a) | connected(b) == set(names), 60, what="four nodes streaming")
        on_a = connected(a)
        assert on_a == {"DCU-1", "DCU-3"} and connected(b) == {"DCU-2", "DCU-4"}
        # Each sees its peer (the store's description is refreshed every 2 s).
        health = wait_for(lambda: (h := get_json(f"{a.url}/api/health")["storage"])["owned_runs"] == 2 and h, 5,
                          what="relay A's health naming its peer and its two runs")
        assert health["engine"] == "postgresql" and len(health["relays"]) == 2, health
        time.sleep(2)
        a.kill9()
        killed = time.monotonic()
        wait_for(lambda: connected(b) == set(names), FAILOVER_S, what=f"{sorted(on_a)} resumed on relay B")
        print(f"\nfailover: the killed relay's nodes resumed on the other in {time.monotonic() - killed:.1f} s")
        for name, proc in nodes.items():
            _, err = proc.communicate(timeout=120)
            assert proc.returncode == 0, err[-3000:]
    finally:
        kill_all(nodes.values())
        a.stop()
        b.stop()
    sessions = list_sessions(pg_url)
    assert len(sessions) == 1 and {r["node"] for r in sessions[0]["runs"]} == set(names)  # one session, four runs
    for name in names:
        trace = read_trace(tmp_path / f"{name}.jsonl")
        assert len(trace.events) > 500
        stored_equals_sent(pg_url, name, trace.events)


async def hello(url: str, node: str, run: str, secret: str | None = None) -> tuple[dict, aiohttp.ClientSession, Link]:
    session = aiohttp.ClientSession()
    link = await Link.open(session, url, None, lambda ack: None)
    message = {"proto": 2, "run": run, "header": header_for(node, 1).to_dict(), "lost": 0}
    if secret is not None:
        message["secret"] = secret
    return await link.call("hello", message, 10), session, link


def test_two_relays_racing_for_one_run_and_one_session_make_one_owner_and_one_session(tmp_path, pg_url):
    a = RelayProcess(pg_url, log=tmp_path / "a.log")
    b = RelayProcess(pg_url, log=tmp_path / "b.log")

    async def scenario():
        open_ = []
        try:
            # Two new nodes, one on each relay, at the same moment: one session.
            (x, *cx), (y, *cy) = await asyncio.gather(hello(a.url, "X", uuid.uuid4().hex),
                                                      hello(b.url, "Y", uuid.uuid4().hex))
            open_ += [cx, cy]
            assert x["ok"] and y["ok"] and x["session"] == y["session"], (x, y)
            # One run's hello on both at once: one owner; the other is told to try again, not refused.
            run = uuid.uuid4().hex
            (ra, *ca), (rb, *cb) = await asyncio.gather(hello(a.url, "Z", run), hello(b.url, "Z", run))
            open_ += [ca, cb]
            won, lost = (ra, rb) if ra["ok"] else (rb, ra)
            assert won["ok"] and won["session"] == x["session"], (ra, rb)
            assert lost["ok"] is False and lost["retry_ms"] > 0 and "owned by another relay" in lost["error"], lost
            winner, loser = (a, b) if ra["ok"] else (b, a)
            # The owner's node leaves: retried on the other relay, with its secret, it resumes there.
            session, link = ca if ra["ok"] else cb
            await link.close()
            await session.close()

            async def resumed():
                while True:
                    reply, *c = await hello(loser.url, "Z", run, won["secret"])
                    open_.append(c)
                    if reply["ok"]:
                        return reply
                    await asyncio.sleep(reply["retry_ms"] / 1000)

            again = await asyncio.wait_for(resumed(), 10)
            assert again["session"] == won["session"] and "secret" not in again
        finally:
            for session, link in open_:
                await link.close()
                await session.close()

    try:
        asyncio.run(scenario())
        for relay in (a, b):
            refused = get_json(f"{relay.url}/api/health")["refused"]
            assert refused["resume_secret"] == 0 and refused["name_taken"] == 0, refused
    finally:
        a.stop()
        b.stop()
    assert len(list_sessions(pg_url)) == 1
