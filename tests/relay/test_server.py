"""The relay app in-process: per-connection rate bound, takeover of a run, page, CLI wiring."""

from __future__ import annotations

import argparse
import asyncio
import signal
import socket
import struct
import subprocess
import sys
import uuid

import aiohttp
import pytest

from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.simnode import synth_events
from dcuscope.protocol.wire import INGEST_PATH, encode_batch
from dcuscope.relay.commands import add_relay_parser
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.guard.limits import Limits
from dcuscope.relay.server import start_relay
from tests.conftest import wait_until_mapped
from tests.relay.helpers import ROOT, HandNode, RelayProcess, env, get_json

T0 = 1_700_000_000_000_000_000


def test_rate_bound_closes_only_the_offender(tmp_path):
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", limits=Limits(messages_per_s=20, message_burst=40)))
        url = f"http://127.0.0.1:{relay.port}"
        try:
            run_b = uuid.uuid4().hex
            a = await HandNode.open(url, "A", uuid.uuid4().hex)
            b = await HandNode.open(url, "B", run_b)
            for _ in range(80):  # twice the burst, at once
                await a.link.tell("sync", None)
            await asyncio.wait_for(a.link.closed(), 5)
            assert not a.connected and a.link.error == "relay error: rate limit exceeded"
            events = synth_events(10, 1, 25.0, T0)
            reply = await b.batch(encode_batch(run_b, 0, events))
            assert reply == {"v": 2, "type": "ack", "seq": 0, "ok": True} and b.connected and not b.link.error
            for n in (a, b):
                await n.close()
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_a_reconnecting_run_takes_over_its_old_connection(tmp_path):
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db"))
        url = f"http://127.0.0.1:{relay.port}"
        run = uuid.uuid4().hex
        try:
            old = await HandNode.open(url, "A", run)
            new = await HandNode.open(url, "A", run, secret=old.secret)
            await asyncio.wait_for(old.link.closed(), 5)
            assert not old.connected and "superseded" in old.link.error
            events = synth_events(10, 1, 25.0, T0)
            assert (await new.batch(encode_batch(run, 0, events)))["ok"]
            dup = await new.batch(encode_batch(run, 0, events))
            assert dup["ok"] and dup["seq"] == 0 and dup["dup"]
            assert relay.state.runs[run].live.events == len(events) and relay.state.runs[run].duplicates == 1
            for n in (old, new):
                await n.close()
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_connections_beyond_the_cap_are_refused_before_the_upgrade(tmp_path):
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", limits=Limits(connections=1)))
        url = f"http://127.0.0.1:{relay.port}"
        try:
            first = await HandNode.open(url, "A", uuid.uuid4().hex)
            with pytest.raises(ExportError, match="HTTP 503"):
                await HandNode.open(url, "B", uuid.uuid4().hex)
            await first.close()
            for _ in range(100):  # until the relay saw it go
                if relay.state.runs and all(rs.sid is None for rs in relay.state.runs.values()):
                    break
                await asyncio.sleep(0.05)
            again = await HandNode.open(url, "B", uuid.uuid4().hex)
            assert again.connected
            await again.close()
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_a_batch_resent_after_a_storage_failure_counts_once(tmp_path):
    """Events used to reach the live state before storage: a batch storage refused, sent again,
    counted twice."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db"))
        run = uuid.uuid4().hex
        events = synth_events(10, 1, 25.0, T0)
        try:
            node = await HandNode.open(f"http://127.0.0.1:{relay.port}", "A", run)
            await relay.storage.call(lambda d: d.conn.execute("PRAGMA query_only = ON"))  # commits now fail
            refused = await node.batch(encode_batch(run, 0, events))
            assert refused["ok"] is False and refused["seq"] == 0 and node.connected
            assert relay.state.runs[run].live.events == 0
            await relay.storage.call(lambda d: d.conn.execute("PRAGMA query_only = OFF"))
            assert (await node.batch(encode_batch(run, 0, events))) == {"v": 2, "type": "ack", "seq": 0, "ok": True}
            assert relay.state.runs[run].live.events == len(events) and relay.state.runs[run].duplicates == 0
            await node.close()
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_page_and_unknown_routes(tmp_path):
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db"))
        try:
            async with aiohttp.ClientSession() as s:
                async with s.get(f"http://127.0.0.1:{relay.port}/") as r:
                    assert r.status == 200 and r.content_type == "text/html"
                async with s.get(f"http://127.0.0.1:{relay.port}/../relay/server.py") as r:
                    assert r.status in (403, 404)
                async with s.get(f"http://127.0.0.1:{relay.port}/api/frames?node=x&since=abc") as r:
                    assert r.status == 404
                async with s.get(f"http://127.0.0.1:{relay.port}/api/stats") as r:
                    assert r.status == 400 and "node=NAME" in (await r.json())["error"]
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_cli_wiring_and_port_in_use(tmp_path):
    parser = argparse.ArgumentParser(prog="dcuscope")
    add_relay_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["relay", "--port", "0", "--db", "x.db", "--clock", "ptp", "--token", "t"])
    assert (args.port, args.db, args.clock, args.token, args.host) == (0, "x.db", "ptp", "t", "127.0.0.1")
    assert callable(args.func)

    import socket
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        p = subprocess.run([sys.executable, "-m", "dcuscope.relay", "--port", str(port), "--db", str(tmp_path / "r.db")],
                           cwd=ROOT, env=env(), capture_output=True, text=True, timeout=30)
    assert p.returncode == 2 and p.stderr.strip().count("\n") == 0
    assert f"cannot listen on 127.0.0.1:{port}" in p.stderr


def test_a_nodes_newest_run_is_its_current_one(tmp_path):
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db"))
        url = f"http://127.0.0.1:{relay.port}"
        first, second = uuid.uuid4().hex, uuid.uuid4().hex
        events = synth_events(10, 1, 25.0, T0)
        try:
            c1 = await HandNode.open(url, "A", first)
            secret = c1.secret
            assert (await c1.batch(encode_batch(first, 0, events)))["ok"]
            await c1.close()
            await asyncio.sleep(0.2)
            c2 = await HandNode.open(url, "A", second)
            assert relay.state.nodes["A"] == second and first not in relay.state.runs  # the old run left memory
            c1 = await HandNode.open(url, "A", first, secret=secret)  # the old run comes back: from storage
            assert relay.state.runs[first].live.events == len(events) and relay.state.nodes["A"] == second
            # Nothing was live when the second run began: it opened a session of its own.
            assert (relay.state.runs[first].session, relay.state.runs[second].session) == (1, 2)
            for c in (c1, c2):
                await c.close()
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_ctrl_c_while_the_relay_is_starting_stops_it_cleanly(tmp_path):
    """The signal lands while aiohttp is still loading: the relay starts, then stops at once."""
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "relay", "--port", "0", "--db", str(tmp_path / "r.db")],
                            cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wait_until_mapped(proc, "aiohttp")
    proc.send_signal(signal.SIGINT)
    output, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, output
    assert "SIGINT while starting" in output and "dcuscope relay: stopped" in output, output
    assert "Traceback" not in output, output


def test_nodes_that_go_away_during_the_handshake_leave_no_traceback(tmp_path):
    """A node stopped while it connects (the demo stopping its DCUs as they start): the relay's
    handshake answer meets a closed socket, which aiohttp logged as an error with a traceback."""
    relay = RelayProcess(tmp_path / "r.db")
    try:
        request = (f"GET {INGEST_PATH} HTTP/1.1\r\nHost: 127.0.0.1:{relay.port}\r\nUpgrade: websocket\r\n"
                   "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                   "Sec-WebSocket-Version: 13\r\n\r\n").encode()
        for _ in range(200):
            with socket.create_connection(("127.0.0.1", relay.port), timeout=5) as sock:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close = RST
                sock.sendall(request)
        assert get_json(f"{relay.url}/api/health")["ok"]
    finally:
        relay.stop()
    assert "Traceback" not in relay.log.read_text(), relay.log.read_text()[-3000:]
