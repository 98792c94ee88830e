"""Statistics against synthetic runs whose every timestamp is known (tests/probes/synth.py)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dcuscope.model.delays import bottleneck, frame_delays, node_stats, series, summarize
from dcuscope.model.frametable import MISSING, frame_table
from dcuscope.probes.trace.stats import stats_document
from dcuscope.probes.trace.tracefile import read_trace, write_trace
from dcuscope.protocol.errors import ProtocolError
from dcuscope.protocol.events import ENTER, EVENT_DTYPE, EXIT, FACT
from tests.probes.synth import run_commands as _cli
from tests.probes.synth import STAGES, pipeline_run

STAT_KEYS = {"count", "mean_ms", "p50_ms", "p95_ms", "p99_ms", "max_ms"}


def expected(values_ns) -> dict:
    """Oracle: the statistics of plain arrays of ns, computed here without probes.trace.stats."""
    v = np.asarray(values_ns, np.float64) / 1e6
    return {"count": v.size, "mean_ms": v.mean(), "p50_ms": np.percentile(v, 50), "p95_ms": np.percentile(v, 95),
            "p99_ms": np.percentile(v, 99), "max_ms": v.max()}


def assert_stats(got: dict, want: dict):
    assert set(got) - {"share", "service", "wait", "utilization", "occupancy"} == STAT_KEYS
    assert got["count"] == want["count"]
    for k in STAT_KEYS - {"count"}:
        assert got[k] == pytest.approx(want[k], rel=1e-12, abs=1e-9), k


def truth_gaps(truth, n_sources):
    """"A->B" -> gap per frame (ns), from the truth matrices."""
    gaps = {}
    for k in range(n_sources):
        sel = truth.source == k
        gaps[f"src{k}->{STAGES[0]}"] = truth.enter[sel, 0] - truth.origin[sel]
    for j in range(1, len(STAGES) + 1):
        name_b = STAGES[j] if j < len(STAGES) else "sink"
        gaps[f"{STAGES[j - 1]}->{name_b}"] = truth.enter[:, j] - truth.exit[:, j - 1]
    return gaps


def test_summarize_uses_linear_percentiles():
    s = summarize([4.0, 1.0, 3.0, 2.0])
    assert s == {"count": 4, "mean_ms": 2.5, "p50_ms": 2.5, "p95_ms": pytest.approx(3.85),
                 "p99_ms": pytest.approx(3.97), "max_ms": 4.0}
    assert summarize([]) == {"count": 0, "mean_ms": None, "p50_ms": None, "p95_ms": None, "p99_ms": None,
                             "max_ms": None}


def test_summarize_percentiles_are_numpys_to_the_last_bit():
    """One partition at the ranks numpy's linear method reads gives np.percentile's figures exactly,
    for any count (1, 2, a few, many), with ties, negatives and a NaN (then NaN, as numpy says)."""
    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 7, 100, 101, 4_999):
        for values in (rng.lognormal(1.0, 1.0, n), np.round(rng.normal(0, 3, n), 1), np.full(n, 2.5)):
            expected = np.percentile(values, (50, 95, 99), method="linear").tolist()
            got = summarize(values)
            assert [got["p50_ms"], got["p95_ms"], got["p99_ms"]] == expected, n
    with_nan = summarize([1.0, np.nan, 3.0])
    assert np.isnan([with_nan["p50_ms"], with_nan["p95_ms"], with_nan["p99_ms"]]).all()


def test_constant_delays_give_exact_stage_gap_and_frame_statistics():
    stage_ns = (2_000_000, 30_000_000, 3_000_000, 1_000_000, 4_000_000)
    header, events, _ = pipeline_run(10, n_sources=2, stage_ns=stage_ns, gap_ns=250_000)
    st = node_stats(header, events, dropped=5)

    assert set(st) == {"stages", "gaps", "frame", "glass", "bottleneck", "fps", "sources", "dropped", "frames"}
    assert list(st["stages"]) == list(STAGES)  # pipeline order; no delay at sources or sink
    for name, ns in zip(STAGES, stage_ns):
        assert_stats(st["stages"][name], expected([ns] * 20))
    assert list(st["gaps"]) == ["src0->mux", "src1->mux", "mux->infer", "infer->tiler", "tiler->convert",
                                "convert->osd", "osd->sink"]
    assert st["gaps"]["src0->mux"]["count"] == 10 and st["gaps"]["mux->infer"]["count"] == 20
    for s in st["gaps"].values():
        assert s["mean_ms"] == pytest.approx(0.25) and s["max_ms"] == pytest.approx(0.25)
    frame_ms = (sum(stage_ns) + 6 * 250_000) / 1e6  # 5 stages + 6 gaps (origin->mux ... osd->sink)
    assert_stats(st["frame"], expected([frame_ms * 1e6] * 20))
    assert st["fps"] == {"0": pytest.approx(10.0), "1": pytest.approx(10.0)}
    assert st["dropped"] == 5
    assert st["frames"] == {"complete": 20, "incomplete": 0}


def test_jittered_run_matches_percentiles_computed_from_the_truth():
    header, events, truth = pipeline_run(97, n_sources=3, jitter_ns=7_000_000, batched_mux=True, seed=3)
    st = node_stats(header, events)
    for j, name in enumerate(STAGES):
        assert_stats(st["stages"][name], expected(truth.exit[:, j] - truth.enter[:, j]))
    for key, values in truth_gaps(truth, 3).items():
        assert_stats(st["gaps"][key], expected(values))
    assert_stats(st["frame"], expected(truth.enter[:, -1] - truth.origin))


@pytest.mark.parametrize("seed", range(5))
def test_frame_delay_is_the_sum_of_stage_delays_and_gaps_for_every_frame(seed):
    rng = np.random.default_rng(seed)
    n_sources = int(rng.integers(1, 5))
    header, events, _ = pipeline_run(int(rng.integers(5, 60)), n_sources=n_sources,
                                     jitter_ns=int(rng.integers(1, 50_000_000)), batched_mux=bool(seed % 2), seed=seed)
    fd = frame_delays(frame_table(header, events))
    table, sr = fd.table, series(fd)
    assert fd.chains.complete.all()
    total = sum(sr.stages.values())  # per stage: one value per complete frame, table order
    gaps = sr.gaps
    for key, values in gaps.items():
        if key.endswith(f"->{STAGES[0]}"):
            continue
        total = total + values
    per_source_gap = np.zeros(len(table))
    for k in range(n_sources):
        per_source_gap[table.source == k] = gaps[f"src{k}->{STAGES[0]}"]
    assert np.array_equal(total + per_source_gap, sr.frame)

    # The same identity on the summary: mean frame delay = sum of stage means + count-weighted gap means.
    st = node_stats(header, events)
    n = st["frame"]["count"]
    sum_of_means = sum(s["mean_ms"] for s in st["stages"].values())
    sum_of_means += sum(s["mean_ms"] * s["count"] / n for s in st["gaps"].values())
    assert st["frame"]["mean_ms"] == pytest.approx(sum_of_means, rel=1e-12)


def test_frames_with_a_lost_event_are_incomplete_and_excluded():
    header, events, truth = pipeline_run(40, n_sources=2, jitter_ns=5_000_000, seed=11)
    rng = np.random.default_rng(1)
    # Origin, enter and exit events (a lost ready point only leaves the frame without a split).
    lost = rng.choice(np.flatnonzero(events["point"] <= EXIT), size=25, replace=False)
    kept = np.delete(events, lost)
    # In this run every event of a frame is needed, so a frame is complete iff it lost none.
    damaged = set(zip(events["source"][lost].tolist(), events["frame"][lost].tolist()))
    st = node_stats(header, kept)
    assert st["frames"] == {"complete": 80 - len(damaged), "incomplete": len(damaged)}

    intact = np.array([(s, f) not in damaged for s, f in zip(truth.source.tolist(), truth.frame.tolist())])
    for j, name in enumerate(STAGES):
        assert_stats(st["stages"][name], expected((truth.exit[:, j] - truth.enter[:, j])[intact]))
    assert_stats(st["frame"], expected((truth.enter[:, -1] - truth.origin)[intact]))


def test_frames_still_in_flight_at_the_end_are_incomplete_not_zero():
    header, events, truth = pipeline_run(10, n_sources=1)
    sink = len(header.stages) - 1
    last = (events["frame"] == 9) & ~((events["stage"] == sink) & (events["point"] == ENTER))
    in_flight = np.concatenate([events[events["frame"] < 9], events[last]])  # frame 9 never reached the sink
    st = node_stats(header, in_flight)
    assert st["frames"] == {"complete": 9, "incomplete": 1}
    assert st["stages"]["osd"]["count"] == 9
    assert_stats(st["frame"], expected((truth.enter[:, -1] - truth.origin)[:9]))


def test_a_tracepoint_seen_twice_keeps_the_earliest():
    header, events, _ = pipeline_run(5, n_sources=1, stage_ns=(1_000_000,) * 5, gap_ns=0)
    infer = header.stages.index("infer")
    again = events[(events["stage"] == infer) & (events["point"] == EXIT)].copy()
    again["ts"] += 50_000_000
    st = node_stats(header, np.concatenate([again, events]))
    assert st["stages"]["infer"]["max_ms"] == pytest.approx(1.0)


def test_frame_table_pairs_events_by_source_and_frame():
    header, events, truth = pipeline_run(3, n_sources=2)
    table = frame_table(header, events)
    assert table.source.tolist() == [0, 0, 0, 1, 1, 1] and table.frame.tolist() == [0, 1, 2, 0, 1, 2]
    assert np.array_equal(table.origin, truth.origin)
    assert table.origin_stage.tolist() == [0, 0, 0, 1, 1, 1]
    first = header.stages.index(STAGES[0])
    assert np.array_equal(table.enter[:, first:], truth.enter)
    assert np.array_equal(table.exit[:, first:-1], truth.exit)
    assert (table.exit[:, -1] == MISSING).all() and (table.enter[:, :first] == MISSING).all()


def test_fps_per_source_counts_intervals_and_lists_idle_sources():
    header, events, _ = pipeline_run(11, n_sources=2, period_ns=40_000_000)
    header.sources[2] = "rtsp://idle"
    one_frame_of_src1 = (events["source"] == 0) | (events["frame"] == 0)
    st = node_stats(header, events[one_frame_of_src1])
    assert st["fps"] == {"0": pytest.approx(25.0), "1": 0.0, "2": 0.0}


def test_no_events_give_empty_statistics():
    header, events, _ = pipeline_run(1)
    st = node_stats(header, events[:0])
    assert st["frame"]["count"] == 0 and st["frames"] == {"complete": 0, "incomplete": 0}
    assert json.loads(json.dumps(st, allow_nan=False)) == st


def test_out_of_range_stage_raises_a_protocol_error():
    header, events, _ = pipeline_run(1)
    bad = np.zeros(1, EVENT_DTYPE)
    bad["stage"] = len(header.stages)
    with pytest.raises(ProtocolError, match="out of range"):
        node_stats(header, np.concatenate([events, bad]))


def test_stats_document_keeps_same_named_nodes_apart():
    a = pipeline_run(3, node="dcu1")
    b = pipeline_run(4, node="dcu1", seed=2)
    c = pipeline_run(5, node="dcu2")

    class T:
        def __init__(self, run, dropped):
            self.header, self.events, self.dropped = run[0], run[1], dropped

    doc = stats_document([T(a, 0), T(b, 1), T(c, 2)])
    assert list(doc["nodes"]) == ["dcu1", "dcu1_2", "dcu2"]
    assert doc["nodes"]["dcu1_2"]["frames"]["complete"] == 8 and doc["nodes"]["dcu2"]["dropped"] == 2


@pytest.fixture
def two_traces(tmp_path):
    paths = []
    for i, node in enumerate(("dcu1", "dcu2")):
        header, events, _ = pipeline_run(8, n_sources=2, node=node, jitter_ns=3_000_000, seed=i)
        paths.append(tmp_path / f"{node}.trace")
        write_trace(paths[-1], header, events, dropped=i)
    return paths


def test_stats_cli_json_prints_one_document(two_traces):
    rc, out, err = _cli("stats", *map(str, two_traces), "--json")
    assert (rc, err) == (0, "")
    doc = json.loads(out)
    assert doc == json.loads(json.dumps(stats_document([read_trace(p) for p in two_traces])))
    assert set(doc["nodes"]) == {"dcu1", "dcu2"} and doc["nodes"]["dcu2"]["dropped"] == 1
    assert set(doc["nodes"]["dcu1"]["stages"]["infer"]) == STAT_KEYS | {"share", "service", "wait", "utilization",
                                                                        "occupancy"}


def test_stats_cli_table_has_one_aligned_block_per_node(two_traces):
    rc, out, _ = _cli("stats", *map(str, two_traces))
    assert rc == 0
    blocks = out.strip().split("\n\n")
    assert [b.splitlines()[0].split()[1] for b in blocks] == ["dcu1", "dcu2"]
    lines = blocks[0].splitlines()
    split_at = next(i for i, ln in enumerate(lines) if "service mean" in ln)
    delays, split = lines[1:split_at], lines[split_at:split_at + 1 + len(STAGES)]
    table = [ln for ln in delays if ln.startswith(("  stage ", "  gap ", "  frame (end"))] + [delays[0]]
    assert len(table) == len(STAGES) + 7 + 1 + 1 and len({len(ln) for ln in table}) == 1
    assert len({len(ln) for ln in split}) == 1 and all(ln.startswith("  stage ") for ln in split[1:])
    st = node_stats(*pipeline_run(8, n_sources=2, node="dcu1", jitter_ns=3_000_000, seed=0)[:2])
    infer = next(ln for ln in delays if ln.startswith("  stage infer")).split()
    assert infer[2:] == [str(st["stages"]["infer"]["count"])] + [
        f"{st['stages']['infer'][k]:.3f}" for k in ("mean_ms", "p50_ms", "p95_ms", "p99_ms", "max_ms")]
    inf = st["stages"]["infer"]
    assert next(ln for ln in split if ln.startswith("  stage infer")).split()[2:] == [
        f"{inf['service']['mean_ms']:.3f}", f"{inf['service']['p99_ms']:.3f}", f"{inf['wait']['mean_ms']:.3f}",
        f"{inf['utilization'] * 100:.1f}", "%", f"{inf['share'] * 100:.1f}", "%", f"{inf['occupancy']:.2f}"]
    b = st["bottleneck"]
    assert f"  {'bottleneck':<14} {b['stage'] + ': ' if b['saturated'] else 'none: '}{b['reason']}" in lines
    assert "source 0       8 delivered, 10.00 frames/s of 10.00 nominal; RTP packets lost 0" in blocks[0]
    assert "16 complete, 0 incomplete" in blocks[0]


def test_stats_says_the_busiest_stage_once_and_a_file_read_faster_than_real_time_is_not_held_to_its_rate():
    from dcuscope.commands.stats import format_stats

    header, events, _ = pipeline_run(8, n_sources=1, jitter_ns=3_000_000, seed=0)
    st = node_stats(header, events)
    st["bottleneck"] = bottleneck({"mux": {"utilization": 0.004, "mean_ms": 3.0, "share": 0.9},
                                   "infer": {"utilization": 0.002, "mean_ms": 0.3, "share": 0.1}})
    st["sources"]["0"]["fps"] = st["sources"]["0"]["nominal_fps"] * 4.5  # a file read as fast as it goes
    text = format_stats({"nodes": {"dcu1": st}})
    neck = next(ln for ln in text.splitlines() if ln.startswith("  bottleneck"))
    assert neck.count("mux") == 2 and "busiest" in neck and neck.count("busiest") == 1, neck
    assert "frames/s (read faster than real time: nominal 10.00)" in text and " of 10.00 nominal" not in text


@pytest.mark.parametrize("content", [None, b"hello\n"])
def test_stats_cli_bad_input_is_one_error_line_and_exit_2(tmp_path, two_traces, content):
    bad = tmp_path / "bad.trace"
    if content is not None:
        bad.write_bytes(content)
    rc, out, err = _cli("stats", str(two_traces[0]), str(bad))
    assert rc == 2 and out == ""
    assert err.startswith("dcuscope: error: ") and str(bad) in err and err.count("\n") == 1


def test_frame_numbers_beyond_the_packed_key_range_give_the_same_statistics():
    header, events, _ = pipeline_run(9, n_sources=2, jitter_ns=3_000_000, seed=8)
    far = events.copy()
    far["frame"][far["point"] != FACT] += 1 << 45  # outside the fast path's 40-bit frame field
    assert node_stats(header, far) == node_stats(header, events)
    table = frame_table(header, far)
    assert table.frame.tolist() == [(1 << 45) + i for i in range(9)] * 2


def _dcuscope(*argv):
    """The real command line, in a child process, as a user runs it."""
    root = Path(__file__).resolve().parents[3]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    return subprocess.run([sys.executable, "-m", "dcuscope.cli", *argv], capture_output=True, text=True,
                          env=env, cwd=root, timeout=60)


def test_dcuscope_stats_through_the_real_command_line(two_traces, tmp_path):
    done = _dcuscope("stats", *map(str, two_traces), "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == json.loads(json.dumps(stats_document([read_trace(p) for p in two_traces])))
    (tmp_path / "junk.trace").write_text("not a trace\n")
    done = _dcuscope("stats", str(tmp_path / "junk.trace"))
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.startswith("dcuscope: error: ") and "junk.trace" in done.stderr
    assert done.stderr.count("\n") == 1


@pytest.mark.parametrize("form", [[], ["--json"]])
def test_stats_to_a_reader_that_went_away_ends_quietly(two_traces, form):
    """``dcuscope stats T | head -0``, or a reader that quit: the table meets a closed pipe."""
    root = Path(__file__).resolve().parents[3]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the command prints anything
    try:
        done = subprocess.run([sys.executable, "-m", "dcuscope.cli", "stats", *map(str, two_traces), *form],
                              stdout=write, stderr=subprocess.PIPE, text=True, env=env, cwd=root, timeout=60)
    finally:
        os.close(write)
    assert done.returncode == 0 and done.stderr == "", done.stderr


def test_service_plus_wait_is_the_stage_delay_and_busy_time_counts_a_batch_once():
    header, events, truth = pipeline_run(40, n_sources=3, jitter_ns=5_000_000, batched_mux=True, seed=7)
    fd = frame_delays(frame_table(header, events))
    service, wait, delay = (fd.per_stage[k] for k in ("service", "wait", "delay"))
    timed = ~np.isnan(service)
    assert timed.sum() == 3 * 40 * len(STAGES)
    assert np.array_equal(service[timed] + wait[timed], delay[timed])
    assert (service[timed] >= 0).all() and (wait[timed] >= 0).all()
    # A batched mux: every frame of a batch waits until the batch's last frame entered.
    mux = header.stages.index("mux")
    ready = truth.enter[:, 0].reshape(3, 40).max(axis=0)[truth.frame]
    assert np.array_equal(wait[:, mux], (ready - truth.enter[:, 0]).astype(float))
    sr = series(fd)
    per_batch = (truth.exit[:, 0] - ready)[truth.source == 0]
    assert sr.busy["mux"] == per_batch.sum()  # once per batch, not three times
    st = node_stats(header, events)
    span = truth.enter[:, -1].max() - truth.origin.min()
    assert st["stages"]["mux"]["utilization"] == pytest.approx(per_batch.sum() / span)
    assert st["glass"]["count"] == 40  # source 0 has capture times, 5 ms before its origins
    own = (truth.enter[:, -1] - truth.origin)[truth.source == 0]
    assert st["glass"]["mean_ms"] == pytest.approx(own.mean() / 1e6 + 5.0)


def _stage(mean_ms, utilization, share=0.1):
    return {"mean_ms": mean_ms, "utilization": utilization, "share": share}


def test_the_bottleneck_is_the_busiest_stage_of_a_saturated_thread_not_the_largest_share():
    stages = {"mux": _stage(380.0, 0.01, 0.7), "infer": _stage(118.0, 0.62, 0.2), "osd": _stage(2.0, 0.35, 0.01)}
    # infer and osd share a thread that is busy 97 %: infer limits, though mux holds frames longest.
    b = bottleneck(stages, {"mux": 1, "infer": 1, "osd": 1})
    assert (b["stage"], b["saturated"], round(b["thread_utilization"], 2)) == ("infer", True, 0.98)
    assert "limits throughput" in b["reason"]
    # Each on its own thread: none saturated; the answer says so and where frames spend time.
    b = bottleneck(stages, {"mux": 1, "infer": 2, "osd": 3})
    assert (b["stage"], b["saturated"]) == ("infer", False)
    assert "no stage is saturated" in b["reason"] and "mux" in b["reason"]
    # A saturated thread wins over a busier stage alone on an unsaturated one.
    stages["tiler"] = _stage(50.0, 0.8)
    b = bottleneck(stages, {"mux": 1, "infer": 1, "osd": 1, "tiler": 4})
    assert b["stage"] == "infer" and b["saturated"]


def test_without_service_times_the_bottleneck_says_it_is_only_the_largest_share():
    b = bottleneck({"mux": _stage(380.0, None, 0.7), "infer": _stage(118.0, None, 0.2)})
    assert b["stage"] == "mux" and b["saturated"] is None and "format-1" in b["reason"]
