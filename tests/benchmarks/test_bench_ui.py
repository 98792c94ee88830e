"""benchmarks/bench_ui.py: its --quick run in headless Chromium (or, without Chromium, one line
saying so), and its summary when no period was measured."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.bench_ui import follow_table, summarise
from benchmarks.figures import NA
from tests.benchmarks.smoke import assert_cannot_run, assert_ran, run_benchmark
from tests.ui.helpers import CHROMIUM

SUMMARY_KEYS = {"min_fps", "mean_fps", "max_draw_ms_mean", "heap_start_mib", "heap_end_mib", "heap_max_mib",
                "dom_start", "dom_end", "frames_per_s_in", "page_errors"}


def test_quick_mode_samples_the_page_twice_and_gives_its_verdict(tmp_path):
    out = tmp_path / "ui.json"
    done = run_benchmark("bench_ui.py", "--quick", "--json", str(out), timeout=120)
    if not Path(CHROMIUM).exists():
        return assert_cannot_run(done, "bench_ui.py", "chromium")
    assert_ran(done, codes=(0, 1))  # 1: FAIL, the page drew under 30 frames/s on a busy machine: a finding
    lines = done.stdout.splitlines()
    assert lines[0] == "load: 1 nodes x 2 sources x 30 fps = 60 frames/s; warm-up 1 s"
    assert lines[1].split() == ["t", "s", "view", "rAF/s", "draw", "ms", "max", "ms", "bars", "frames/s", "in",
                                "heap", "MiB", "DOM"]
    assert [line.split()[1] for line in lines[2:4]] == ["stage", "frame"]
    verdict = lines[-1]
    assert verdict.startswith("PASS: " if done.returncode == 0 else "FAIL: ")
    summary = json.loads("\n".join(lines[4:-1]))
    assert set(summary) == SUMMARY_KEYS and summary["page_errors"] == []
    assert json.loads(out.read_text())["summary"] == summary


def test_without_a_measured_period_the_rates_are_n_a_with_the_reason():
    sample = {"t": 0.0, "raf": 0, "heap": 25 * 2**20, "dom": 300, "perf": {"drawMsMean": 1.0}, "in_fps": 0.0}
    summary = summarise([sample], [])
    none = NA("no sample period was measured")
    rates = ("min_fps", "mean_fps", "max_draw_ms_mean", "frames_per_s_in")
    assert [summary[key] for key in rates] == [none] * 4
    assert summary["heap_start_mib"] == summary["heap_end_mib"] == 25.0


def test_follow_cpu_prints_the_modes_side_by_side():
    """--follow-cpu's table (its run takes a minute: measured by hand, docs/benchmarks-log.md, "Web UI under load")."""
    state = {"seconds": 20.0, "draws_per_s": 60.0, "chromium_cores": 0.49, "renderer_cores": 0.38, "gpu_cores": 0.09}
    lines = follow_table({"every frame": state, "capped": dict(state, draws_per_s=30.0, chromium_cores=0.33)})
    assert lines[0].split() == ["every", "frame", "capped"]
    assert lines[1].split() == ["draws/s", "60.0", "30.0"]
    assert lines[2].split() == ["Chromium", "CPU,", "cores", "0.49", "0.33"]
    assert [line.split()[0] for line in lines[3:]] == ["renderer", "GPU"]
