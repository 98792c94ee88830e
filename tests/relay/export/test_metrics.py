"""``GET /metrics``: a real relay on 127.0.0.1 fed by nodes over its ingest WebSocket, scraped and
parsed with prometheus_client's own parser; every figure is checked against the delay model over
the same events (model.delays) or against ``/api/stats`` taken at the same moment."""

from __future__ import annotations

import asyncio
import json
import time
import urllib.request
import uuid

import aiohttp
import numpy as np
import pytest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.parser import text_string_to_metric_families

from dcuscope.model.delays import frame_delays, series
from dcuscope.model.frametable import frame_table
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.events import DROP, DROP_REASONS, ENTER, EVENT_DTYPE, EXIT, ORIGIN, TraceHeader
from dcuscope.protocol.wire import PTP_STATES, encode_batch
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.export.framemetrics import MAX_GAPS, NS_PER_S, gap_stages
from dcuscope.relay.export.metrics import BUCKETS_S
from dcuscope.relay.guard.auth import Credentials
from dcuscope.relay.guard.limits import Limits
from dcuscope.relay.live.run import LiveConfig
from dcuscope.relay.server import start_relay
from tests.probes.synth import pipeline_run
from tests.relay.helpers import HandNode, RelayProcess, finish_node, start_node, wait_for

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
    families = list(text_string_to_metric_families(text))
    names = [f.name for f in families]
    assert len(names) == len(set(names)), sorted({n for n in names if names.count(n) > 1})  # one TYPE line each
    return {f.name: f.samples for f in families}


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
    (Series of the node's own events: stage delays, service and wait, gaps, frame and glass times,
    busy time); the bottleneck, utilization, fps and counters are /api/stats' window's."""
    # infer's service (half its delay or more) fills most of the frame period: it saturates.
    header, events, _ = pipeline_run(150, 2, period_ns=40_000_000, jitter_ns=3_000_000, batched_mux=True,
                                     stage_ns=(2_000_000, 50_000_000, 3_000_000, 1_000_000, 4_000_000), node="A")
    events = events[np.argsort(events["ts"], kind="stable")]
    values = series(frame_delays(frame_table(header, events)))

    async def scenario():
        # A window longer than the run: the scrape's and /api/stats' windows, taken a moment apart, hold
        # the same frames (a window ends at the present, and a loaded machine may let the run's first
        # frames age out of a 10 s one between the two).
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", live=LiveConfig(settle_s=0.0, window_s=600.0)))
        url = f"http://127.0.0.1:{relay.port}"
        run = uuid.uuid4().hex
        try:
            node = await HandNode.open(url, "A", run, header=header)
            await feed(node, run, events)
            await finalised(relay, run, len(values.frame))
            fams = await scrape(url)
            stats = await get_json(url, "/api/stats?node=A")
            await node.close()
        finally:
            await relay.stop()
        return fams, stats, run

    fams, stats, run = asyncio.run(scenario())
    assert len(values.frame) == 300 and len(values.glass) == 150 and len(values.service) == 5
    assert_histogram(fams, "dcuscope_frame_delay_seconds", values.frame, node="A")
    assert_histogram(fams, "dcuscope_frame_glass_seconds", values.glass, node="A")  # no clock correction yet
    for name, kind in [("dcuscope_stage_delay_seconds", "stages"), ("dcuscope_stage_service_seconds", "service"),
                       ("dcuscope_stage_wait_seconds", "wait")]:
        per_stage = getattr(values, kind)
        assert len(values_of(fams, name, f"{name}_count")) == len(per_stage)
        for stage, v in per_stage.items():
            assert_histogram(fams, name, v, node="A", stage=stage)
    for gap, v in values.gaps.items():
        a, _, b = gap.partition("->")
        assert_histogram(fams, "dcuscope_gap_seconds", v, node="A", from_stage=a, to_stage=b)
    busy = values_of(fams, "dcuscope_stage_busy_seconds", "dcuscope_stage_busy_seconds_total", node="A")
    assert busy == {(("stage", s),): pytest.approx(ns / NS_PER_S, rel=1e-12) for s, ns in values.busy.items()}

    window = stats["window"]
    neck = window["bottleneck"]
    assert neck["stage"] == "infer" and neck["saturated"] is True
    gauges = {name: values_of(fams, name, name, node="A") for name in
              ("dcuscope_bottleneck", "dcuscope_stage_saturated", "dcuscope_stage_utilization")}
    assert gauges["dcuscope_bottleneck"] == {(("stage", s),): float(s == "infer") for s in window["stages"]}
    assert gauges["dcuscope_stage_saturated"] == gauges["dcuscope_bottleneck"]
    assert gauges["dcuscope_stage_utilization"] == {(("stage", s),): st["utilization"]
                                                    for s, st in window["stages"].items()}
    for name, key in [("dcuscope_source_fps", "fps"), ("dcuscope_source_nominal_fps", "nominal_fps")]:
        assert values_of(fams, name, name, node="A") == {(("source", sid),): src[key]
                                                          for sid, src in window["sources"].items()}
    delivered = values_of(fams, "dcuscope_source_frames_delivered", "dcuscope_source_frames_delivered_total", node="A")
    assert delivered == {(("source", sid),): src["delivered"] for sid, src in window["sources"].items()}
    assert sum(delivered.values()) == 301  # 150 frames of 2 sources, and the lone origin
    assert values_of(fams, "dcuscope_frames_complete", "dcuscope_frames_complete_total") == \
        {(("node", "A"),): len(values.frame)}
    assert values_of(fams, "dcuscope_node_info", "dcuscope_node_info") == \
        {(("node", "A"), ("run", run), ("session", str(stats["session"]))): 1.0}
    assert values_of(fams, "dcuscope_ptp_state", "dcuscope_ptp_state", node="A") == \
        {(("state", s),): float(s == "unavailable") for s in PTP_STATES}
    assert values_of(fams, "dcuscope_relay_events", "dcuscope_relay_events_total") == {(): len(events) + 1}
    assert values_of(fams, "dcuscope_relay_batches", "dcuscope_relay_batches_total") == {(): 5}
    assert values_of(fams, "dcuscope_relay_store_batches", "dcuscope_relay_store_batches_total") == {(): 5}
    commits = values_of(fams, "dcuscope_relay_store_commits", "dcuscope_relay_store_commits_total")[()]
    assert 1 <= commits <= 5
    assert values_of(fams, "dcuscope_node_connected", "dcuscope_node_connected") == {(("node", "A"),): 1.0}
    assert values_of(fams, "dcuscope_node_ended", "dcuscope_node_ended") == {(("node", "A"),): 0.0}


def test_the_policy_guards_metrics_as_it_guards_the_api(tmp_path):
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", credentials=Credentials(TOKEN)))
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
    assert statuses == [(401, {"error": "unauthorized: a credential is required"})] * 2 + \
        [(401, {"error": "unauthorized: wrong or expired credential"})]
    # A token in the address is no credential (it would end in logs and histories).
    assert "dcuscope_relay_events" in by_header and by_query == 401


def test_a_nodes_new_run_starts_its_series_afresh(tmp_path):
    """A restarted node (a new run under its name) is a counter reset: its histograms and counters
    start from zero, its old run's stages and run id are gone."""
    first = synth_events(100, 1, 25.0, T0, seed=1)
    second = synth_events(40, 1, 25.0, T0 + 60 * 10**9, seed=2)
    header = header_for("A", 1)
    n_first = len(series(frame_delays(frame_table(header, first))).frame)
    second_values = series(frame_delays(frame_table(header, second)))

    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", live=LiveConfig(settle_s=0.0)))
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


def test_only_the_nodes_the_relay_holds_have_series(tmp_path):
    """A node whose run left memory (beyond --limit runs_held) leaves /metrics: nodes are bounded too."""
    events = synth_events(30, 1, 25.0, T0)

    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", limits=Limits(runs_held=2),
                                  live=LiveConfig(settle_s=0.0)))
        url = f"http://127.0.0.1:{relay.port}"
        try:
            for name in ("A", "B", "C"):
                run = uuid.uuid4().hex
                node = await HandNode.open(url, name, run)
                await feed(node, run, events)
                await node.close()
                await asyncio.sleep(0.05)  # heard from in this order: A is the least recent
            fams = await scrape(url)
            held = sorted(relay.state.nodes)
        finally:
            await relay.stop()
        return fams, held

    fams, held = asyncio.run(scenario())
    assert held == ["B", "C"]
    for name, samples in fams.items():
        assert {s.labels["node"] for s in samples if "node" in s.labels} <= {"B", "C"}, name
    assert {dict(k)["node"] for k in values_of(fams, "dcuscope_frame_delay_seconds",
                                               "dcuscope_frame_delay_seconds_count")} == {"B", "C"}


def node_series(fams: dict, node: str) -> set[str]:
    """The families with a series of ``node``."""
    return {name for name, samples in fams.items() if any(s.labels.get("node") == node for s in samples)}


def test_on_a_shared_store_a_relay_shows_only_the_runs_it_holds(tmp_path, pg_url):
    """Two relays of one PostgreSQL store: a node streams to A, its connection ends, it resumes its
    run on B. A then shows only the node's state (connected 0, ended, last seen, run): its frames and
    counters are B's to show. Each relay's histograms count the frames finalised while it held the
    run: together every frame, none twice (B's reload of A's part counts none). A relay alone on its
    store keeps showing a run whose connection ended (test_only_the_nodes_the_relay_holds_have_series)."""
    header = header_for("N", 1)
    first = synth_events(40, 1, 25.0, T0, seed=1)
    second = synth_events(40, 1, 25.0, T0, seed=1, first_frame=40)
    n_first = len(series(frame_delays(frame_table(header, first))).frame)
    n_all = len(series(frame_delays(frame_table(header, np.concatenate([first, second])))).frame)
    assert n_first == 40 and n_all == 80

    async def scenario():
        a = await start_relay(RelayConfig(port=0, db=pg_url, live=LiveConfig(settle_s=0.0)))
        b = await start_relay(RelayConfig(port=0, db=pg_url, live=LiveConfig(settle_s=0.0)))
        url_a, url_b = (f"http://127.0.0.1:{r.port}" for r in (a, b))
        run = uuid.uuid4().hex
        try:
            node = await HandNode.open(url_a, "N", run, header=header)
            seq = await feed(node, run, first)
            await finalised(a, run, n_first)
            streaming = await scrape(url_a)
            await node.close()
            await wait_for_async(lambda: a.state.runs[run].sid is None)
            # The run's ownership is given back in the store's queue, before this call's turn.
            await asyncio.sleep(0.05)
            await a.state.storage.call("run_stored", run)
            left = await scrape(url_a)
            node = await HandNode.open(url_b, "N", run, secret=node.secret, header=header)
            for part in [*np.array_split(second, 2), lone_origin(int(second["ts"].max()) + 5 * 10**9, 10**9 + 1)]:
                assert (await node.batch(encode_batch(run, seq, part)))["ok"]
                seq += 1
            await finalised(b, run, n_all)
            on_b, still_a = await scrape(url_b), await scrape(url_a)
            await node.close()
        finally:
            await a.stop()
            await b.stop()
        return run, streaming, left, on_b, still_a

    run, streaming, left, on_b, still_a = asyncio.run(scenario())
    state = {"dcuscope_node_connected", "dcuscope_node_ended", "dcuscope_node_last_seen_timestamp_seconds",
             "dcuscope_node_info"}
    assert histogram(streaming, "dcuscope_frame_delay_seconds", node="N")[2] == n_first
    assert "dcuscope_source_frames_delivered" in node_series(streaming, "N")
    for fams in (left, still_a):
        assert node_series(fams, "N") == state, node_series(fams, "N") - state
        assert values_of(fams, "dcuscope_node_connected", "dcuscope_node_connected") == {(("node", "N"),): 0.0}
        assert [dict(k)["run"] for k in values_of(fams, "dcuscope_node_info", "dcuscope_node_info")] == [run]
    assert len(node_series(on_b, "N")) > 20
    assert values_of(on_b, "dcuscope_node_connected", "dcuscope_node_connected") == {(("node", "N"),): 1.0}
    # B counts the frames it finalised; its frame counter starts at the stored run's (Prometheus
    # sees a new series on another instance: its first value is no increase).
    assert histogram(on_b, "dcuscope_frame_delay_seconds", node="N")[2] == n_all - n_first
    assert values_of(on_b, "dcuscope_frames_complete", "dcuscope_frames_complete_total") == {(("node", "N"),): n_all}


async def wait_for_async(predicate, timeout: float = 10.0) -> None:
    for _ in range(int(timeout / 0.02)):
        if predicate():
            return
        await asyncio.sleep(0.02)
    raise AssertionError("condition not met")


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
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", live=LiveConfig(settle_s=0.0)))
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
    assert reasons == set(DROP_REASONS.values())  # every one, at 0 before its first drop
    assert len(gaps) == MAX_GAPS + 1 and sum(gaps.values()) == sum(len(v) for v in values.gaps.values())
    bound = HISTOGRAM_SAMPLES * (2 + 3 * n_stages + MAX_GAPS + 1) + 4 * n_stages + n_sources * (6 + len(reasons)) + 18
    assert len(samples) <= bound
    assert all(len(s.labels.get("uri", "")) <= 200 for s in samples)
    assert histogram(fams, "dcuscope_frame_delay_seconds", node="H")[2] == len(values.frame)


def test_ingest_lag_is_the_relays_now_less_the_nodes_newest_event(tmp_path):
    """Bracketed by the relay's clock read before and after the scrape (the node's clock is the
    relay's here: no correction); the relay's own gauges and its extension points."""
    events = synth_events(20, 1, 25.0, time.time_ns() - 3 * 10**9)
    newest = int(events["ts"].max())

    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db"))
        url = f"http://127.0.0.1:{relay.port}"
        run = uuid.uuid4().hex
        try:
            node = await HandNode.open(url, "A", run)
            assert (await node.batch(encode_batch(run, 0, events)))["ok"]
            # The extension points the OTLP exporter uses.
            relay.metrics.extra.append(lambda: [GaugeMetricFamily("dcuscope_test_gauge", "a test's", value=3)])
            relay.metrics.queues["otlp"] = lambda: 5
            before = time.time_ns()
            fams = await scrape(url)
            after = time.time_ns()
            async with aiohttp.ClientSession() as http:  # no token: the Host check applies as to any route
                async with http.get(f"{url}/metrics", headers={"Host": "evil.example"}) as r:
                    foreign_host = r.status
            await node.close()
        finally:
            await relay.stop()
        return fams, before, after, foreign_host

    fams, before, after, foreign_host = asyncio.run(scenario())
    [lag] = values_of(fams, "dcuscope_relay_ingest_lag_seconds", "dcuscope_relay_ingest_lag_seconds", node="A").values()
    assert (before - newest) / NS_PER_S <= lag <= (after - newest) / NS_PER_S
    assert values_of(fams, "dcuscope_relay_connections", "dcuscope_relay_connections", kind="ingest") == {(): 1.0}
    depth = values_of(fams, "dcuscope_relay_queue_depth", "dcuscope_relay_queue_depth")
    assert depth == {(("queue", "live_pending"),): 0.0, (("queue", "storage"),): 0.0, (("queue", "otlp"),): 5.0}
    assert values_of(fams, "dcuscope_test_gauge", "dcuscope_test_gauge") == {(): 3.0}
    assert foreign_host == 403


def test_node_processes_clock_limit_and_bottleneck_as_the_api_gives_them(tmp_path):
    """Two probes.ship.simnode processes (one clock 2 s ahead) feed a relay process: the clock gauges are
    /api/nodes' estimate and its bound (which holds the true offset), the frame limit shows for
    the node that has one, each histogram counts the frames the run finalised, the bottleneck
    gauge names /api/stats' stage."""
    relay = RelayProcess(tmp_path / "relay.db", clock="estimate", args=["--frame-limit", "DCU-1=250"])
    try:
        procs = {"DCU-1": start_node(relay.url, "DCU-1", tmp_path / "n1.npz", frames=300, fps=60, paced=True,
                                     offset_ns=2 * 10**9, seed=1),
                 "DCU-2": start_node(relay.url, "DCU-2", tmp_path / "n2.npz", frames=300, fps=60, paced=True, seed=2)}
        for p in procs.values():
            finish_node(p, 60)
        wait_for(lambda: all(not n["connected"] for n in http_json(f"{relay.url}/api/nodes")), 10, what="nodes gone")
        # The window ends at the relay's now: 10 s after the runs ended it holds no frame and names no
        # bottleneck. A scrape is compared with the stats read on both sides of it that agree.
        for _ in range(3):
            before = {name: window_bottleneck(http_json(f"{relay.url}/api/stats?node={name}")) for name in procs}
            fams = {f.name: f.samples for f in text_string_to_metric_families(http_text(f"{relay.url}/metrics"))}
            nodes = {n["node"]: n for n in http_json(f"{relay.url}/api/nodes")}
            necks = {name: window_bottleneck(http_json(f"{relay.url}/api/stats?node={name}")) for name in procs}
            if necks == before:
                break
    finally:
        assert relay.stop() == 0

    def gauge(name: str) -> dict[str, float]:
        return {dict(k)["node"]: v for k, v in values_of(fams, name, name).items()}

    offset, bound = gauge("dcuscope_clock_offset_seconds"), gauge("dcuscope_clock_uncertainty_seconds")
    for name, n in nodes.items():
        assert offset[name] == n["clock"]["offset_ns"] / NS_PER_S
        # The bound grows with the time since the estimate (its drift's): /api/nodes was read after.
        clock = n["clock"]
        assert clock["uncertainty_ns"] / NS_PER_S <= bound[name] <= clock["correction_uncertainty_ns"] / NS_PER_S
        assert abs(offset[name] - (2.0 if name == "DCU-1" else 0.0)) <= bound[name]
        assert histogram(fams, "dcuscope_frame_delay_seconds", node=name)[2] == n["frames"]["finalised"] > 0
        neck = values_of(fams, "dcuscope_bottleneck", "dcuscope_bottleneck", node=name)
        assert [dict(k)["stage"] for k, v in neck.items() if v == 1] == ([necks[name]] if necks[name] else [])
    assert gauge("dcuscope_frame_delay_limit_seconds") == {"DCU-1": 0.25}
    assert gauge("dcuscope_node_connected") == {"DCU-1": 0.0, "DCU-2": 0.0}
    assert gauge("dcuscope_node_ended") == {"DCU-1": 1.0, "DCU-2": 1.0}  # a clean end: no disconnection alert


def window_bottleneck(stats: dict) -> str | None:
    return (stats["window"].get("bottleneck") or {}).get("stage")


def http_json(url: str):
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


def http_text(url: str) -> str:
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.read().decode()


def test_gap_labels_name_the_stages_even_when_stage_names_hold_an_arrow():
    stages = ["src0", "a->b", "c", "b->c", "sink"]
    assert [gap_stages(f"{a}->{b}", stages) for a, b in zip(stages, stages[1:])] == list(zip(stages, stages[1:]))
