"""A node given several relays (``--relay URL1,URL2``) moves to the next when its relay dies, and
its run goes on there: same run, same session, every event stored once. A relay that asks the
node to come back later sends it to the next relay after that wait; one that refuses the node
for now (another live run holds its name) is asked again, as with one relay. A list with a bad
item is refused with one clear line.

The failover runs real ``dcuscope relay`` processes, one after the other on one SQLite file (one
relay at a time may hold it), as relays sharing a database would; the node is a real
:class:`RelayExporter` in this process, so that the test knows exactly what it wrote and sees
when it switched.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import threading
import time

import numpy as np
import pytest
from aiohttp import WSCloseCode, WSMsgType, web

from dcuscope.core.clocks import PretendClock
from dcuscope.probes.ship import failover
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.ship.simnode import feed, header_for, synth_events
from dcuscope.protocol import envelope
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.server import start_relay
from dcuscope.relay.store.runs import load_runs
from tests.conftest import run_cli
from tests.ports import free_port
from tests.relay.helpers import RelayProcess, get_json, sort_events, wait_for

SWITCH_WITHIN_S = 10.0


def test_a_node_whose_relay_dies_goes_on_at_the_next_relay_of_its_list(tmp_path, caplog):
    db = tmp_path / "relay.db"
    url_b = f"http://127.0.0.1:{free_port()}"
    relay_a = RelayProcess(db, port=free_port())
    relay_b = None
    # 2 sources at 50 fps for 14 s, written as their time comes: ~1,200 events/s in batches of 256. On a
    # loaded machine relay B's start takes seconds: the node must still be writing when it switches.
    t0 = time.clock_gettime_ns(time.CLOCK_REALTIME) + 200_000_000
    events = synth_events(700, 2, 50.0, t0, drop_rate=0.02)
    exporter = RelayExporter(f"{relay_a.url},{url_b}", "DCU-1", batch_events=256, close_timeout_s=20.0)
    writer = threading.Thread(target=feed, args=(exporter, events), kwargs={"paced": True, "clock": PretendClock()},
                              daemon=True)
    try:
        try:
            with caplog.at_level(logging.WARNING, logger="dcuscope.probes.ship"):
                exporter.start(header_for("DCU-1", 2, t0))
                writer.start()
                wait_for(lambda: exporter.counters()["acked"] > 2000, 20, what="events stored by relay A")
                (at_a,) = get_json(f"{relay_a.url}/api/nodes")
                # A hangs, then dies: the batches sent meanwhile were never acknowledged, and go to B.
                relay_a.proc.send_signal(signal.SIGSTOP)
                time.sleep(0.5)
                relay_a.kill9()
                killed = time.monotonic()
                relay_b = RelayProcess(db, port=int(url_b.rsplit(":", 1)[1]))
                listening = time.monotonic()
                wait_for(lambda: exporter.counters()["relay"] == url_b, SWITCH_WITHIN_S, interval=0.02,
                         what="the node connected to relay B")
                switched = time.monotonic()
                assert writer.is_alive(), "the node had written everything before it switched: no failover under way"
                writer.join(30)
        finally:
            exporter.close(0)
        c = exporter.counters()
        print(f"\nrelay A killed -> relay B listening {listening - killed:.2f} s -> node connected to B "
              f"{switched - listening:.2f} s later: switched {switched - killed:.2f} s after the kill; {c}")
        assert c["connects"] == 2 and c["lost"] == 0 and c["written"] == c["acked"] == len(events), c
        assert c["sent"] > c["written"], "no batch was sent again: the failover resent nothing"
        assert f"connection to relay {relay_a.url} lost; trying {url_b}" in caplog.text
        (at_b,) = wait_for(lambda: [n for n in get_json(f"{url_b}/api/nodes") if n["ended"]], 10, what="end at B")
        assert at_a["run"] == at_b["run"] == exporter.run_id and at_a["session"] == at_b["session"]
        sessions = get_json(f"{url_b}/api/sessions")
        assert len(sessions) == 1 and [r["run"] for r in sessions[0]["runs"]] == [exporter.run_id]
    finally:
        relay_a.stop()
        if relay_b is not None:
            relay_b.stop()
    (run,) = load_runs(db, exporter.run_id, corrected=False)
    assert run.session == at_a["session"]
    stored = sort_events(run.events)
    assert len(stored) == len(events) and len(np.unique(stored)) == len(stored)  # none lost, none twice
    assert np.array_equal(stored, sort_events(events))


class LaterRelay:
    """A relay's ingest endpoint that answers every hello "later", then closes: with ``ok: false``
    and ``retry_ms`` (as a relay whose peer owns the run does, relay.ingest), or with an error
    message saying another relay holds the run."""

    def __init__(self, how: str) -> None:
        self.how, self.hellos = how, []

    async def start(self) -> str:
        app = web.Application()
        app.router.add_get("/ingest", self._ingest)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        port = free_port()
        await web.TCPSite(self._runner, "127.0.0.1", port).start()
        return f"http://127.0.0.1:{port}"

    async def stop(self) -> None:
        await self._runner.cleanup()

    async def _ingest(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        async for msg in ws:
            if msg.type != WSMsgType.TEXT:
                break
            d = json.loads(msg.data)
            if d["type"] != "hello":
                break
            self.hellos.append(time.monotonic())
            owned = f"run {d['data']['run']} is owned by another relay"
            if self.how == "reply":
                await ws.send_str(envelope.reply(d["id"], {"ok": False, "error": owned, "retry_ms": 400}))
            else:
                await ws.send_str(json.dumps({"v": 2, "type": "error", "error": owned, "retry_ms": 400}))
            await ws.close(code=WSCloseCode.TRY_AGAIN_LATER)
        return ws


@pytest.mark.parametrize("how", ["reply", "error"])
def test_a_relay_that_says_another_holds_the_run_is_asked_again_then_the_next(tmp_path, how, monkeypatch):
    """Not a refusal: the node waits what the relay asked and asks it again (the holder lets the run
    go within seconds), up to ELSEWHERE_PATIENCE_S, then tries the next relay."""
    monkeypatch.setattr(failover, "ELSEWHERE_PATIENCE_S", 1.0)

    async def scenario():
        later = LaterRelay(how)
        url_later = await later.start()
        relay = await start_relay(RelayConfig(port=free_port(), db=tmp_path / "r.db"))
        url = f"http://127.0.0.1:{relay.port}"
        exporter = RelayExporter(f"{url_later},{url}", "DCU-1", close_timeout_s=5.0)
        try:
            exporter.start(header_for("DCU-1", 2))
            await until(lambda: exporter.counters()["relay"] == url, 5.0, what="the node at the second relay")
            connected = time.monotonic()
            gaps = np.diff(later.hellos)
            assert len(later.hellos) >= 2 and gaps.min() >= 0.35, later.hellos  # asked again after each wait
            assert connected - later.hellos[0] >= 1.0
            events = synth_events(20, 2, 25.0, 1_700_000_000_000_000_000)
            exporter.write(events)
            await asyncio.to_thread(exporter.close, 0)
            c = exporter.counters()
            assert exporter.refused is None and c["acked"] == len(events) and c["connects"] == 1, c
        finally:
            await relay.stop()
            await later.stop()

    asyncio.run(scenario())


def test_a_relay_that_refuses_the_node_for_now_is_asked_again_not_left(tmp_path):
    """Another live run holds the node's name at relay A: the node asks A again after the backoff,
    as with one relay (the second relay, down, is never tried), and gets in once that run ended."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=free_port(), db=tmp_path / "r.db"))
        url = f"http://127.0.0.1:{relay.port}"
        holder = RelayExporter(url, "DCU-1", close_timeout_s=5.0)
        second = RelayExporter(f"{url},http://127.0.0.1:{free_port()}", "DCU-1", close_timeout_s=5.0,
                               backoff_s=(0.1, 0.5))
        try:
            holder.start(header_for("DCU-1", 2))
            await until(lambda: holder.counters()["connected"], 5.0, what="the first run connected")
            second.start(header_for("DCU-1", 2))
            await until(lambda: "refused this node for now" in second.counters()["last_error"], 5.0, what="refusal")
            await asyncio.sleep(1.0)
            assert second.url == url and "unreachable" not in second.counters()["last_error"]
            await asyncio.to_thread(holder.close, 0)
            await until(lambda: second.counters()["relay"] == url, 5.0, what="the second run at relay A")
            await asyncio.to_thread(second.close, 0)
            assert second.refused is None
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_a_relay_list_with_a_bad_url_is_refused_with_a_clear_error(tmp_path):
    with pytest.raises(ExportError, match=r"relay list 'http://127.0.0.1:1,,http://127.0.0.1:2': item 2 is empty"):
        RelayExporter("http://127.0.0.1:1,,http://127.0.0.1:2", "n")
    with pytest.raises(ExportError, match=r"must start with http:// or https://, not '127.0.0.1:2'"):
        RelayExporter("http://127.0.0.1:1, 127.0.0.1:2", "n")
    assert RelayExporter(" http://127.0.0.1:1/ ,https://relay-b:3000", "n").relays.urls == \
        ("http://127.0.0.1:1", "https://relay-b:3000")
    config = tmp_path / "c.yaml"
    config.write_text("sources:\n  - {test: smpte}\nstages: []\n")
    result = run_cli("run", config, "--relay", "http://127.0.0.1:1,", "-n", "1", cwd=tmp_path, timeout=60)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == ["dcuscope: error: relay list 'http://127.0.0.1:1,': item 2 is empty"]


async def until(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)
