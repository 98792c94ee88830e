"""RelayExporter: write never blocks, the buffer is bounded, losses are counted; a batch the relay
could not store is sent again, once the hold the relay asks for (growing, capped) has passed;
evicted batches leave no gap at the relay; the probe shipper waits for its close."""

from __future__ import annotations

import asyncio
import json
import math
import subprocess
import sys
import time

import numpy as np
import pytest

from dcuscope.core.gst import Gst
from dcuscope.plugins import framestamp
from dcuscope.probes.capture.shipper import Shipper
from dcuscope.probes.capture.tracer import attach
from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.server import start_relay
from tests.ports import free_port
from tests.relay.helpers import RelayProcess, wait_for
from tests.relay.netcut import CutProxy

T0 = 1_700_000_000_000_000_000


def test_unreachable_relay_write_returns_at_once_and_losses_are_counted():
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    # A write that waited on the network would wait out a round of tries: the backoff (1 s here) or a
    # connect timeout (2 s). The bound sits well below that and well above a loaded machine's hiccup
    # (CI once measured 50.6 ms for a write that never touched the network).
    exporter = RelayExporter(url, "lonely", max_buffer_events=5_000, batch_events=1000, close_timeout_s=1.0,
                             backoff_s=(1.0, 5.0))
    exporter.start(header_for("lonely", 2))
    events = synth_events(2000, 2, 25.0, T0)  # 48,000 events
    worst = 0.0
    for i in range(0, len(events), 500):
        t = time.perf_counter()
        exporter.write(events[i:i + 500])
        worst = max(worst, time.perf_counter() - t)
        time.sleep(0.002)
    assert worst < 0.5, f"write took {worst * 1e3:.1f} ms"
    time.sleep(0.3)
    c = exporter.counters()
    assert not c["connected"] and c["acked"] == 0 and "cannot reach relay" in c["last_error"]
    assert c["buffered"] <= 5_000 + 1000 and c["lost"] >= len(events) - 6_000
    t = time.perf_counter()
    exporter.close(dropped=3)
    assert time.perf_counter() - t < 5.0
    assert exporter.counters()["written"] == len(events)
    delivery = exporter.delivery()
    assert (delivery.events, delivery.stored, delivery.tried) == (len(events), 0, [url]) and not delivery.complete
    assert delivery.line().startswith(f"relay: 0 events stored (acknowledged), {len(events)} not acknowledged; "
                                      f"relays tried: {url}; last error: cannot reach relay {url}")


def test_the_simulated_node_exits_non_zero_when_its_events_were_not_all_acknowledged(tmp_path):
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    node = subprocess.run([sys.executable, "-m", "dcuscope.probes.ship.simnode", "--relay", url, "--node", "lonely",
                           "--frames", "5", "--close-timeout", "1", "--no-spool"], capture_output=True, text=True,
                          timeout=60)
    assert node.returncode == UNACKNOWLEDGED_STATUS, node.stderr
    counters = json.loads(node.stdout.splitlines()[-1])
    assert counters["acked"] == 0 and counters["tried"] == [url]
    assert node.stderr.splitlines()[-1].startswith(f"simnode lonely: relay: 0 events stored (acknowledged), "
                                                   f"{counters['events']} not acknowledged; relays tried: {url}")
    # With its spool (the default), nothing is lost: the events wait on disk, and the node says where.
    spool = tmp_path / "spool"
    node = subprocess.run([sys.executable, "-m", "dcuscope.probes.ship.simnode", "--relay", url, "--node", "lonely",
                           "--frames", "5", "--close-timeout", "1", "--spool", str(spool)], capture_output=True,
                          text=True, timeout=60)
    assert node.returncode == 0, node.stderr
    counters = json.loads(node.stdout.splitlines()[-1])
    assert f"0 not acknowledged; relays tried: {url}; {counters['events']} events kept in the spool ({spool})" \
        in node.stderr.splitlines()[-1]


def test_bad_arguments_are_user_errors():
    with pytest.raises(ExportError, match="http://"):
        RelayExporter("127.0.0.1:3000", "n")
    with pytest.raises(ExportError, match="unknown clock"):
        RelayExporter("http://127.0.0.1:3000", "n", clock="sundial")
    exporter = RelayExporter("http://127.0.0.1:1", "n")
    with pytest.raises(ValueError, match="EVENT_DTYPE"):
        exporter.write(np.zeros(3, np.int64))
    exporter.close(0)  # never started: nothing to do


async def until(predicate, timeout: float = 30.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.05)


def test_batches_evicted_before_the_relay_came_leave_no_gap_in_its_seqs(tmp_path):
    """The relay used to keep every later seq one by one, for the rest of the run, behind the
    gap the evicted batches left."""
    port = free_port()
    exporter = RelayExporter(f"http://127.0.0.1:{port}", "A", max_buffer_events=2_000, batch_events=200,
                             backoff_s=(0.05, 0.2))
    events = synth_events(250, 2, 25.0, T0)  # 6,000 events, 30 batches: the first 20 evicted

    async def scenario():
        exporter.start(header_for("A", 2))
        for i in range(0, len(events), 200):
            exporter.write(events[i:i + 200])
            await until(lambda: exporter.outbox.pending_n == 0, what="a batch cut")  # else write would shed
        assert exporter.lost == exporter.outbox.evicted == 4_000
        relay = await start_relay(RelayConfig(port=port, db=tmp_path / "r.db"))
        try:
            await until(lambda: exporter.counters()["acked"] + exporter.lost == len(events), what="acknowledgements")
            rs = relay.state.runs[exporter.run_id]
            assert rs.live.events == exporter.counters()["acked"] > 0
            assert rs.seqs.held == 0 and rs.seqs.low == 30
            await asyncio.to_thread(exporter.close, 0)
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_batches_evicted_in_flight_count_delivered_if_the_relay_stored_them_else_lost(tmp_path):
    """An evicted batch in flight used to count lost even when the relay had stored it (its
    acknowledgement lost with the connection): the relay then held more than the node said."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db"))
        proxy = CutProxy(relay.port)
        exporter = RelayExporter(proxy.url, "A", max_buffer_events=2_000, batch_events=200, backoff_s=(0.05, 0.2),
                                 close_timeout_s=8.0)
        events = synth_events(500, 2, 25.0, T0)  # 12,000 events

        async def write(part):
            for i in range(0, len(part), 200):
                exporter.write(part[i:i + 200])
                await until(lambda: exporter.outbox.pending_n == 0, what="a batch cut")

        async def reconnect():
            connects = exporter.counters()["connects"]
            proxy.cut("refuse")
            await asyncio.sleep(0.2)
            proxy.restore()
            await until(lambda: exporter.counters()["connects"] > connects, what="a new connection")

        try:
            exporter.start(header_for("A", 2))
            await until(lambda: exporter.counters()["connected"], what="connection")
            rs = relay.state.runs[exporter.run_id]
            # Deaf: every batch reaches the relay, no acknowledgement comes back; 4,000 events
            # against a 2,000-event buffer evict the first 10 batches in flight: doubtful, not lost.
            proxy.cut("deaf")
            await write(events[:4_000])
            await until(lambda: rs.live.events == 4_000, what="the relay storing every batch")
            assert exporter.lost == 0 and len(exporter.outbox.doubtful) == 10
            await reconnect()  # its hello asks; the relay stored all of them
            await until(lambda: exporter.counters()["acked"] == 4_000, what="every batch acknowledged")
            assert exporter.lost == 0 and not exporter.outbox.doubtful
            # Black hole: the batches never reach the relay; the evicted ones, asked about, are lost.
            proxy.cut("blackhole")
            await write(events[4_000:8_000])
            assert exporter.lost == 0 and len(exporter.outbox.doubtful) == 10
            await reconnect()
            await until(lambda: exporter.counters()["acked"] == 6_000, what="the batches kept, resent")
            assert exporter.lost == 2_000 and not exporter.outbox.doubtful
            await write(events[8_000:])
            await asyncio.to_thread(exporter.close, 0)
            c = exporter.counters()
            assert c["acked"] == 10_000 and c["lost"] == 2_000
            assert rs.live.events == c["acked"] and rs.lost == c["lost"] and rs.ended
        finally:
            proxy.close()
            await relay.stop()

    asyncio.run(scenario())


def test_a_batch_the_relay_could_not_store_is_sent_again(tmp_path):
    """An ``ok: false`` acknowledgement used to leave its batch in flight until a 30 s timeout."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db"))
        exporter = RelayExporter(f"http://127.0.0.1:{relay.port}", "A", close_timeout_s=8.0)
        try:
            exporter.start(header_for("A", 2))
            await until(lambda: exporter.counters()["connected"], what="connection")
            await relay.storage.call(lambda d: d.conn.execute("PRAGMA query_only = ON"))  # commits now fail
            events = synth_events(50, 2, 25.0, T0)
            exporter.write(events)
            await until(lambda: "store" in exporter.counters()["last_error"], what="a refused batch")
            await relay.storage.call(lambda d: d.conn.execute("PRAGMA query_only = OFF"))
            await asyncio.to_thread(exporter.close, 0)
            c = exporter.counters()
            assert c["acked"] == len(events) and c["connects"] == 1 and c["lost"] == 0
            assert relay.state.runs[exporter.run_id].live.events == len(events)
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_a_node_holds_its_batches_while_the_relays_storage_fails(tmp_path):
    """Refused batches used to be sent again every 0.1 s for as long as storage failed (a full
    disk): now every batch waits out a hold that grows with each failed round, so each is refused
    at most once per round: 2 + log2(T / 0.1 s) rounds in T seconds, not T / 0.1 s."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db"))
        exporter = RelayExporter(f"http://127.0.0.1:{relay.port}", "A", batch_events=100, close_timeout_s=20.0,
                                 backoff_s=(0.1, 5.0))
        try:
            exporter.start(header_for("A", 2))
            await until(lambda: exporter.counters()["connected"], what="connection")
            await relay.storage.call(lambda d: d.conn.execute("PRAGMA query_only = ON"))  # commits now fail
            events = synth_events(100, 2, 25.0, T0)  # 2,400 events, 24 batches
            exporter.write(events)
            await until(lambda: exporter.counters()["retries"] > 0, what="a refused batch")
            failing_since = time.monotonic()
            await until(lambda: time.monotonic() - failing_since > 2.0, what="2 s of failing storage")
            retries, failing_s = exporter.counters()["retries"], time.monotonic() - failing_since
            await relay.storage.call(lambda d: d.conn.execute("PRAGMA query_only = OFF"))
            await asyncio.to_thread(exporter.close, 0)
            batches = math.ceil(len(events) / 100)  # one write, cut into batches of 100
            rounds = 2 + math.log2(failing_s / 0.1)
            assert retries <= batches * rounds, (retries, batches, failing_s)
            c = exporter.counters()
            assert c["acked"] == len(events) and c["connects"] == 1 and c["lost"] == 0
            assert relay.state.runs[exporter.run_id].live.events == len(events)
        finally:
            await relay.stop()

    asyncio.run(scenario())


def test_the_probe_shipper_waits_for_the_relay_exporters_close(tmp_path):
    """Shipper.stop waited 10 s while the exporter's close could take 15 s: it returned with the
    close still running. Here the relay is black-holed, so close takes all the time it may (its own
    ``close_timeout_s``, which the shipper waits for)."""
    name, rank, cls = framestamp.__gstelementfactory__
    if Gst.ElementFactory.find(name) is None:
        Gst.Element.register(None, name, rank, cls.__gtype__)
    relay = RelayProcess(tmp_path / "relay.db")
    proxy = CutProxy(relay.port)
    try:
        pipe = Gst.parse_launch("videotestsrc num-buffers=30 ! video/x-raw,width=64,height=48 ! "
                                "framestamp source-id=0 ! identity ! fakesink")
        tracer = attach(pipe, "A")
        exporter = RelayExporter(proxy.url, "A", sync_interval_s=60.0, close_timeout_s=12.0)  # nothing ends the link early
        shipper = Shipper(tracer, [exporter]).start()
        wait_for(lambda: exporter.counters()["connected"], 10, what="connection")
        proxy.cut("blackhole")
        pipe.set_state(Gst.State.PLAYING)
        assert pipe.get_bus().timed_pop_filtered(20 * Gst.SECOND, Gst.MessageType.EOS) is not None
        pipe.set_state(Gst.State.NULL)
        shipper.stop()
        assert not shipper._thread.is_alive() and not exporter._thread.is_alive()
        assert exporter.counters()["written"] > 0 and exporter.counters()["acked"] == 0
    finally:
        proxy.close()
        relay.stop()


def test_close_keeps_trying_for_its_timeout_and_says_what_it_waits_for(tmp_path, caplog):
    """The run ends while no relay answers: close goes on trying (saying every CLOSE_SAY_S what it
    waits for), and the relay that comes up meanwhile gets everything and the run's end."""
    port = free_port()
    exporter = RelayExporter(f"http://127.0.0.1:{port}", "late", close_timeout_s=30.0, backoff_s=(0.1, 0.5))
    events = synth_events(50, 2, 25.0, T0)

    async def scenario():
        exporter.start(header_for("late", 2))
        exporter.write(events)
        closing = asyncio.create_task(asyncio.to_thread(exporter.close, 0))
        await asyncio.sleep(6.0)  # longer than CLOSE_SAY_S: it said what it waits for at least once
        assert not closing.done()
        relay = await start_relay(RelayConfig(port=port, db=tmp_path / "r.db"))
        try:
            await closing
            rs = relay.state.runs[exporter.run_id]
            assert rs.ended and rs.written == len(events) and rs.live.events == len(events)
        finally:
            await relay.stop()

    with caplog.at_level("WARNING", logger="dcuscope.probes.ship"):
        asyncio.run(scenario())
    c = exporter.counters()
    assert c["acked"] == len(events) and c["lost"] == 0, c
    said = [r.getMessage() for r in caplog.records if "closing: waiting for" in r.getMessage()]
    assert said and f"{len(events)} events to be acknowledged" in said[0] and "--close-timeout" in said[0], said


def test_a_close_shorter_than_the_last_cut_still_spools_or_counts_every_event(tmp_path):
    """No relay, a 1 MiB spool, 2.9 MB written at once and closed with 50 ms to spare: cutting and spooling
    the last writes takes the exporter's loop longer than that. Every event is still either kept in the
    spool or counted lost (the close timeout is the relay's, not the disk's), and the node says so."""
    from dcuscope.probes.ship.spool import Spool

    exporter = RelayExporter(f"http://127.0.0.1:{free_port()}", "N", close_timeout_s=0.05,
                             spool=Spool(tmp_path / "spool", 1 << 20))
    exporter.start(header_for("N", 4, T0))
    events = synth_events(2500, 4, 30.0, T0)
    exporter.write(events)
    exporter.close(0)
    delivery, spool = exporter.delivery(), Spool(tmp_path / "spool", 1 << 20)
    kept = sum(r.events for r in spool.runs())
    assert exporter.lost > 0 and delivery.spooled == kept
    assert kept + exporter.lost == len(events) == delivery.events, (kept, exporter.lost, len(events))
    assert delivery.unacknowledged == exporter.lost
    assert f"{exporter.lost} not acknowledged" in delivery.line()
