"""Everything timed from a monotonic clock works on a machine booted a moment ago.

``time.monotonic()`` counts from boot: CI runners, new VMs, containers and a DCU just powered on
read small values. A "last time" of 0.0 makes ``now - last >= interval`` false there, and a first
pass meant to be due at once waits until the machine has been up for the interval (the relay's
heap reclaimer, with its test's hour, never ran on a machine up for less than an hour). Each place
that had that pattern (now ``core.clocks.NEVER``) is run here with the clock frozen 1 ms after
boot: what is due at once must then happen with no time passing, while the old code waited for a
time that never came. The page's own clock (``requestAnimationFrame``'s, which starts at 0 as the
page loads) is tested in ``tests/ui/test_nodes_panel.py``.

A frozen clock stops asyncio's timers in this process too: each test does its setting up on the
real clock, freezes, and bounds its waits with ``time.perf_counter`` (not frozen).
"""

from __future__ import annotations

import asyncio
import io
import time
import uuid
from contextlib import contextmanager

import pytest
import socketio

from dcuscope.pipeline.build import build_pipeline
from dcuscope.pipeline.config import load_config
from dcuscope.pipeline.run import Runner
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.wire import encode_batch
from dcuscope.relay import heap
from dcuscope.relay.api.ui import Ticker
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.live.mirror import Mirrors
from dcuscope.relay.server import start_relay
from tests.pipeline.test_run import LIVE_BALL
from tests.relay.helpers import HandNode, RelayProcess, wait_for

YOUNG_S = 0.001
"""The frozen clock: a machine booted 1 ms ago."""
T0 = 1_700_000_000_000_000_000


@pytest.fixture
def young(monkeypatch):
    """``with young():`` freezes ``time.monotonic()`` at YOUNG_S."""
    @contextmanager
    def freeze():
        with monkeypatch.context() as m:
            m.setattr(time, "monotonic", lambda: YOUNG_S)
            yield

    return freeze


async def spin_until(condition, seconds: float = 10.0) -> bool:
    """Let the loop's I/O run (no timers: they stand still with the clock) until ``condition()``."""
    end = time.perf_counter() + seconds
    while not condition() and time.perf_counter() < end:
        await asyncio.sleep(0)
        time.sleep(0.001)
    return condition()


def test_the_heap_reclaimer_is_due_as_soon_as_runs_left_memory(young):
    released = [0]
    with young():
        r = heap.Reclaimer(lambda: released[0], min_interval_s=3600)
        assert not r.due()
        released[0] = 1
        assert r.due()
        r.reclaim()
        released[0] = 2
        assert not r.due()  # the next pass waits its interval


def test_the_relay_ticks_pushes_and_mirrors_from_its_first_moment(tmp_path, young):
    """The ticker's first housekeeping pairs every run, lists the fleet and sends a watching page
    the statistics; its pusher pushes the first new frames at once; a mirror of a stored run is
    read at its first use."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", clock_port=0))
        relay._task.cancel()  # this test ticks by hand, with a ticker that never ticked
        ticker = Ticker(relay.state, relay.ui, relay.fleet, relay.ticker.interest)
        url = f"http://127.0.0.1:{relay.port}"
        run = uuid.uuid4().hex
        page = socketio.AsyncClient(reconnection=False)
        got: dict[str, list] = {"stats": [], "frames": []}
        for event in got:
            page.on(event, (lambda e: lambda data: got[e].append(data))(event), namespace="/ui")
        node = await HandNode.open(url, "DCU-Y", run)
        try:
            await page.connect(url, namespaces=["/ui"], transports=["websocket"], wait_timeout=10)
            assert await spin_until(lambda: relay.ui.wishes), "the page's subscription"
            await node.batch(encode_batch(run, 0, synth_events(40, 1, 25.0, T0), compress=True))
            assert await spin_until(lambda: relay.storage.batches_written >= 1), "the batch stored"
            live = relay.state.runs[run].live
            assert live.visible == 0  # nothing paired it yet
            with young():
                await ticker.housekeeping()
                assert live.visible > 0, "the first tick did not pair"
                assert "DCU-Y" in relay.fleet.views, "the first tick did not list the fleet"
                assert await spin_until(lambda: got["stats"]), "the first tick sent no statistics"

                pusher = asyncio.ensure_future(ticker.pairing.run(ticker.push_frames))
                # Not node.batch: its acknowledgement waits for the store's commit, which waits on a timer.
                await node.link.send_batch(encode_batch(run, 1, synth_events(40, 1, 25.0, T0, first_frame=40), compress=True))
                pushed = await spin_until(lambda: got["frames"])
                pusher.cancel()
                assert pushed, "the first new frames were not pushed"

                mirrors = Mirrors(tmp_path / "r.db", relay.state.live_config, relay.state.run_budget(1))
                try:
                    view = await mirrors.view(run, "DCU-Y", "another relay")
                finally:
                    mirrors.close()
                assert view.live.events > 0, "the mirror was not read at its first use"
        finally:
            await page.disconnect()
            await node.close()
            await relay.stop()

    asyncio.run(scenario())


def test_a_node_ships_its_first_events_at_once_on_an_idle_link(tmp_path, young):
    relay = RelayProcess(tmp_path / "relay.db")
    exporter = RelayExporter(relay.url, "DCU-Y", close_timeout_s=10.0)
    try:
        exporter.start(header_for("DCU-Y", 1))
        wait_for(lambda: exporter.counters()["connected"], 15, what="connection")
        with young():
            exporter.write(synth_events(5, 1, 25.0, T0))
            end = time.perf_counter() + 10
            while exporter.counters()["batches"] == 0 and time.perf_counter() < end:
                time.sleep(0.005)
            assert exporter.counters()["batches"] == 1, "the first events waited for the clock to pass min_flush_s"
    finally:
        exporter.close(0)
        relay.stop()


def test_a_run_reports_its_progress_from_the_first_tick(tmp_path, young):
    config = tmp_path / "ball.yaml"
    config.write_text(LIVE_BALL)
    built = build_pipeline(load_config(config))
    progress = io.StringIO()
    with young():
        result = Runner(built, num_frames=15, progress=progress, progress_every=1.0).run()
    lines = progress.getvalue().splitlines()
    assert result.frames == 15
    assert any(" fps" in line and "frames in" not in line for line in lines), lines  # before the final line
