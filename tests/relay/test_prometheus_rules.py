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

from tests.relay.promserver import require_tool

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "prometheus"
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


def test_the_rules_unit_test_passes_and_covers_every_alert(shipped):
    result = promtool("test", "rules", UNIT_TEST, cwd=shipped)
    assert result.returncode == 0 and "SUCCESS" in result.stdout, result.stdout + result.stderr
    alerts = set(re.findall(r"^\s+- alert: (\w+)$", (shipped / RULES).read_text(), re.MULTILINE))
    tested = set(re.findall(r"alertname: (\w+)$", (shipped / UNIT_TEST).read_text(), re.MULTILINE))
    assert len(alerts) >= 8 and alerts == tested, (alerts, tested)


@pytest.mark.parametrize("old, new, fails", [
    ("dcuscope_clock_uncertainty_seconds > 0.001", "dcuscope_clock_uncertainty_seconds > 0.01", "test"),
    ("> on(job, instance, node) dcuscope_frame_delay_limit_seconds", "< on(job, instance, node) "
     "dcuscope_frame_delay_limit_seconds", "test"),
    ("expr: dcuscope_stage_saturated == 1", "expr: dcuscope_stage_saturated == 1)", "check"),
])
def test_a_broken_rule_fails_promtool(shipped, old, new, fails):
    rules = shipped / RULES
    assert old in rules.read_text()
    rules.write_text(rules.read_text().replace(old, new))
    result = promtool(*(["check", "rules", RULES] if fails == "check" else ["test", "rules", UNIT_TEST]), cwd=shipped)
    assert result.returncode != 0 and "FAILED" in result.stdout + result.stderr, result.stdout


def test_a_config_whose_token_file_is_missing_fails_the_check(shipped, tmp_path):
    (tmp_path / "relay.token").unlink()
    result = promtool("check", "config", CONFIG, cwd=shipped)
    assert result.returncode != 0 and "relay.token" in result.stdout + result.stderr


def test_the_grafana_dashboard_names_only_recorded_series_the_rules_define():
    """(The live test checks that every panel has data from a real relay.)"""
    dashboard = json.loads((CONFIGS / "grafana-dashboard.json").read_text())
    exprs = [t["expr"] for p in dashboard["panels"] for t in p.get("targets", [])]
    recorded = set(re.findall(r"- record: (\S+)", (CONFIGS / RULES).read_text()))
    names = set(re.findall(r"\b((?:node(?:_stage|_source)?:)?dcuscope_[a-z_]+(?::[a-z0-9_]+)?)", " ".join(exprs)))
    assert len(exprs) >= 6 and names
    unknown = {n for n in names if ":" in n and n not in recorded}
    assert not unknown, unknown
