"""The --quick runs of the benchmarks that take seconds: bench_live_memory.py, bench_stats.py,
bench_pipeline.py, bench_probes.py, bench_coverage.py, bench_spool.py and floor.py; and their tables fed figures a run could
not produce."""

from __future__ import annotations

import re

from benchmarks.bench_pipeline import table
from benchmarks.bench_probes import report
from benchmarks.figures import NA
from dcuscope.probes.capture import native
from tests.benchmarks.smoke import (
    assert_cannot_run, assert_every_na_has_a_reason, assert_ran, json_lines, run_benchmark,
)


def test_live_memory_quick_mode_reports_every_10_simulated_seconds_and_at_the_end():
    done = run_benchmark("bench_live_memory.py", "--quick")
    assert_ran(done)
    rows = json_lines(done.stdout)
    assert [r["frames"] for r in rows] == [3600, 7200]  # 10 and 20 s of 6 sources at 60 fps
    for r in rows:
        assert set(r) == {"minutes", "frames", "bounded", "keep-all", "heap_ratio_keep_all_vs_bounded"}
        assert r["bounded"]["heap_mib"] > 0 and set(r["bounded"]) == {"heap_mib", "stats_ms", "percentile_error"}
    # a run that is not a multiple of --every still ends with a row
    done = run_benchmark("bench_live_memory.py", "--minutes", str(15 / 60), "--every", str(10 / 60))
    assert_ran(done)
    assert [r["frames"] for r in json_lines(done.stdout)] == [3600, 5400]


def test_stats_quick_mode_times_every_step():
    done = run_benchmark("bench_stats.py", "--quick")
    assert_ran(done)
    lines = done.stdout.splitlines()
    assert re.fullmatch(r"\d+ events, \d+ frames, 4 sources", lines[0])
    assert [line[:28].strip() for line in lines[1:]] == [
        "node_stats", "write_trace", "trace file size", "read_trace", "export perfetto (to JSON)", "export csv"]


def test_pipeline_quick_mode_runs_both_variants_and_prints_the_table():
    done = run_benchmark("bench_pipeline.py", "--quick")
    assert_ran(done)
    lines = done.stdout.splitlines()
    assert [line.split(" frames/s")[0].split()[:4] for line in lines[:2]] == [
        ["rep", "1:", "1", "source(s)"]] * 2
    assert "probes=off" in lines[0] and "probes=on" in lines[1] and "tracepoints" in lines[1]
    head = lines.index(" sources  no probes     probes  probes/none  vs 1 source")
    assert lines[head + 1].split()[0] == "1" and len(lines[head + 1].split()) == 5


def test_pipeline_table_shows_a_failed_variant_as_n_a_with_its_reason():
    results = {(1, False): [30.0, 32.0], (1, True): [NA("the run failed: infer: model file x does not exist")] * 2,
               (2, False): [NA("3 collages reached the sink")], (2, True): [20.0]}
    lines = table(results, [1, 2])
    assert lines[1].split() == ["1", "31.00", "n/a", "[1]", "n/a", "[1]", "1.00"]
    assert lines[2].split() == ["2", "n/a", "[2]", "20.00", "n/a", "[2]", "n/a", "[2]"]
    assert lines[3:] == ["n/a [1]: the run failed: infer: model file x does not exist",
                         "n/a [2]: 3 collages reached the sink"]


def test_probes_quick_mode_reports_every_mode():
    done = run_benchmark("bench_probes.py", "--quick")
    if native.load() is None:
        return assert_cannot_run(done, "bench_probes.py", "the native probes are unavailable")
    assert_ran(done)
    lines = done.stdout.strip().splitlines()
    assert lines[0].startswith("== identity20: 300 frames, 42 tracepoints per frame (46 under GST_TRACERS=dcuscope)")
    assert lines[2].split()[:3] == ["mode", "fps", "x"]
    assert [line.split()[0] for line in lines[3:9]] == ["none", "latency", "probes", "hooks", "tracer", "python"]
    summary = [line.split(" cost per tracepoint")[0] for line in lines[9:] if not line.startswith("n/a [")]
    assert summary == ["hooks / probes", "hooks / latency", "python / hooks"]


def test_probes_against_a_folder_that_is_no_checkout_nor_venv_is_refused_before_any_run(tmp_path):
    done = run_benchmark("bench_probes.py", "--quick", "--against", str(tmp_path))
    assert done.returncode == 2 and "neither a dcuscope checkout" in done.stderr and not done.stdout
    assert "nor a venv with dcuscope installed" in done.stderr


def test_probes_report_without_tracepoints_is_n_a_with_the_reason(capsys):
    run = {"wall": 1.0, "cpu": 0.5, "points": 0}
    report("identity20", 100, {m: [dict(run)] for m in ("none", "latency", "probes", "hooks", "tracer", "python")})
    out = capsys.readouterr().out
    assert "n/a (no tracepoints counted)" in out
    assert_every_na_has_a_reason(out)


def test_live_tick_runs_each_checkout_in_turn_and_prints_its_cost_beside_this_ones():
    done = run_benchmark("bench_live_tick.py", "--runs", "2", "--seconds", "1", "--rounds", "1", "--checkout", ".")
    assert_ran(done)
    lines = done.stdout.splitlines()
    assert lines[0] == "2 paced runs, 30 ticks/s, 1 s of node time, 1 rounds"
    assert re.fullmatch(r"this checkout: [\d.]+ µs per event, \d+ µs per run and tick, [\d,]+ frames shown \(1\.00× this checkout\)",
                        lines[1])
    assert re.fullmatch(r"\S+: [\d.]+ µs per event, \d+ µs per run and tick, [\d,]+ frames shown \([\d.]+× this checkout\)", lines[3])
    for line in (lines[2], lines[4]):  # each checkout's statistics under its line
        assert re.fullmatch(r"  statistics of a run at the end, ms \(each round's median\): window [\d.]+; whole run [\d.]+; "
                            r"the engine holds [\d.]+ MB a run", line), line
    assert int(lines[1].split("tick, ")[1].split(" frames")[0].replace(",", "")) > 100
    done = run_benchmark("bench_live_tick.py", "--checkout", "/nonexistent")
    assert done.returncode == 2 and "not a dcuscope checkout" in done.stderr


def test_push_clock_times_a_runs_pushes_with_its_clock_history_beside_other_checkouts():
    done = run_benchmark("bench_push_clock.py", "--runs", "2", "--reports", "20", "--pushes", "3", "--rounds", "1",
                         "--checkout", ".")
    assert_ran(done)
    lines = done.stdout.splitlines()
    assert lines[0] == "2 runs, 20 clock reports each, 3 pushes timed, 1 rounds; µs per run and push (each round's median)"
    for line, who in zip(lines[1:], ("this checkout", r"\S+")):
        history = re.fullmatch(who + r": clock history (\d+) estimates; frames pushed \d+; statistics pushed \d+", line)
        assert history and 15 <= int(history[1]) <= 20, line  # about one a report, 2 s apart
    done = run_benchmark("bench_push_clock.py", "--checkout", "/nonexistent")
    assert done.returncode == 2 and "not a dcuscope checkout" in done.stderr


def test_coverage_prints_old_and_new_side_by_side():
    done = run_benchmark("bench_coverage.py", "--runs", "2", "--frames", "300", "--resamples", "50")
    assert_ran(done)
    rows = [line.split(" | ")[:3] for line in done.stdout.splitlines() if line.startswith("| old") or line.startswith("| new")]
    assert rows == [[f"| {m}", phi, noise] for m in ("old", "new") for phi in ("0.7", "0.9")
                    for noise in ("gaussian", "lognormal")], done.stdout


def test_profile_relay_splits_samples_by_category_and_names_the_innermost_place_of_ours(tmp_path):
    from benchmarks.profile_relay import categorise, report
    raw = tmp_path / "raw.txt"
    raw.write_text(
        "<module> (/x/relay/__main__.py:1);Ticker.tick (/x/relay/api/ui.py:9);maintain_all (/x/relay/live/run.py:5);"
        "LiveRun._merge (/x/relay/live/run.py:9);unique (/v/lib/python3.11/site-packages/numpy/lib/a.py:3) 30\n"
        "<module> (/x/relay/__main__.py:1);Ingest.handle (/x/relay/ingest/endpoint.py:1);"
        "write (/usr/lib/python3.11/asyncio/selector_events.py:5) 10\n"
        "<module> (/x/relay/__main__.py:1);EpollSelector.select (/usr/lib/python3.11/selectors.py:4) 50\n")
    counts, total, places = categorise(raw)
    assert total == 40  # the event loop waiting is not CPU
    assert counts["pairing (LiveRun.maintain, maintain_all)"] == 30
    assert places["pairing (LiveRun.maintain, maintain_all)", "LiveRun._merge (run.py)"] == 30
    assert places["ingest: receive, decode, check, acknowledge", "Ingest.handle (endpoint.py)"] == 10
    run = {"events": 1000, "batches": 10, "cpu_s": 0.004, "wall_s": 1.0, "nodes_cpu_s": 0.0,
           "shares": {name: counts[name] / total for name in counts},
           "places": {f"{c}\t{p}": n / total for (c, p), n in places.items()}}
    run["shares"].update({name: run["shares"].get(name, 0.0) for name in
                          ("push: frames built", "fan-out: Redis publish and receive", "push: encoded and sent",
                           "statistics pushed", "fleet rows", "store writer thread",
                           "socket writes (pushes, acknowledgements)", "clock exchanges", "other")})
    lines = report("here", [run], top=3)
    at = next(i for i, line in enumerate(lines) if line.lstrip().startswith("pairing"))
    assert re.fullmatch(r" +pairing \(LiveRun\.maintain, maintain_all\) +75% +3\.00 +300", lines[at])
    assert re.fullmatch(r" +LiveRun\._merge \(run\.py\) +3\.00 +300", lines[at + 1])


def test_spool_quick_mode_measures_every_mode_side_by_side_and_drains():
    done = run_benchmark("bench_spool.py", "--quick")
    assert_ran(done)
    figures = json_lines(done.stdout)[-1]
    assert set(figures["cpu_us_per_event"]) == {"off", "on", "on, fsync every batch"}
    assert all(v > 0 for v in figures["cpu_us_per_event"].values())
    assert figures["on_vs_off"] == figures["cpu_us_per_event"]["on"] / figures["cpu_us_per_event"]["off"]
    assert 24 <= figures["bytes_per_event"] < 25 and figures["drain_events_per_s"] > 0
    assert "  spool                     µs/event   vs off" in done.stdout.splitlines()


def test_floor_quick_mode_prints_the_compiled_cores_cost_per_event_and_per_frame():
    done = run_benchmark("floor.py", "--quick")
    assert_ran(done)
    m = re.search(r"merge ([\d.]+) µs/event; the delay model's judgement ([\d.]+) µs/frame", done.stdout)
    assert m and 0 < float(m[1]) < 50 and 0 < float(m[2]) < 50, done.stdout
