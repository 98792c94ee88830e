"""dcuscope capacity's parts on known inputs: the plan of a count, the figures of a synthetic run
against the timestamps it was made from, bounds, the answer line, the prediction, the report, and
bad input (exit 2, one line, before anything runs)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from dcuscope.capacity.measure import Estimate, after_warmup, measure
from dcuscope.capacity.plan import check_replicable, for_streams, grid
from dcuscope.capacity.predict import describe, predict
from dcuscope.capacity.report import render
from dcuscope.capacity.verdict import FAILS, HOLDS, UNDECIDED, _outcome, answer, check_fps, parse_slo
from dcuscope.cli import main
from dcuscope.core.errors import UsageError
from dcuscope.pipeline.config import load_config
from dcuscope.probes.trace.tracefile import Trace
from dcuscope.protocol.events import FACT
from tests.conftest import REPO, VTEST
from tests.probes.synth import pipeline_run

MS = 1_000_000


def write(tmp_path, text: str, name: str = "c.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_count_cycles_the_sources_plays_files_live_and_sizes_the_batch_and_the_grid(tmp_path):
    config = load_config(write(tmp_path, f"""
sources:
  - {{uri: '{VTEST}', rate: 10}}
  - {{test: ball}}
stages:
  - mux: {{batch-size: 2, width: 320, height: 180}}
  - tiler: {{rows: 1, columns: 2}}
  - convert: {{}}
"""))
    five = for_streams(config, 5)
    assert [s.kind for s in five.sources] == ["uri", "test", "uri", "test", "uri"]
    assert all(s.live for s in five.sources) and five.sources[0].loop and five.sources[0].rate == 10
    mux, tiler, convert = five.stages
    assert mux.properties["batch-size"] == 5 and (tiler.properties["rows"], tiler.properties["columns"]) == (2, 3)
    assert convert is config.stages[2]
    kept = for_streams(config, 2, keep_batch=True)
    assert kept.stages[0].properties["batch-size"] == 2 and kept.stages[1] is config.stages[1]
    served = for_streams(config, 3, rtsp_uris=[f"rtsp://127.0.0.1:1/cam{i}" for i in range(3)], rtsp_mux_timeout_us=1000)
    assert [s.location for s in served.sources][2] == "rtsp://127.0.0.1:1/cam2" and served.sources[0].rate == 10
    assert served.stages[0].properties["live-source"] is True
    assert served.stages[0].properties["batched-push-timeout"] == 1000
    assert [grid(n) for n in (1, 2, 3, 4, 5, 7, 9)] == [(1, 1), (1, 2), (2, 2), (2, 2), (2, 3), (3, 3), (3, 3)]


@pytest.mark.parametrize("yaml, rtsp, says", [
    ("launch: videotestsrc ! fakesink\n", False, "a launch: pipeline has no sources to replicate"),
    ("sources: [{test: ball}]\nstages: [{convert: {}}]\n", False, "the first stage is not a mux"),
    ("sources: [{uri: 'udp://127.0.0.1:5000'}]\nstages: [{mux: {}}]\n", False, "source 0 (uri:udp://127.0.0.1:5000) cannot be replicated"),
    ("sources: [{test: ball}]\nstages: [{mux: {}}]\n", True, "source 0 (test:ball): --rtsp serves file sources"),
])
def test_a_config_that_cannot_be_replicated_says_which_source_and_why(tmp_path, yaml, rtsp, says):
    config = load_config(write(tmp_path, yaml))
    with pytest.raises(UsageError, match=says.replace("(", r"\(").replace(")", r"\)")):
        check_replicable(config, rtsp)


def test_slos_read_as_compare_bounds_with_absolute_values():
    slo = parse_slo("e2e.p99 <= 200ms")
    assert (slo.stage, slo.kind, slo.figure, slo.op, slo.value_ms) == ("e2e", "delay", "p99", "<=", 200.0)
    slo = parse_slo(" infer.service.p95 < 0.04s ")
    assert (slo.stage, slo.kind, slo.figure, slo.value_ms) == ("infer", "service", "p95", 40.0)
    assert parse_slo("mux.wait.mean <= 500us").value_ms == 0.5
    assert parse_slo("infer.mean <= 60ms").short() == "infer.mean ≤ 60 ms"
    for bad in ("e2e.p99 <= 200", "e2e.p99 < +5%", "e2e.p42 <= 1ms", "p99 <= 1ms", "e2e.wait.p99 <= 1ms", "e2e.p99 = 1ms"):
        with pytest.raises(UsageError, match="--slo"):
            parse_slo(bad)


def test_a_bound_holds_fails_or_is_undecided_by_its_whole_interval():
    assert _outcome(Estimate(150, 140, 190), "<=", 200) == HOLDS
    assert _outcome(Estimate(210, 201, 230), "<=", 200) == FAILS
    assert _outcome(Estimate(190, 170, 215), "<=", 200) == UNDECIDED
    assert _outcome(Estimate(29.9, 29.5, 30.2), ">=", 27) == HOLDS
    assert _outcome(Estimate(20.0, 19.0, 21.0), ">=", 27) == FAILS


def synthetic(n_frames=60, n_sources=2, infer_ms=30, period_ms=100, jitter_ms=0):
    header, events, truth = pipeline_run(n_frames, n_sources, period_ns=period_ms * MS, jitter_ns=jitter_ms * MS,
                                         stage_ns=(2 * MS, infer_ms * MS, 3 * MS, 1 * MS, 4 * MS), batched_mux=True)
    return Trace(header, events, dropped=0, complete=True), truth


def test_the_figures_of_a_run_match_the_timestamps_it_was_made_from():
    trace, truth = synthetic(jitter_ms=8)
    figs = measure(trace, 2, warmup_s=1.0)
    steady = truth.frame >= 10  # the first second of origins left out
    e2e_ms = (truth.enter[:, -1] - truth.origin)[steady] / MS
    assert figs.frames == steady.sum() == 100
    assert figs.e2e["mean"].value == pytest.approx(e2e_ms.mean())
    assert figs.e2e["p95"].value == pytest.approx(np.percentile(e2e_ms, 95))
    for f in ("mean", "p50", "p95", "p99"):
        e = figs.e2e[f]
        assert e.low <= e.value <= e.high
    infer_ms = ((truth.exit[:, 1] - truth.enter[:, 1])[steady] / MS).mean()
    assert figs.stages["infer"]["delay"] == pytest.approx(infer_ms)
    # 10 frames/s per stream, every stream; the interval is tight on a steady rate
    assert figs.fps.value == pytest.approx(10.0, rel=1e-6) and figs.fps.low <= 10.0 <= figs.fps.high
    assert figs.nominal_fps is not None and figs.limiting["stage"] == "infer"
    assert figs.threads and set(figs.threads) <= set(trace.header.stages)
    assert (after_warmup(trace.events, 1.0)["point"] == FACT).sum() == (trace.events["point"] == FACT).sum()


def test_the_fps_floor_is_checked_on_the_stream_furthest_below_its_rate():
    trace, _ = synthetic(period_ms=125)  # 8 frames/s while the sources say another rate
    figs = measure(trace, 2, warmup_s=1.0)
    rate = figs.nominal_fps
    assert figs.fps.value == pytest.approx(8.0, rel=1e-6)
    check = check_fps(figs, 0.9, 10.0)
    assert check.outcome == FAILS and "fps ≥ 9 (90 % of 10)" == check.what, check
    assert check_fps(figs, 0.7, 10.0).outcome == HOLDS
    assert check_fps(figs, 0.9, None).outcome == UNDECIDED
    assert rate is None or rate > 0


def count(n, outcome, fps=30.0, checks=None, limiting=None, error=None, u=(0.3,), a=40.0, cpu=0.5):
    """A count's document as search.run_count gives it, with the figures the answer and the model read."""
    stages = {f"s{i}": {"delay": a / len(u), "service": a / len(u), "wait": 0.0, "utilization": ui} for i, ui in enumerate(u)}
    return {"streams": n, "outcome": outcome, "error": error, "cpu_cores": cpu, "server_cores": None, "wall_s": 20.0,
            "rate_fps": 30.0, "limiting": limiting,
            "checks": checks if checks is not None else [{"what": "fps ≥ 27 (90 % of 30)", "outcome": outcome,
                                                          "detail": f"slowest stream {fps:.1f} fps [{fps - 0.2:.1f}, {fps + 0.2:.1f}]"}],
            "figures": {"streams": n, "frames": 450 * n, "incomplete": 0, "fps": {"value": fps, "low": fps - 0.2, "high": fps + 0.2},
                        "fps_mean": fps, "nominal_fps": 30.0,
                        "e2e": {f: {"value": a, "low": a - 1, "high": a + 1} for f in ("mean", "p50", "p95", "p99")},
                        "stages": stages, "between_ms": 0.1, "limiting": limiting,
                        "threads": {f"s{i}": 100 + i for i in range(len(u))}, "dropped": {}, "delivered": 450 * n}}


def test_the_answer_says_the_capacity_the_bounds_and_what_gives_out_next():
    neck = {"stage": "infer", "utilization": 0.98, "thread_utilization": 0.98, "saturated": True}
    counts = [count(n, HOLDS) for n in range(1, 6)] + [count(6, FAILS, fps=22.0, limiting=neck)]
    capacity, line = answer(counts, 8)
    assert capacity == 5
    assert line == ("capacity 5 streams: fps ≥ 27 (90 % of 30) hold at 5 with 95 % confidence; at 6 fps ≥ 27 fails "
                    "(slowest stream 22.0 fps [21.8, 22.2]); infer saturates (utilization 98%)")
    neck = {"stage": "infer", "utilization": 0.79, "thread_utilization": 0.89, "saturated": False}
    assert answer([count(1, FAILS, fps=20.0, limiting=neck)], 8) == (
        0, "capacity 0 streams; at 1 fps ≥ 27 fails (slowest stream 20.0 fps [19.8, 20.2]); infer limits "
           "(utilization 79%, its thread 89%)")
    undecided = [count(1, HOLDS), count(2, UNDECIDED, checks=[{"what": "e2e.p99 ≤ 200 ms", "outcome": UNDECIDED,
                                                               "detail": "e2e.p99 198.0 ms [180.0, 215.0]"}])]
    assert answer(undecided, 8) == (1, "capacity 1 stream: fps ≥ 27 (90 % of 30) hold at 1 with 95 % confidence; "
                                       "undecided at 2: run longer (--duration) (e2e.p99 198.0 ms [180.0, 215.0])")
    assert answer([count(1, HOLDS), count(2, HOLDS)], 2)[1].endswith("; --max-streams 2 reached: it may take more")
    failed = [count(1, FAILS, checks=[], error="source 0 lost: not found")]
    assert answer(failed, 4) == (None, "capacity unknown; at 1 the run failed: source 0 lost: not found")
    unsure = [count(1, UNDECIDED, checks=[{"what": "fps ≥ 27 (90 % of 30)", "outcome": UNDECIDED,
                                           "detail": "slowest stream 27.5 fps [26.0, 29.0]"}])]
    assert answer(unsure, 4) == (None, "capacity unknown; undecided at 1: run longer (--duration) (slowest stream "
                                       "27.5 fps [26.0, 29.0])")
    assert answer([], 4, "stopped by Ctrl-C during 1 stream") == (None, "capacity unknown; stopped by Ctrl-C during 1 stream")
    assert answer([count(1, HOLDS)], 4, "stopped by Ctrl-C during 2 streams")[1].endswith("; stopped by Ctrl-C during 2 streams")


def test_the_prediction_extrapolates_each_threads_utilization_to_its_saturation():
    # two threads: 0.20 + 0.22/stream and 0.05 + 0.01/stream: the first reaches 1.0 at n = 5 (1.08)
    one, two = count(1, HOLDS, u=(0.20, 0.05), a=40.0), count(2, HOLDS, u=(0.42, 0.06), a=70.0)
    p = predict(one, two, [], n_cores=2)
    assert p["saturates_at"] == 5 and p["capacity"] == 4 and p["saturates"]["what"] == "s0"
    assert p["saturates"]["utilization"] == pytest.approx(0.20 + 4 * 0.22)
    assert p["a_ms"] == pytest.approx({1: 40.0, 2: 70.0, 3: 100.0, 4: 130.0})
    assert describe(p) == "predicted capacity 4: thread s0 saturates at 5 (utilization 108%)"
    # a bound reached first: e2e.mean grows 30 ms a stream, 100 ms is passed at 4
    bound = predict(one, two, [parse_slo("e2e.mean <= 100ms")], n_cores=2)
    assert bound["capacity"] == 3 and describe(bound) == "predicted capacity 3: e2e.mean ≤ 100 ms predicted 130 ms at 4"
    # the CPU: 0.5 + 0.6 a stream reaches 2 cores at 4 streams, before any thread saturates
    cpu = predict(count(1, HOLDS, u=(0.1,), cpu=0.5), count(2, HOLDS, u=(0.15,), cpu=1.1), [], n_cores=2)
    assert cpu["saturates_at"] == 4 and cpu["saturates"]["kind"] == "cpu" and cpu["capacity"] == 3
    assert predict(one, two, [parse_slo("infer.p99 <= 1ms")], n_cores=2)["unpredicted"] == ["infer.p99 <= 1ms"]


def test_the_report_has_the_papers_tables_the_prediction_and_the_answer():
    neck = {"stage": "s0", "utilization": 0.98, "thread_utilization": 0.99, "saturated": True}
    counts = [count(1, HOLDS, u=(0.20, 0.05)), count(2, HOLDS, u=(0.42, 0.06), a=70.0),
              count(3, FAILS, fps=20.0, u=(0.98, 0.07), a=300.0, limiting=neck)]
    doc = {"plan": {"config": "x.yaml", "duration_s": 20.0, "warmup_s": 5.0, "fps_floor_pct": 90.0},
           "bounds": ["fps ≥ 90 % of the source's rate"], "counts": counts,
           "prediction": predict(counts[0], counts[1], [], n_cores=2), "notes": ["a note"]}
    doc["capacity"], doc["answer"] = answer(counts, 8)
    text = render(doc)
    assert "A = S/n, mean ms" in text and "300.0 (299.0–301.0)" in text and "s0 98%, thread 99% sat." in text
    assert "note: a note" in text
    # Figure 12's data names its terms: a row per count and stage, delay = service + wait
    head = next(line for line in text.splitlines() if line.startswith("streams  stage"))
    assert re.split(r"\s{2,}", head) == ["streams", "stage", "delay ms", "service ms", "wait ms", "utilization"]
    assert ["1", "s0", "20.0", "20.0", "0.0", "20%"] in [line.split() for line in text.splitlines()]
    assert "·" not in text.split("Per stage")[1].split("Prediction")[0]
    assert "predicted capacity 4" in text and text.rstrip().endswith(doc["answer"])
    md = render(doc, markdown=True)
    assert "| streams | fps/stream (slowest)" in md and f"**{doc['answer']}**" in md


def test_a_prediction_alone_says_its_answer_once_and_its_columns_line_up():
    counts = [count(1, HOLDS, u=(0.20, 0.05)), count(2, HOLDS, u=(0.42, 0.06), a=70.0)]
    prediction = predict(*counts, [], n_cores=2)
    doc = {"plan": {"config": "x.yaml", "duration_s": 20.0, "warmup_s": 5.0, "fps_floor_pct": 90.0, "max_streams": 8,
                    "predict_only": True},
           "bounds": ["fps ≥ 90 % of the source's rate"], "counts": counts, "prediction": prediction, "notes": [],
           "answer": describe(prediction)}
    text = render(doc)
    assert text.count(describe(prediction)) == 1 and text.rstrip().endswith(describe(prediction)), text
    lines = text.splitlines()
    table = lines[lines.index("Prediction from 1 and 2 streams beside the measurement:") + 2:]
    table = table[:table.index("")]
    assert [r.split()[0] for r in table[1:]] == ["1", "2", "3", "4", "5"]
    # every cell of a column ends where its header ends, the measured ones of 3 streams and more ("–") too
    ends = [m.end() for m in re.finditer(r"\S+(?: \S+)*", table[0])]
    for row in table[1:]:
        assert [m.end() for m in re.finditer(r"\S+", row)][1:] == ends[1:], (table[0], row)


@pytest.mark.parametrize("argv, says", [
    (["--slo", "e2e.p99 < 5%"], "--slo 'e2e.p99 < 5%': expected STAGE[.KIND].FIGURE OP VALUE"),
    (["--warmup", "30"], "--warmup (30 s) must leave part of --duration (20 s)"),
    (["--fps-floor", "0"], "--fps-floor is a percentage"),
    (["--plot", "x.gif"], "--plot x.gif: give a file ending in .png, .svg, .pdf"),
])
def test_bad_options_exit_2_with_one_line_before_anything_runs(capsys, argv, says):
    assert main(["capacity", str(REPO / "configs" / "vtest.yaml"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err, err


def test_a_config_without_sources_or_that_cannot_be_replicated_exits_2_naming_it(capsys, tmp_path):
    assert main(["capacity", str(write(tmp_path, "stages: [{mux: {}}]\n"))]) == 2
    assert "missing 'sources'" in capsys.readouterr().err
    camera = write(tmp_path, "sources: [{uri: 'udp://127.0.0.1:5004'}, {test: ball}]\nstages: [{mux: {}}]\n", "u.yaml")
    assert main(["capacity", str(camera)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "source 0 (uri:udp://127.0.0.1:5004) cannot be replicated" in err
