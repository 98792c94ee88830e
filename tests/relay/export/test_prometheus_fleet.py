"""A real Prometheus scrapes two real relays sharing one PostgreSQL store (one job, each relay a
target) while simulated nodes stream to them, and the shipped rules count every node once.

Node S streams to relay A, T and L to relay B, M to A through a proxy that then cuts it: M resumes
its run on B, while A keeps M's run in memory and shows its state only (connected 0). L is killed
(no end). Prometheus (tests/relay/promserver.py, scraping both relays every second, the shipped rules
with ``for: 0s``) must then count 4 nodes, 3 of them connected, one frame-delay p99 per node, and
raise the disconnection alert for L alone; counted per relay (what the rules must not do) there are
5 nodes, M twice."""

from __future__ import annotations

import re
import urllib.request
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.relay import promserver
from tests.relay.helpers import RelayProcess, kill_all, start_node, wait_for
from tests.relay.netcut import CutProxy
from tests.relay.promserver import JOB, PromServer

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "prometheus"
STATE = {"dcuscope_node_connected", "dcuscope_node_ended", "dcuscope_node_last_seen_timestamp_seconds",
         "dcuscope_node_info"}
"""The only series a relay shows of a run it keeps but no longer holds (relay/export/nodemetrics.py)."""


def quick_rules(tmp: Path) -> Path:
    """The shipped rules with every ``for:`` at 0 s (the expressions unchanged)."""
    quick, n = re.subn(r"(?m)^(\s+)for: \S+$", r"\1for: 0s", (CONFIGS / "dcuscope-rules.yml").read_text())
    assert n >= 4
    path = tmp / "dcuscope-rules.yml"
    path.write_text(quick)
    return path


def relay_series(relay: RelayProcess, node: str) -> dict[str, float]:
    """The families of the relay's /metrics with a series of ``node``, each with its first value."""
    with urllib.request.urlopen(f"{relay.url}/metrics", timeout=10) as r:
        text = r.read().decode()
    found: dict[str, float] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.labels.get("node") == node:
                found.setdefault(family.name, s.value)
    return found


@pytest.fixture
def both_relays_one_job(monkeypatch):
    """PromServer's job scrapes a second target too: ``add(host_port)`` before starting it."""
    extra: list[str] = []
    original = promserver.scrape_config

    def config(target, *args, **kwargs):
        made = original(target, *args, **kwargs)
        made["scrape_configs"][0]["static_configs"][0]["targets"] += extra
        return made

    monkeypatch.setattr(promserver, "scrape_config", config)
    return extra.append


def test_two_relays_of_one_store_count_each_node_once(tmp_path, pg_url, both_relays_one_job):
    a = RelayProcess(pg_url, log=tmp_path / "a.log")
    b = RelayProcess(pg_url, log=tmp_path / "b.log")
    proxy = CutProxy(a.port)
    prom, nodes = None, {}
    try:
        both_relays_one_job(f"127.0.0.1:{b.port}")
        prom = PromServer(tmp_path / "prom", f"127.0.0.1:{a.port}", rule_files=[quick_rules(tmp_path)])
        urls = {"S": a.url, "T": b.url, "L": b.url, "M": f"{proxy.url},{b.url}"}
        for i, (name, url) in enumerate(urls.items()):
            nodes[name] = start_node(url, name, tmp_path / f"{name}.npz", frames=4000, sources=1, fps=20,
                                     paced=True, seed=i)

        def value(expr: str) -> float | None:
            found = prom.query(expr)
            return float(found[0]["value"][1]) if len(found) == 1 else None

        def per_relay() -> dict[str, float]:
            return {s["metric"]["instance"]: float(s["value"][1])
                    for s in prom.query(f'sum without (node) (dcuscope_node_connected{{job="{JOB}"}})')}

        def p99_nodes() -> list[str]:
            return sorted(s["metric"]["node"] for s in prom.query("node:dcuscope_frame_delay_seconds:p99_1m > 0"))

        wait_for(lambda: value("job:dcuscope_nodes_connected:sum") == 4, 40, 0.5, "four nodes connected")
        wait_for(lambda: p99_nodes() == ["L", "M", "S", "T"], 30, 0.5, "every node's frames scraped")
        assert per_relay() == {f"127.0.0.1:{a.port}": 2, f"127.0.0.1:{b.port}": 2}
        assert {t["labels"]["instance"] for t in prom.targets() if t["health"] == "up"} == \
            {f"127.0.0.1:{r.port}" for r in (a, b)}

        nodes["L"].kill()
        nodes["L"].wait(10)
        proxy.cut("refuse")
        # M resumes on B; A keeps its run, showing its state only.
        wait_for(lambda: relay_series(b, "M").get("dcuscope_node_connected") == 1.0, 20, 0.2, "M resumed on relay B")
        wait_for(lambda: set(relay_series(a, "M")) == STATE, 10, 0.2, "relay A showing M's state only")
        assert relay_series(a, "M")["dcuscope_node_connected"] == 0.0
        assert relay_series(b, "L").get("dcuscope_node_connected") == 0.0

        def fleet() -> dict:
            p99 = [s["metric"] for s in prom.query("node:dcuscope_frame_delay_seconds:p99_1m")]
            alerts = prom.query('ALERTS{alertname="DcuscopeNodeDisconnected", alertstate="firing"}')
            return {"nodes": value("job:dcuscope_nodes:count"), "connected": value("job:dcuscope_nodes_connected:sum"),
                    "per_relay_nodes": value(f'count(dcuscope_node_info{{job="{JOB}"}})'),
                    "p99_nodes": sorted(m["node"] for m in p99), "p99_instances": [m for m in p99 if "instance" in m],
                    "disconnected": sorted(s["metric"]["node"] for s in alerts)}

        truth = {"nodes": 4, "connected": 3, "per_relay_nodes": 5, "p99_nodes": ["L", "M", "S", "T"],
                 "p99_instances": [], "disconnected": ["L"]}
        try:
            wait_for(lambda: fleet() == truth, 20, 0.5, "the fleet's rules to count each node once")
        except AssertionError as exc:
            raise AssertionError(f"{exc}: {fleet()}") from None
        # S on A; T and M on B, once Prometheus scraped A after it let M go (the rules above may
        # count M once from a sample of A taken before, with B's).
        after = {f"127.0.0.1:{a.port}": 1, f"127.0.0.1:{b.port}": 2}
        assert wait_for(lambda: per_relay() == after, 20, 0.5, "each relay's own nodes connected"), per_relay()
    finally:
        kill_all(nodes.values())
        if prom is not None:
            prom.stop()
        proxy.close()
        a.stop()
        b.stop()
    for relay in (a, b):
        assert "Traceback" not in relay.log.read_text(), relay.log.read_text()[-3000:]
