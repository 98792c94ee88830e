"""A real Prometheus scrapes a relay fed by two real pipeline nodes; its answers must agree with the
relay's own ``/api/stats``, and the shipped frame-delay alert must fire for the node over its limit.

The relay runs with a token and per-node frame limits; Prometheus (tests/relay/promserver.py) scrapes
``/metrics`` every second with the token in its ``authorization`` credentials file (a second job
without it is refused), and evaluates the shipped rules every second, with their ``for:`` set to 0 s
so that an alert fires within seconds. Each node runs a live test source at 10 frames/s through
``mux -> work (identity, sleep-time) -> queue``: DCU-2's work sleeps 40 ms, so every one of its
frames takes over its 10 ms limit; DCU-1's 15 ms, far under its 5 s one (a loaded fresh clone queued
DCU-1's frames past 1 s). ``work`` is each node's
bottleneck by far (utilization ~0.4 and ~0.15 against a few % for the others)."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
import time
import urllib.error
from pathlib import Path

import pytest

from dcuscope.core.clocks import NEVER
from dcuscope.relay.live.state import WINDOW_MAX_AGE_S
from tests.conftest import cli_env
from tests.relay.helpers import RelayProcess, get_json, kill_all, wait_for
from tests.relay.promserver import JOB, PromServer, wait_scrape

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "prometheus"
TOKEN = "prom-test-token"
LIMIT_MS = {"DCU-1": 5000, "DCU-2": 10}
"""Each node's frames take at least its work's sleep: DCU-1's (15 ms) would be over DCU-2's limit and
DCU-2's (40 ms) under DCU-1's, so the alert fires for DCU-2 only if each is held to its own."""
WORK_US = {"DCU-1": 15_000, "DCU-2": 40_000}
DURATION_S = 12
ALERT = "DcuscopeFrameDelayOverLimit"
P99 = 'histogram_quantile(0.99, sum by (node, le) (dcuscope_frame_delay_seconds_bucket))'
"""Over the whole run's counters: the population of /api/stats' whole-run p99."""


def node_config(tmp: Path, name: str) -> Path:
    path = tmp / f"{name}.yaml"
    path.write_text(f"node: {name}\nsources:\n  - {{test: ball, width: 160, height: 120, rate: 10, live: true}}\n"
                    "stages:\n  - mux: {batch-size: 1, width: 160, height: 120, live-source: true}\n"
                    f"  - factory: identity\n    name: work\n    properties: {{sleep-time: {WORK_US[name]}}}\n"
                    "  - queue: {}\n")
    return path


def quick_rules(tmp: Path) -> Path:
    """The shipped rules with every ``for:`` at 0 s (the expressions unchanged)."""
    text = (CONFIGS / "dcuscope-rules.yml").read_text()
    quick, n = re.subn(r"(?m)^(\s+)for: \S+$", r"\1for: 0s", text)
    assert n >= 4 and f"alert: {ALERT}" in quick
    path = tmp / "dcuscope-rules.yml"
    path.write_text(quick)
    return path


def stats(relay: RelayProcess, node: str) -> dict:
    return get_json(f"{relay.url}/api/stats?node={node}", TOKEN)


def window_bottleneck(relay: RelayProcess, node: str) -> str | None:
    """The stage /api/stats names over its window; None before the node said hello."""
    try:
        found = (stats(relay, node).get("window") or {}).get("bottleneck")
    except urllib.error.HTTPError as exc:
        if exc.code != 404:
            raise
        return None
    return found["stage"] if found else None


def frame_counts(relay: RelayProcess, prom: PromServer) -> tuple[dict, dict] | None:
    """None when Prometheus' frame delay histogram counts as many frames as /api/stats, per node."""
    scraped = prom.values("dcuscope_frame_delay_seconds_count", "node")
    api = {n: stats(relay, n)["frame"]["count"] for n in LIMIT_MS}
    return None if scraped == api else (scraped, api)


SETTLED_S = (WINDOW_MAX_AGE_S, 1.0 + WINDOW_MAX_AGE_S)
"""A scrape's gauge is compared with /api/stats where every reading agrees from the last one answered
WINDOW_MAX_AGE_S or more before the scrape began (a scrape reuses a window computed up to that long
before it, e.g. for one of those readings) to the first one asked 1 s + WINDOW_MAX_AGE_S after it (a
scrape answers within that second; that reading may reuse a window as old). A reading counts from
when it was asked to when it was answered: on a loaded machine an answer comes long after its question."""


def watch(relay: RelayProcess, prom: PromServer, nodes: dict, seen: dict) -> None:
    """While the nodes run: the bottleneck by /api/stats, read every 0.2 s; Prometheus' gauge with
    the time of the scrape it came from; the alert's states. Then each scrape's gauge beside what
    /api/stats said around that scrape (``seen["bottleneck"]``), where that was settled."""
    readings: dict[str, list[tuple[float, float, str | None]]] = {n: [] for n in nodes}  # asked, answered, stage
    scrapes: set[tuple[str, float, str]] = set()
    last_query = NEVER
    while any(p.poll() is None for p in nodes.values()):
        for n in nodes:
            asked = time.time()
            stage = window_bottleneck(relay, n)
            readings[n].append((asked, time.time(), stage))
        if time.monotonic() - last_query >= 0.5:
            last_query = time.monotonic()
            for s in prom.query("timestamp(dcuscope_bottleneck == 1)"):  # the scrape's time, labels kept
                scrapes.add((s["metric"]["node"], float(s["value"][1]), s["metric"]["stage"]))
            for a in prom.alerts(ALERT):
                seen["alert"].add((a["labels"]["node"], a["state"]))
        time.sleep(0.2)
    for node, scraped_at, stage in sorted(scrapes, key=lambda s: s[1]):
        before = [r for r in readings[node] if r[1] <= scraped_at - SETTLED_S[0]]
        after = [r for r in readings[node] if r[0] >= scraped_at + SETTLED_S[1]]
        if not before or not after:
            continue  # not read on both sides
        since, until = before[-1][0], after[0][1]
        around = {b for asked, answered, b in readings[node] if since <= asked and answered <= until}
        if len(around) == 1 and None not in around:
            seen["bottleneck"].append((node, around.pop(), stage))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The relay and Prometheus (both still up) after both nodes ran; what was seen while they ran."""
    tmp = tmp_path_factory.mktemp("prometheus")
    limits = [a for n, ms in LIMIT_MS.items() for a in ("--frame-limit", f"{n}={ms}")]
    relay = RelayProcess(tmp / "relay.db", token=TOKEN, args=limits)
    prom, nodes, seen = None, {}, {"bottleneck": [], "alert": set()}
    try:
        unguarded = {"job_name": "no-token", "scrape_interval": "1s", "scrape_timeout": "1s",
                     "static_configs": [{"targets": [f"127.0.0.1:{relay.port}"]}]}
        prom = PromServer(tmp / "prom", f"127.0.0.1:{relay.port}", TOKEN, [quick_rules(tmp)], extra_jobs=[unguarded])
        for name in WORK_US:
            cmd = [sys.executable, "-m", "dcuscope.cli", "run", str(node_config(tmp, name)), "--probes", "--relay",
                   relay.url, "--token", TOKEN, "--duration", str(DURATION_S), "-q"]
            with open(tmp / f"{name}.log", "wb") as log:
                nodes[name] = subprocess.Popen(cmd, cwd=tmp, env=cli_env(), stderr=log)
        watch(relay, prom, nodes, seen)
        for name, proc in nodes.items():
            assert proc.wait(60) == 0, (tmp / f"{name}.log").read_text()[-3000:]
        logs = {name: (tmp / f"{name}.log").read_text()[-1500:] for name in nodes}
        assert {n["node"] for n in get_json(f"{relay.url}/api/nodes", TOKEN)} == set(nodes), \
            f"both nodes' runs are not on the relay: {logs}"  # a node that never reached it exits 0 (its spool keeps all)
        wait_for(lambda: all(n["ended"] for n in get_json(f"{relay.url}/api/nodes", TOKEN)), 20, 0.2, "runs ended")
        # The runs' last frames are finalised at their end (a batch may still land after it): the
        # histograms then hold every frame /api/stats counts.
        wait_scrape(prom, time.time())
        try:
            wait_for(lambda: frame_counts(relay, prom) is None, 20, 0.5, "the frame counts to agree")
        except AssertionError as exc:
            raise AssertionError(f"{exc}: Prometheus', /api/stats': {frame_counts(relay, prom)}") from None
        seen["alert"] |= {(a["labels"]["node"], a["state"]) for a in prom.alerts(ALERT)}
        yield relay, prom, seen
    finally:
        kill_all(nodes.values())
        if prom is not None:
            prom.stop()
        relay.stop()


def bucket_index(value: float, bounds: list[float]) -> int:
    """The bucket (lower, upper] holding ``value``: the index of its upper bound."""
    return next(i for i, b in enumerate(bounds) if value <= b)


def test_prometheus_p99_per_node_lies_in_the_bucket_of_api_stats_p99(run):
    """histogram_quantile interpolates inside the bucket that holds the ceil(0.99 n)-th frame delay;
    /api/stats' p99 lies between the k-th and (k+1)-th (k = floor(0.99 (n - 1)), numpy's linear
    method). Same bucket, unless those two delays sit on either side of a bound: then the
    neighbouring bucket, and Prometheus' own cumulative count at that bound says they do."""
    relay, prom, _ = run
    p99 = prom.values(P99, "node")
    buckets: dict[str, dict[float, float]] = {}
    for s in prom.query("dcuscope_frame_delay_seconds_bucket"):
        buckets.setdefault(s["metric"]["node"], {})[float(s["metric"]["le"])] = float(s["value"][1])
    for node in LIMIT_MS:
        api = stats(relay, node)["frame"]
        cumulative = buckets[node]
        bounds = sorted(cumulative)
        n = int(cumulative[math.inf])
        assert n == api["count"] >= 60, (node, n, api["count"])  # every frame, the last ones too
        expected, got = api["p99_ms"] / 1e3, p99[node]
        i, j = bucket_index(expected, bounds), bucket_index(got, bounds)
        where = f"{node}: /api/stats p99 {expected * 1e3:.3f} ms, Prometheus {got * 1e3:.3f} ms, bounds {bounds}"
        if i != j:
            k = math.floor(0.99 * (n - 1))
            assert abs(i - j) == 1 and cumulative[bounds[min(i, j)]] == k + 1, where
        assert (bounds[j - 1] if j else 0.0) < got <= bounds[j], where


def test_the_bottleneck_gauge_names_the_stage_api_stats_names(run):
    _, _, seen = run
    for node in LIMIT_MS:
        pairs = [(by_api, by_gauge) for n, by_api, by_gauge in seen["bottleneck"] if n == node]
        assert len(pairs) >= 3, (node, seen["bottleneck"])
        assert all(a == g for a, g in pairs), (node, pairs)
        # work is the bottleneck by far, but a window holding little more than the pipeline's
        # start (a loaded machine's) may name mux: work, by the end and in most of the scrapes.
        named = [a for a, _ in pairs]
        assert named[-1] == "work" and named.count("work") > len(named) / 2, (node, pairs)


def test_the_frame_delay_alert_fires_for_the_node_over_its_limit_only(run):
    _, prom, seen = run
    assert ("DCU-2", "firing") in seen["alert"], seen["alert"]
    assert not {s for s in seen["alert"] if s[0] == "DCU-1"}, seen["alert"]
    firing = prom.query(f'ALERTS{{alertname="{ALERT}", alertstate="firing"}}')
    assert [s["metric"]["node"] for s in firing] == ["DCU-2"]
    assert firing[0]["metric"]["severity"] == "critical"
    # Never pending or firing for DCU-1 during the whole run, though it has a limit.
    ever = prom.query(f'count_over_time(ALERTS{{alertname="{ALERT}", node="DCU-1"}}[10m])')
    assert ever == [] and prom.values("dcuscope_frame_delay_limit_seconds", "node") == {
        n: ms / 1e3 for n, ms in LIMIT_MS.items()}


def test_prometheus_scrapes_with_the_token_and_is_refused_without(run):
    _, prom, _ = run
    health = {t["labels"]["job"]: t for t in prom.targets()}
    assert health[JOB]["health"] == "up", health[JOB]
    assert health["no-token"]["health"] == "down" and "401" in health["no-token"]["lastError"], health["no-token"]


def test_every_metric_the_rules_and_dashboard_name_is_scraped(run):
    """The shipped files name the relay's real metrics, and every query of the dashboard has data."""
    _, prom, _ = run
    scraped = {s["metric"]["__name__"] for s in prom.query('group by (__name__) ({__name__=~"dcuscope_.+"})')}
    exprs = re.findall(r"(?m)^\s+expr: (.+)$", (CONFIGS / "dcuscope-rules.yml").read_text())
    named = set(re.findall(r"(?<![:\w])(dcuscope_[a-z_]+)\b(?!:)", " ".join(exprs)))
    missing = named - scraped - {"dcuscope_source_frames_dropped_total"}  # a reason appears with its first drop
    assert not missing, missing
    dashboard = json.loads((CONFIGS / "grafana-dashboard.json").read_text())
    for panel in dashboard["panels"]:
        # Over the run (the nodes ended: the figures of a node connected nowhere are not shown now).
        exprs = [t["expr"].replace("$relay", ".*").replace("$node", ".*") for t in panel["targets"]]
        empty = [e for e in exprs if not prom.query(f"last_over_time(({e})[10m:1s])")]
        assert not empty, (panel["title"], empty)
