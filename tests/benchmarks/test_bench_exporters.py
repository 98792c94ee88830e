"""benchmarks/bench_exporters.py --quick: a real relay fed by simulated nodes in both arms, a real
Prometheus scraping it and a loopback OTLP sink in arm b. Checks the output's shape and that every
run did its work; the figures themselves are the benchmark's to report, not a test's to judge."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import REPO, cli_env

SUMMARY_KEYS = {"ingest_a", "ingest_b", "ingest_lost", "lag_p50_ms_a", "lag_p50_ms_b", "lag_p99_ms_a", "lag_p99_ms_b",
                "relay_cpu_pct_a", "relay_cpu_pct_b", "scrape_ms_mean", "metrics_bytes", "metrics_series",
                "spans_exported_per_s", "otlp_frames_dropped"}


def test_quick_mode_runs_both_arms_and_arm_b_is_scraped_and_exports_spans():
    done = subprocess.run([sys.executable, "benchmarks/bench_exporters.py", "--quick"], cwd=REPO, env=cli_env(),
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-3000:]
    first, *table = done.stdout.strip().splitlines()
    line = json.loads(first)  # one JSON line per node count: --quick runs 2 nodes only
    assert line["nodes"] == 2 and line["frame_limit_ms"] > 0
    assert SUMMARY_KEYS <= set(line["summary"])
    assert table[0].startswith("| nodes |") and table[2].startswith("| 2 |")  # exporters' figures, a vs b
    assert table[3].startswith("| nodes | arm |") and [row[:10] for row in table[5:]] == ["| 2 | a | ", "| 2 | b | "]
    runs = {run["arm"]: run for run in line["runs"]}
    assert sorted(runs) == ["a", "b"]
    for run in runs.values():
        assert run["throughput"]["events"] > 0 and run["throughput"]["lost"] == 0
        assert run["lag"]["events_received"] > 0 and run["lag"]["frames_seen"] > 0
    assert "exporters" not in runs["a"]["throughput"] and "exporters" not in runs["a"]["lag"]
    scraped = runs["b"]["lag"]["exporters"]
    assert scraped["scrapes_ok"] >= 1 and scraped["metrics_series"] > 0 and scraped["series_dcu1"] > 0
    # the relay exported spans in the throughput phase, and all it counts as exported reached the sink
    sent = runs["b"]["throughput"]["exporters"]["final"]
    assert 0 < sent["spans_exported"] <= sent["sink_spans"]
