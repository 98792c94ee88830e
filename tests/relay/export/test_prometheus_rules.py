"""The shipped Prometheus files (configs/prometheus/) pass Prometheus' own checker: ``promtool check
rules`` and ``check config``, and ``promtool test rules`` runs their unit test (every alert firing
on synthetic series where it should, silent where it should not). A broken copy fails each."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.relay.promserver import require_tool
from tests.tlscerts import TestCA

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "prometheus"
RULES, UNIT_TEST, CONFIG = "dcuscope-rules.yml", "dcuscope-rules.test.yml", "prometheus.yml"
SHIPPED_TOKEN_FILE = "/etc/prometheus/dcuscope-relay.token"


def promtool(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([require_tool("promtool"), *args], cwd=cwd, capture_output=True, text=True, timeout=60)


@pytest.fixture
def shipped(tmp_path) -> Path:
    """A copy of configs/prometheus whose example config's token file exists (promtool checks it does)."""
    folder = tmp_path / "prometheus"
    shutil.copytree(CONFIGS, folder)
    token = tmp_path / "relay.token"
    token.write_text("secret")
    config = folder / CONFIG
    assert SHIPPED_TOKEN_FILE in config.read_text()
    config.write_text(config.read_text().replace(SHIPPED_TOKEN_FILE, str(token)))
    return folder


def test_promtool_checks_the_shipped_rules_and_config(shipped):
    rules = promtool("check", "rules", RULES, cwd=shipped)
    assert rules.returncode == 0 and "SUCCESS" in rules.stdout, rules.stdout + rules.stderr
    config = promtool("check", "config", CONFIG, cwd=shipped)
    assert config.returncode == 0 and "SUCCESS: 1 rule files found" in config.stdout, config.stdout + config.stderr
    # The commented HTTPS job, in place of the plain one (its CA file must exist: promtool reads it).
    text = (shipped / CONFIG).read_text()
    job = yaml.safe_load("\n".join(ln.split("#~ ", 1)[1] for ln in text.splitlines()
                                   if ln.lstrip().startswith("#~ ")))
    assert job[0]["scheme"] == "https" and job[0]["tls_config"]["ca_file"] == "/etc/prometheus/dcuscope-ca.pem"
    job[0]["tls_config"]["ca_file"] = str(TestCA(shipped.parent).cert)
    (shipped / "https.yml").write_text(yaml.safe_dump({**yaml.safe_load(text), "scrape_configs": job}))
    config = promtool("check", "config", "https.yml", cwd=shipped)
    assert config.returncode == 0 and "SUCCESS" in config.stdout, config.stdout + config.stderr


def test_the_rules_unit_test_passes_and_covers_every_alert(shipped):
    result = promtool("test", "rules", UNIT_TEST, cwd=shipped)
    assert result.returncode == 0 and "SUCCESS" in result.stdout, result.stdout + result.stderr
    alerts = set(re.findall(r"^\s+- alert: (\w+)$", (shipped / RULES).read_text(), re.MULTILINE))
    tested = set(re.findall(r"alertname: (\w+)$", (shipped / UNIT_TEST).read_text(), re.MULTILINE))
    assert len(alerts) >= 8 and alerts == tested, (alerts, tested)


@pytest.mark.parametrize("old, new, fails", [
    ("last_over_time(node:dcuscope_clock_uncertainty_seconds:max[1m]) > 0.001",
     "last_over_time(node:dcuscope_clock_uncertainty_seconds:max[1m]) > 0.01", "test"),
    ("node:dcuscope_frame_delay_seconds:p99_1m\n          > max", "node:dcuscope_frame_delay_seconds:p99_1m\n          < max",
     "test"),
    ("expr: last_over_time(node_stage:dcuscope_stage_saturated:max[1m]) == 1",
     "expr: last_over_time(node_stage:dcuscope_stage_saturated:max[1m]) == 1)", "check"),
])
def test_a_broken_rule_fails_promtool(shipped, old, new, fails):
    rules = shipped / RULES
    assert old in rules.read_text()
    rules.write_text(rules.read_text().replace(old, new))
    result = promtool(*(["check", "rules", RULES] if fails == "check" else ["test", "rules", UNIT_TEST]), cwd=shipped)
    assert result.returncode != 0 and "FAILED" in result.stdout + result.stderr, result.stdout


FLEET_MISTAKES = {
    "a per-relay alert (two alerts for a node that moved, one on each relay)":
        ("sum without (instance) (increase(dcuscope_source_frames_lost_total[5m]))",
         "increase(dcuscope_source_frames_lost_total[5m])"),
    "counters summed as they stand (the new relay's counter starts at the run's count)":
        ("sum without (instance) (increase(dcuscope_source_frames_lost_total[5m]))",
         "sum without (instance) (max_over_time(dcuscope_source_frames_lost_total[5m]))"),
    "connections counted per relay (a node connected to two relays for a scrape counts twice)":
        ("sum without (node) (node:dcuscope_node_connected:max)", "sum without (node, instance) (dcuscope_node_connected)"),
    "nodes counted per relay (a node two relays keep counts twice)":
        ("count without (node) (node:dcuscope_node_connected:max)",
         "count without (node, instance) (dcuscope_node_connected)"),
    "a handover's gap resets `for:` (the saturated stage's alert starts over on the new relay)":
        ("last_over_time(node_stage:dcuscope_stage_saturated:max[1m]) == 1", "node_stage:dcuscope_stage_saturated:max == 1"),
    "the limit read without bridging the handover":
        ("max without (instance) (last_over_time(dcuscope_frame_delay_limit_seconds[1m]))",
         "max without (instance) (dcuscope_frame_delay_limit_seconds)"),
    "any relay's copy that ended silences the node (an older run's end hides a newer run's loss)":
        ("(max without (instance) (dcuscope_node_last_seen_timestamp_seconds and dcuscope_node_ended == 1)\n"
         "           >= max without (instance) (dcuscope_node_last_seen_timestamp_seconds))",
         "max without (instance) (dcuscope_node_ended) == 1"),
    "a disconnected run's clock bound (frozen figures of a node no longer connected)":
        ("dcuscope_clock_uncertainty_seconds and dcuscope_node_connected == 1", "dcuscope_clock_uncertainty_seconds"),
    "a disconnected run's saturated stage":
        ("dcuscope_stage_saturated and ignoring (stage) dcuscope_node_connected == 1", "dcuscope_stage_saturated"),
}


@pytest.mark.parametrize("mistake", FLEET_MISTAKES)
def test_the_unit_test_catches_rules_that_count_a_node_per_relay(shipped, mistake):
    """The fleet group of the unit test (relays sharing a store, nodes moving between them) fails
    each way of counting a node once per relay, or losing it in a handover."""
    old, new = FLEET_MISTAKES[mistake]
    rules = shipped / RULES
    assert rules.read_text().count(old) == 1, old
    rules.write_text(rules.read_text().replace(old, new))
    assert promtool("check", "rules", RULES, cwd=shipped).returncode == 0
    result = promtool("test", "rules", UNIT_TEST, cwd=shipped)
    assert result.returncode != 0 and "FAILED" in result.stdout + result.stderr, (mistake, result.stdout)


def test_every_aggregation_of_node_series_drops_instance_only():
    """Every rule that aggregates keeps the labels a user gives the targets (``site``): it names the
    labels it drops (``without``), never the ones it keeps (``by``), and drops ``instance`` or ``node``."""
    exprs = [rule["expr"] for group in yaml.safe_load((CONFIGS / RULES).read_text())["groups"]
             for rule in group["rules"]]
    assert len(exprs) >= 20
    joined = " ".join(exprs)
    assert not re.search(r"\b(by|on)\s*\(", joined), "a rule names the labels it keeps"
    drops = set(re.findall(r"without \(([^)]*)\)", joined))
    assert drops == {"instance", "node"}, drops


def test_a_config_whose_token_file_is_missing_fails_the_check(shipped, tmp_path):
    (tmp_path / "relay.token").unlink()
    result = promtool("check", "config", CONFIG, cwd=shipped)
    assert result.returncode != 0 and "relay.token" in result.stdout + result.stderr


def test_the_grafana_dashboard_names_only_recorded_series_the_rules_define():
    """(The live test checks that every panel has data from a real relay.)"""
    dashboard = json.loads((CONFIGS / "grafana-dashboard.json").read_text())
    exprs = [t["expr"] for p in dashboard["panels"] for t in p.get("targets", [])]
    recorded = set(re.findall(r"- record: (\S+)", (CONFIGS / RULES).read_text()))
    names = set(re.findall(r"\b((?:[a-z_]+:)?dcuscope_[a-z_]+(?::[a-z0-9_]+)?)", " ".join(exprs)))
    assert len(exprs) >= 6 and names
    unknown = {n for n in names if ":" in n and n not in recorded}
    assert not unknown, unknown
