"""``GET /metrics``: a real relay on 127.0.0.1 fed by nodes over its ingest WebSocket, scraped and
parsed with prometheus_client's own parser; every figure is checked against the delay model over
the same events (probes.delays) or against ``/api/stats`` taken at the same moment."""

from __future__ import annotations

import asyncio
import uuid

import aiohttp
import numpy as np
import pytest
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.parser import text_string_to_metric_families

from probes.delays import frame_delays, series
from probes.events import DROP, DROP_REASONS, ENTER, EVENT_DTYPE, EXIT, ORIGIN, TraceHeader
from probes.frametable import frame_table
from probes.simnode import header_for, synth_events
from probes.wire import PTP_STATES, encode_batch
from relay.framemetrics import MAX_GAPS, NS_PER_S
from relay.limits import Limits
from relay.live import LiveConfig
from relay.metrics import BUCKETS_S
from relay.server import start_relay
from tests.relay.helpers import HandNode

T0 = 1_700_000_000_000_000_000
BOUNDS_NS = np.array([round(b * NS_PER_S) for b in BUCKETS_S])
TOKEN = "metrics-token-0123456789"
HISTOGRAM_SAMPLES = len(BUCKETS_S) + 3  # the buckets, +Inf, sum, count


async def scrape(url: str, **headers) -> dict[str, list]:
    """/metrics parsed: family name -> its samples."""
    async with aiohttp.ClientSession() as http:
        async with http.get(f"{url}/metrics", headers=headers) as r:
            assert r.status == 200 and r.headers["Content-Type"] == CONTENT_TYPE_LATEST
            text = await r.text()
    return {f.name: f.samples for f in text_string_to_metric_families(text)}


async def get_json(url: str, path: str) -> dict:
    async with aiohttp.ClientSession() as http:
        async with http.get(f"{url}{path}") as r:
            assert r.status == 200
            return await r.json()


def values_of(fams: dict, family: str, sample: str, **labels) -> dict[tuple, float]:
    """Samples named ``sample`` of ``family`` whose labels include ``labels``: their other labels -> value."""
    out = {}
    for s in fams[family]:
        if s.name == sample and all(s.labels.get(k) == v for k, v in labels.items()):
            out[tuple(sorted((k, v) for k, v in s.labels.items() if k not in labels))] = s.value
    return out


def histogram(fams: dict, name: str, **labels) -> tuple[list[float], float, float]:
    """(cumulative bucket counts in bound order, +Inf last; sum; count) of one histogram series."""
    buckets = values_of(fams, name, f"{name}_bucket", **labels)
    by_le = {float(dict(k)["le"]): v for k, v in buckets.items()}
    [total] = values_of(fams, name, f"{name}_sum", **labels).values()
    [count] = values_of(fams, name, f"{name}_count", **labels).values()
    return [by_le[le] for le in sorted(by_le)], total, count


def expected(values_ns: np.ndarray) -> list[float]:
    """Cumulative le-bucket counts: values at or below each bound, then all of them."""
    ordered = np.sort(values_ns)
    return np.searchsorted(ordered, BOUNDS_NS, side="right").tolist() + [len(ordered)]


def assert_histogram(fams: dict, name: str, values_ns: np.ndarray, **labels) -> None:
    buckets, total, count = histogram(fams, name, **labels)
    assert count == len(values_ns) and buckets == expected(values_ns), (name, labels)
    assert total == pytest.approx(values_ns.sum() / NS_PER_S, rel=1e-9, abs=1e-12)


def lone_origin(ts: int, frame: int = 10**9) -> np.ndarray:
    """One origin of a frame never completed: moves the node's time on, so that every complete
    frame before it is finalised."""
    ev = np.zeros(1, EVENT_DTYPE)
    ev["ts"], ev["frame"], ev["point"] = ts, frame, ORIGIN
    return ev


async def feed(node: HandNode, run: str, events: np.ndarray, parts: int = 4, first_seq: int = 0) -> int:
    """Send ``events`` in ``parts`` batches, then a lone origin 5 s later; returns the next seq."""
    seq = first_seq
    for part in [*np.array_split(events, parts), lone_origin(int(events["ts"].max()) + 5 * 10**9)]:
        assert (await node.batch(encode_batch(run, seq, part)))["ok"]
        seq += 1
    return seq


async def finalised(relay, run: str, n: int) -> None:
    live = relay.state.runs[run].live
    for _ in range(200):
        live.maintain()
        if live.finalised >= n:
            assert live.finalised == n
            return
        await asyncio.sleep(0.02)
    raise AssertionError(f"{live.finalised} frames finalised, not {n}")


def test_histograms_gauges_and_counters_equal_the_delay_model_and_api_stats(tmp_path):
    """Histogram counts are the run's finalised frames, each bucket the values at or below its bound
    (Series of the node's own events); the bottleneck, fps and counters are /api/stats' window's."""
    header = header_for("A", 2)
    events = synth_events(300, 2, 25.0, T0, drop_rate=0.1, seed=3)
    values = series(frame_delays(frame_table(header, events)))

    async def scenario():
        relay = await start_relay(port=0, db=tmp_path / "r.db", live=LiveConfig(settle_s=0.0))
        url = f"http://127.0.0.1:{relay.port}"
        run = uuid.uuid4().hex
        try:
            node = await HandNode.open(url, "A", run, stages=2)
            await feed(node, run, events)
            await finalised(relay, run, len(values.frame))
            fams = await scrape(url)
            stats = await get_json(url, "/api/stats?node=A")
            await node.close()
        finally:
            await relay.stop()
        return fams, stats, run

    fams, stats, run = asyncio.run(scenario())
    assert 0 < len(values.frame) < 600  # some frames were dropped: incomplete, never counted
    assert_histogram(fams, "dcuscope_frame_delay_seconds", values.frame, node="A")
    assert_histogram(fams, "dcuscope_frame_glass_seconds", np.zeros(0), node="A")  # no capture times
    for stage, v in values.stages.items():
        assert_histogram(fams, "dcuscope_stage_delay_seconds", v, node="A", stage=stage)
    for gap, v in values.gaps.items():
        a, _, b = gap.partition("->")
        assert_histogram(fams, "dcuscope_gap_seconds", v, node="A", from_stage=a, to_stage=b)
    assert len(values_of(fams, "dcuscope_stage_delay_seconds", "dcuscope_stage_delay_seconds_count")) == \
        len(values.stages)

    window = stats["window"]
    neck = values_of(fams, "dcuscope_bottleneck", "dcuscope_bottleneck", node="A")
    assert neck == {(("stage", s),): float(s == window["bottleneck"]["stage"]) for s in window["stages"]}
    assert sum(neck.values()) == 1
    fps = values_of(fams, "dcuscope_source_fps", "dcuscope_source_fps", node="A")
    assert fps == {(("source", sid),): src["fps"] for sid, src in window["sources"].items()}
    delivered = values_of(fams, "dcuscope_source_frames_delivered", "dcuscope_source_frames_delivered_total", node="A")
    assert delivered == {(("source", sid),): src["delivered"] for sid, src in window["sources"].items()}
    assert sum(delivered.values()) == 601  # 300 frames of 2 sources, and the lone origin
    assert values_of(fams, "dcuscope_frames_complete", "dcuscope_frames_complete_total") == \
        {(("node", "A"),): len(values.frame)}
    assert values_of(fams, "dcuscope_node_info", "dcuscope_node_info") == \
        {(("node", "A"), ("run", run), ("session", str(stats["session"]))): 1.0}
    assert values_of(fams, "dcuscope_ptp_state", "dcuscope_ptp_state", node="A") == \
        {(("state", s),): float(s == "unavailable") for s in PTP_STATES}
    assert values_of(fams, "dcuscope_relay_events", "dcuscope_relay_events_total") == {(): len(events) + 1}
    assert values_of(fams, "dcuscope_relay_batches", "dcuscope_relay_batches_total") == {(): 5}
    assert values_of(fams, "dcuscope_node_connected", "dcuscope_node_connected") == {(("node", "A"),): 1.0}


def test_the_token_guards_metrics_as_it_guards_the_api(tmp_path):
    async def scenario():
        relay = await start_relay(port=0, db=tmp_path / "r.db", token=TOKEN)
        url = f"http://127.0.0.1:{relay.port}"
        try:
            async with aiohttp.ClientSession() as http:
                statuses = []
                for path, headers in [("/metrics", {}), ("/metrics?token=wrong", {}),
                                      ("/metrics", {"Authorization": "Bearer wrong"})]:
                    async with http.get(url + path, headers=headers) as r:
                        statuses.append((r.status, await r.json()))
            by_header = await scrape(url, Authorization=f"Bearer {TOKEN}")
            async with aiohttp.ClientSession() as http:
                async with http.get(f"{url}/metrics?token={TOKEN}") as r:
                    by_query = r.status
        finally:
            await relay.stop()
        return statuses, by_header, by_query

    statuses, by_header, by_query = asyncio.run(scenario())
    assert statuses == [(401, {"error": "unauthorized: wrong or missing token"})] * 3
    assert "dcuscope_relay_events" in by_header and by_query == 200


def test_a_nodes_new_run_starts_its_series_afresh(tmp_path):
    """A restarted node (a new run under its name) is a counter reset: its histograms and counters
    start from zero, its old run's stages and run id are gone."""
    first = synth_events(100, 1, 25.0, T0, seed=1)
    second = synth_events(40, 1, 25.0, T0 + 60 * 10**9, seed=2)
    header = header_for("A", 1)
    n_first = len(series(frame_delays(frame_table(header, first))).frame)
    second_values = series(frame_delays(frame_table(header, second)))

    async def scenario():
        relay = await start_relay(port=0, db=tmp_path / "r.db", live=LiveConfig(settle_s=0.0))
        url = f"http://127.0.0.1:{relay.port}"
        runs = uuid.uuid4().hex, uuid.uuid4().hex
        try:
            node = await HandNode.open(url, "A", runs[0])
            await feed(node, runs[0], first)
            await finalised(relay, runs[0], n_first)
            before = await scrape(url)
            await node.close()
            node = await HandNode.open(url, "A", runs[1])
            fresh = await scrape(url)
            await feed(node, runs[1], second)
            await finalised(relay, runs[1], len(second_values.frame))
            after = await scrape(url)
            await node.close()
        finally:
            await relay.stop()
        return runs, before, fresh, after

    runs, before, fresh, after = asyncio.run(scenario())
    assert histogram(before, "dcuscope_frame_delay_seconds", node="A")[2] == n_first > 0
    assert histogram(fresh, "dcuscope_frame_delay_seconds", node="A")[2] == 0
    assert values_of(fresh, "dcuscope_stage_delay_seconds", "dcuscope_stage_delay_seconds_count") == {}
    assert values_of(fresh, "dcuscope_frames_complete", "dcuscope_frames_complete_total") == {(("node", "A"),): 0}
    assert [dict(k)["run"] for k in values_of(fresh, "dcuscope_node_info", "dcuscope_node_info")] == [runs[1]]
    assert_histogram(after, "dcuscope_frame_delay_seconds", second_values.frame, node="A")


def hostile_events(stages: int, sources: int, frames: int, rng: np.random.Generator) -> np.ndarray:
    """Complete frames of every source, each through its own random subset of the middle stages
    (so that they show hundreds of gap pairs), plus drops of every reason code."""
    parts = []
    for f in range(frames):
        src = f % sources
        mids = np.sort(rng.choice(np.arange(1, stages - 1), rng.integers(1, 6), replace=False))
        t = T0 + f * 1_000_000
        rows = [(t, ORIGIN, 0)]
        for s in mids:
            rows += [(t + 100 * s, ENTER, s), (t + 100 * s + 50, EXIT, s)]
        rows.append((t + 100 * stages, ENTER, stages - 1))
        ev = np.zeros(len(rows), EVENT_DTYPE)
        ev["ts"], ev["point"], ev["stage"] = np.array(rows).T
        ev["frame"], ev["source"] = f, src
        parts.append(ev)
    drops = np.zeros(sources * 8, EVENT_DTYPE)
    drops["ts"], drops["point"] = T0, DROP
    drops["source"], drops["code"] = np.arange(len(drops)) % sources, np.arange(len(drops)) % len(DROP_REASONS)
    drops["frame"] = 10**8 + np.arange(len(drops))
    events = np.concatenate([drops, *parts])
    return events[np.argsort(events["ts"], kind="stable")]


def test_a_hostile_node_cannot_push_its_series_beyond_the_stated_bound(tmp_path):
    """A node declaring every stage and source the relay takes, and frames through hundreds of
    distinct gap pairs: its series stay within the module docstring's formula."""
    limits = Limits()
    n_stages, n_sources = limits.stages, limits.sources
    header = TraceHeader(node="H", clock="realtime", stages=[f"s{k}" for k in range(n_stages)], kinds={},
                         sources={k: f"sim://{'x' * 500}{k}" for k in range(n_sources)})
    events = hostile_events(n_stages, n_sources, 3000, np.random.default_rng(5))
    values = series(frame_delays(frame_table(header, events)))
    assert len(values.gaps) > 3 * MAX_GAPS  # the cap is what bounds them

    async def scenario():
        relay = await start_relay(port=0, db=tmp_path / "r.db", live=LiveConfig(settle_s=0.0))
        url = f"http://127.0.0.1:{relay.port}"
        run = uuid.uuid4().hex
        try:
            node = await HandNode.open(url, "H", run, header=header)
            await feed(node, run, events, parts=8)
            await finalised(relay, run, len(values.frame))
            fams = await scrape(url)
            await node.close()
        finally:
            await relay.stop()
        return fams

    fams = asyncio.run(scenario())
    samples = [s for family in fams.values() for s in family if s.labels.get("node") == "H"]
    gaps = values_of(fams, "dcuscope_gap_seconds", "dcuscope_gap_seconds_count", node="H")
    reasons = {s.labels["reason"] for s in fams["dcuscope_source_frames_dropped"]}
    assert len(gaps) == MAX_GAPS + 1 and sum(gaps.values()) == sum(len(v) for v in values.gaps.values())
    bound = HISTOGRAM_SAMPLES * (2 + 3 * n_stages + MAX_GAPS + 1) + 4 * n_stages + n_sources * (6 + len(reasons)) + 18
    assert len(samples) <= bound
    assert all(len(s.labels.get("uri", "")) <= 200 for s in samples)
    assert histogram(fams, "dcuscope_frame_delay_seconds", node="H")[2] == len(values.frame)
