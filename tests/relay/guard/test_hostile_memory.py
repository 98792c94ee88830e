"""Memory bombs (issue 12, item 3): well-formed input that used to take the relay to gigabytes.

Each test runs a real relay process with a well-behaved simulated node streaming beside the
attacker; the node's statistics stay exact and everything it sent is acknowledged, the relay's
resident memory stays under RSS_BOUND_MB throughout (its kernel high-water mark), and
``/api/health`` keeps answering.
"""

from __future__ import annotations

import asyncio
import threading
import time
import urllib.error
import uuid

import numpy as np
import pytest

from dcuscope.model.delays import node_stats
from dcuscope.protocol.events import ENTER, EVENT_DTYPE, TraceHeader
from dcuscope.protocol.wire import SOURCE_LIMIT, encode_batch
from tests.relay.helpers import (HandNode, RelayProcess, assert_stats_equal, finish_node, get_json, load_node,
                                 start_node, wait_for)

RSS_BOUND_MB = 300
HEALTH_BOUND_S = 2.0
T0 = 1_700_000_000_000_000_000


class Watch:
    """Polls /api/health in a thread while an attack runs: its slowest answer and the relay's RSS."""

    def __init__(self, relay: RelayProcess) -> None:
        self.relay, self.slowest, self.failures = relay, 0.0, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            t = time.monotonic()
            try:
                get_json(f"{self.relay.url}/api/health", timeout=10)
            except (OSError, urllib.error.URLError) as exc:
                self.failures.append(repr(exc))
            self.slowest = max(self.slowest, time.monotonic() - t)
            self._stop.wait(0.1)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(15)


def _good_node(relay: RelayProcess, tmp_path):
    return start_node(relay.url, "good", tmp_path / "good.npz", frames=240, sources=4, fps=60, paced=True, seed=3)


def _check_good_node(relay: RelayProcess, proc, tmp_path) -> None:
    counters = finish_node(proc, 60)
    assert counters["acked"] == counters["events"] and counters["lost"] == 0, counters
    header, events = load_node(tmp_path / "good.npz")
    assert_stats_equal(node_stats(header, events), get_json(f"{relay.url}/api/stats?node=good"))


def _check_memory(relay: RelayProcess, watch: Watch, what: str) -> dict:
    watch.stop()
    peak = relay.peak_rss_mb()
    print(f"\n{what}: relay peak RSS {peak:.0f} MiB, slowest /api/health {watch.slowest:.2f} s")
    assert relay.alive()
    assert peak < RSS_BOUND_MB, f"{what}: relay peak RSS {peak:.0f} MiB"
    assert not watch.failures and watch.slowest < HEALTH_BOUND_S, (watch.slowest, watch.failures[:3])
    health = get_json(f"{relay.url}/api/health")
    memory = health["memory"]
    assert 0 < memory["live_bytes"] <= memory["live_budget_bytes"], memory
    return health


def _bomb(run: str, seq: int, stages: int, n: int = 65536) -> bytes:
    """``n`` events, each of a frame never seen, spread over the stages, compressed."""
    ev = np.zeros(n, EVENT_DTYPE)
    ev["ts"] = T0 + seq * n + np.arange(n)
    ev["frame"] = seq * n + np.arange(n)
    ev["stage"] = np.arange(n) % stages
    ev["point"] = ENTER
    return encode_batch(run, seq, ev, compress=True)


async def _stage_bomb(url: str, stages: int, batches: int) -> int:
    names = [f"{i:03d}" + "x" * 97 for i in range(stages)]  # 100 characters each, the name limit
    header = TraceHeader(node="bomber", clock="realtime", stages=names, kinds={}, sources={}, started_ns=0)
    run = uuid.uuid4().hex
    node = await HandNode.open(url, "bomber", run, header=header)
    wire = 0
    try:
        for seq in range(batches):
            data = _bomb(run, seq, stages)
            wire += len(data)
            ack = await node.batch(data)
            assert ack["ok"], ack
    finally:
        await node.close()
    return wire


@pytest.mark.alone  # merging the bomb holds the relay's loop ~0.2-0.7 s; beside five busy workers, over the 2 s bound
def test_many_stages_and_distinct_frames_stay_within_the_byte_budget(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", args=["--limit", "stages=256"])
    try:
        good = _good_node(relay, tmp_path)
        watch = Watch(relay)
        wire = asyncio.run(_stage_bomb(relay.url, 256, 4))
        # The attack is over once the relay has merged it: its run counts every event.
        bomber = wait_for(lambda: {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}.get("bomber"), 20)
        wait_for(lambda: get_json(f"{relay.url}/api/stats?node=bomber")["frames"]["incomplete"] > 0, 30,
                 what="the bomb merged")
        _check_good_node(relay, good, tmp_path)
        health = _check_memory(relay, watch, f"256 stages x 4 x 65,536 frames ({wire / 1e3:.0f} kB on the wire)")
        assert bomber["events"] == 4 * 65536
        assert health["memory"]["runs_with_live_state"] == 2
        evicted = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}["bomber"]["frames"]["evicted"]
        assert evicted > 0
    finally:
        relay.stop()


async def _source_bombs(url: str, runs: int) -> None:
    ev = np.zeros(1, EVENT_DTYPE)
    ev["ts"], ev["source"], ev["point"] = T0, SOURCE_LIMIT - 1, ENTER
    for i in range(runs):
        run = uuid.uuid4().hex
        node = await HandNode.open(url, f"far-source-{i}", run)
        try:
            ack = await node.batch(encode_batch(run, 0, ev))
            assert ack["ok"], ack
        finally:
            await node.close()


async def _too_many_sources(url: str, sources: int) -> str:
    ev = np.zeros(sources, EVENT_DTYPE)
    ev["ts"], ev["source"], ev["point"] = T0, np.arange(sources) * 1000, ENTER
    run = uuid.uuid4().hex
    node = await HandNode.open(url, "many-sources", run)
    try:
        await node.link.send_batch(encode_batch(run, 0, ev))
        await asyncio.wait_for(node.link.closed(), 10)
        return node.link.error
    finally:
        await node.close()


async def _too_many_stages(url: str, stages: int) -> str:
    header = TraceHeader(node="many-stages", clock="realtime", stages=[f"s{i}" for i in range(stages)])
    try:
        await HandNode.open(url, "many-stages", uuid.uuid4().hex, header=header)
    except ConnectionError as exc:
        return str(exc)
    raise AssertionError("a hello beyond the stage limit was taken")


def test_far_source_ids_cost_no_memory_and_too_many_are_refused(tmp_path):
    # Every run held in memory (none released), so that each one's cost shows.
    relay = RelayProcess(tmp_path / "relay.db", args=["--limit", "runs_held=200"])
    try:
        good = _good_node(relay, tmp_path)
        watch = Watch(relay)
        asyncio.run(_source_bombs(relay.url, 150))
        _check_good_node(relay, good, tmp_path)
        _check_memory(relay, watch, "150 runs with source id 524287")
        error = asyncio.run(_too_many_sources(relay.url, 257))
        assert "257 distinct source ids" in error and "--limit sources=N" in error, error
        error = asyncio.run(_too_many_stages(relay.url, 65))
        health = get_json(f"{relay.url}/api/health")
        assert "65 stages" in error and "--limit stages=N" in error, error
        assert health["refused"]["sources"] == 1 and health["refused"]["stages"] == 1, health["refused"]
        assert health["memory"]["runs_with_live_state"] >= 151
        listed = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}
        assert listed["far-source-149"]["events"] == 1 and "many-sources" not in listed  # refused, released
    finally:
        relay.stop()
