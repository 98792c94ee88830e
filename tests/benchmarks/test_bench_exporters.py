"""benchmarks/bench_exporters.py --quick: a real relay fed by simulated nodes in both arms, a real
Prometheus scraping it and a loopback OTLP sink in arm b. Checks the output's shape and that every
run did its work; the figures themselves are the benchmark's to report, not a test's to judge.
And its tables, fed runs that produced no figure (a throughput run too short for a rate, a round
without its arm-a partner): n/a with the reason, not a crash."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks import bench_exporters
from benchmarks.bench_exporters import arms_table, summarise, table
from benchmarks.figures import NA, CannotRun
from tests.benchmarks.smoke import assert_cannot_run, assert_every_na_has_a_reason, assert_ran, run_benchmark

SUMMARY_KEYS = {"ingest_a", "ingest_b", "ingest_lost", "lag_p50_ms_a", "lag_p50_ms_b", "lag_p99_ms_a", "lag_p99_ms_b",
                "relay_cpu_pct_a", "relay_cpu_pct_b", "scrape_ms_mean", "metrics_bytes", "metrics_series",
                "spans_exported_per_s", "otlp_frames_dropped"}
TOO_SHORT = "no two samples of the stored count inside 10-90 % of the events: the run was too short"


def blocks(text: str) -> list[list[str]]:
    """The output's blocks of lines, split at blank lines."""
    return [block.splitlines() for block in text.strip().split("\n\n")]


@pytest.mark.alone  # four relays in turn, Prometheus and an OTLP sink at full speed: a burst that starves the tests beside it
def test_quick_mode_runs_both_arms_and_arm_b_is_scraped_and_exports_spans():
    """Not alone: each exporters' window closes once Prometheus has scraped the relay in it (however
    busy the machine), so that arm b's 1 s lag window holds a scrape on a loaded machine too."""
    if not Path(bench_exporters.PROMETHEUS).exists():
        return assert_cannot_run(run_benchmark("bench_exporters.py", "--quick"), "bench_exporters.py", "prometheus")
    done = run_benchmark("bench_exporters.py", "--quick", timeout=180)
    assert_ran(done)
    first, *rest = blocks(done.stdout)
    line = json.loads(first[0])  # one JSON line per node count: --quick runs 2 nodes only
    assert line["nodes"] == 2 and line["frame_limit_ms"] > 0
    assert SUMMARY_KEYS <= set(line["summary"])
    exporters = first[1:]  # the exporters' figures, a vs b; then the reasons of its n/a cells, if any; every arm
    assert exporters[0].startswith("| nodes | ingest a / b") and exporters[2].startswith("| 2 |")
    assert len(exporters) == 3
    [arms] = [block for block in rest if block[0].startswith("| nodes | arm |")]
    assert arms[0].startswith("| nodes | arm |") and [row[:10] for row in arms[2:]] == ["| 2 | a | ", "| 2 | b | "]
    runs = {run["arm"]: run for run in line["runs"]}
    assert sorted(runs) == ["a", "b"]
    for run in runs.values():
        assert run["throughput"]["events"] > 0 and run["throughput"]["lost"] == 0
        assert run["lag"]["events_received"] > 0 and run["lag"]["frames_seen"] > 0
    assert "exporters" not in runs["a"]["throughput"] and "exporters" not in runs["a"]["lag"]
    scraped = runs["b"]["lag"]["exporters"]
    assert scraped["scrapes_ok"] >= 1 and scraped["metrics_series"] > 0 and scraped["series_dcu1"] > 0
    assert runs["b"]["throughput"]["exporters"]["scrapes_ok"] >= 1
    # the relay exported spans in the throughput phase, and all it counts as exported reached the sink
    sent = runs["b"]["throughput"]["exporters"]["final"]
    assert 0 < sent["spans_exported"] <= sent["sink_spans"]


def run(arm: str, rep: int, rate, cpu=90, p50=12.5) -> dict:
    """One arm's run as bench() records it, with only what summarise() reads."""
    throughput = {"events_per_s": rate, "relay_cpu_pct_in_window": cpu}
    lag = {"lag_p50_ms": p50, "lag_p99_ms": 40.0, "relay_cpu_pct": 55}
    if arm == "b":
        throughput["exporters"] = {"scrape_ms_max": 3.1, "otlp_frames_dropped": 0}
        lag["exporters"] = {"scrape_ms_mean": 1.2, "scrape_ms_max": 3.3, "prometheus_cpu_pct": 2,
                            "metrics_bytes": 92295, "metrics_series": 1061, "series_dcu1": 523,
                            "spans_exported_per_s": 694.4, "sink_spans_per_s": 694.4, "otlp_frames_per_s": 42.3,
                            "otlp_frames_dropped": 0, "over_limit_share": NA("no frame completed in the window")}
    return {"arm": arm, "rep": rep, "throughput": throughput, "lag": lag}


def test_a_pair_without_a_figure_is_n_a_with_its_reason_in_both_tables():
    """The crash of issue 21: arm a's throughput run of round 1 too short for a rate (the relay
    stored 600,000 events between two samples), and round 2 without arm a at all."""
    runs = [run("a", 0, NA(TOO_SHORT), cpu=NA(TOO_SHORT)), run("b", 0, 690_000), run("b", 1, 700_000)]
    lines = [{"nodes": 2, "summary": summarise(runs)}]
    s = lines[0]["summary"]
    assert s["ingest_a"] == NA(TOO_SHORT) and s["ingest_b"] == 695_000 and s["ingest_lost"] == NA(TOO_SHORT)
    assert s["ingest_lost_per_pair"] == [NA(TOO_SHORT), NA("no run of arm a in round 2")]
    out = table(lines)
    rows = out.splitlines()
    assert rows[0].startswith("| nodes | ingest a / b")
    assert rows[2].startswith("| 2 | n/a [1] / 695 k | n/a [1] (n/a [1], n/a [2]) |")
    assert f"n/a [1]: {TOO_SHORT}" in rows and "n/a [2]: no run of arm a in round 2" in rows and rows[3] == ""
    assert "n/a: no frame completed in the window" not in out and "no frame completed in the window" in out
    assert_every_na_has_a_reason(out)
    arms = arms_table(lines)
    assert arms.splitlines()[2:4] == ["| 2 | a | n/a [1] | n/a [1] | 12.5 / 40 ms | 55 % |",
                                      "| 2 | b | 695 k (n/a [1]) | 772 k (n/a [1]) | 12.5 / 40 ms | 55 % |"]
    assert_every_na_has_a_reason(arms)


def test_figures_of_an_arm_that_did_not_run_are_n_a_not_a_crash():
    lines = [{"nodes": 8, "summary": summarise([run("a", 0, 1_000_000, p50=NA("no frame reached the /ui client"))])}]
    out = table(lines) + "\n" + arms_table(lines)
    assert "| 8 | 1.00 M / n/a [1] |" in out and "n/a [1]: no run of arm b" in out
    assert "no frame reached the /ui client" in out
    assert_every_na_has_a_reason(out)


def test_without_prometheus_it_says_so_in_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(bench_exporters, "PROMETHEUS", str(tmp_path / "prometheus"))
    with pytest.raises(CannotRun, match="prometheus is missing"):
        bench_exporters.main(["--quick"])
    assert bench_exporters.run(lambda: bench_exporters.main(["--quick"]), "bench_exporters.py") == 2
    assert capsys.readouterr().err.count("\n") == 1
