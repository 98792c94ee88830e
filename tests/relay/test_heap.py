"""relay.heap: the reclaim pass after runs leave memory, /api/health's ``heap``, and the run state
a released run leaves behind (benchmarks/bench_relay_soak.py measures the whole over many restarts)."""

from __future__ import annotations

import asyncio
import gc
import uuid
import weakref

import numpy as np
import pytest

from dcuscope.probes.ship.simnode import synth_events
from dcuscope.protocol.wire import encode_batch
from dcuscope.relay import heap
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.server import start_relay
from tests.relay.helpers import HandNode

T0 = 1_700_000_000_000_000_000
GLIBC = heap._TRIM is not None


class _Cycle:
    def __init__(self, nbytes: int) -> None:
        self.data = np.ones(nbytes, np.uint8)
        self.me = self


@pytest.mark.skipif(not GLIBC, reason="malloc_trim and mallinfo2 are glibc's")
def test_heap_view_and_trim_on_glibc():
    view = heap.heap_view()
    assert view["available"] and set(view) == {"available", "arena", "in_use", "free", "mmapped"}
    assert view["in_use"] > 0 and view["arena"] >= view["in_use"]
    assert heap.trim()


def test_a_pass_is_due_only_once_runs_left_memory_and_not_twice_within_the_interval():
    released = [0]
    r = heap.Reclaimer(lambda: released[0], min_interval_s=3600)
    assert not r.due()
    released[0] = 1
    assert r.due()
    r.reclaim()
    assert r.passes == 1 and not r.due()
    released[0] = 2
    assert not r.due()  # within the interval: the next pass waits
    assert set(r.view()) >= {"reclaims", "collected", "last_reclaim_ms", "last_trim_ms", "available"}


def test_a_pass_frees_arrays_held_in_a_reference_cycle():
    """What a relay allocating few large objects may not collect for a long time by itself."""
    gc.disable()
    try:
        cycle = _Cycle(16 << 20)
        ref = weakref.ref(cycle)
        del cycle
        assert ref() is not None  # refcounting alone cannot free it
        released = [0]
        r = heap.Reclaimer(lambda: released[0], min_interval_s=0)
        released[0] += 1
        r.reclaim()
        assert ref() is None and r.collected >= 1
    finally:
        gc.enable()


def test_a_released_run_leaves_memory_at_once_without_a_garbage_collection(tmp_path):
    """A node restarts: its former run is released as the new one says hello, and its live state
    goes then, not at the next full garbage collection (the exporters' callback closed a cycle
    through the run: relay.live.state.RelayState.release breaks it)."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", clock_port=0))
        url = f"http://127.0.0.1:{relay.port}"
        first, second = uuid.uuid4().hex, uuid.uuid4().hex
        nodes = []
        gc.disable()
        try:
            nodes.append(await HandNode.open(url, "A", first))
            assert (await nodes[0].batch(encode_batch(first, 0, synth_events(200, 1, 25.0, T0), compress=True)))["ok"]
            live = weakref.ref(relay.state.runs[first].live)
            await nodes[0].close()
            for _ in range(100):  # until the relay saw the connection go
                if relay.state.runs[first].sid is None:
                    break
                await asyncio.sleep(0.05)
            nodes.append(await HandNode.open(url, "A", second))  # the restarted node: its former run leaves memory
            assert first not in relay.state.runs and relay.state.released == 1
            assert live() is None, [type(r).__name__ for r in gc.get_referrers(live())]
        finally:
            gc.enable()
            for node in nodes:
                await node.close()
            await relay.stop()

    asyncio.run(scenario())


def test_the_ui_ticker_keeps_no_pushed_version_per_run_that_left_memory():
    """Keyed by run, one was added per restart of a node while a page was open, for ever."""
    from dcuscope.relay.api.interest import ALL, Interest
    from dcuscope.relay.api.ui import VERSIONS_SLACK, Ticker

    class State:
        runs = {"kept": object()}
        nodes: dict = {}

        def nodes_view(self) -> list:
            return []

    class Ui:
        async def emit(self, *args, **kwargs) -> None:
            pass

    ticker = Ticker(State(), Ui(), fleet=None, interest=Interest({}))
    ticker._stats_versions = {f"gone-{k}": k for k in range(VERSIONS_SLACK + 10)} | {"kept": 1}
    asyncio.run(ticker._push_stats({ALL: 25}))
    assert ticker._stats_versions == {"kept": 1}
