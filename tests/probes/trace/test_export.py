"""Perfetto/Chrome Trace Event JSON and CSV exports, checked structurally against known runs."""

import csv
import io
import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from dcuscope.model.delays import delay_summary, frame_delays, series
from dcuscope.model.frametable import frame_table
from dcuscope.probes.trace.export import CSV_COLUMNS, assign_lanes, perfetto_document, write_csv
from dcuscope.probes.trace.tracefile import read_trace, write_trace
from dcuscope.protocol.events import CAPTURE, ENTER, EXIT, FORMAT_VERSION, ORIGIN, READY
from dcuscope.relay.clock.correction import Correction, Segment
from tests.conftest import run_cli
from tests.probes.synth import run_commands as _cli
from tests.probes.synth import STAGES, pipeline_run


def _doc(*runs):
    doc = perfetto_document([(h, e) for h, e, _ in runs])
    # Valid JSON as the viewers read it: no NaN or Infinity, everything serialisable.
    return json.loads(json.dumps(doc, allow_nan=False))


def _by_phase(doc, ph):
    return [e for e in doc["traceEvents"] if e["ph"] == ph]


def _stage_slices(doc):
    """The slice of each frame at each stage (not the wait and service parts nested in it, nor
    the capture slices)."""
    return [e for e in _by_phase(doc, "X") if e["name"].startswith("frame ")]


def _thread_names(doc):
    return {(e["pid"], e["tid"]): e["args"]["name"] for e in _by_phase(doc, "M") if e["name"] == "thread_name"}


@pytest.fixture(scope="module")
def two_nodes():
    a = pipeline_run(12, n_sources=2, node="dcu1", jitter_ns=4_000_000, batched_mux=True, seed=1)
    b = pipeline_run(7, n_sources=3, node="dcu2", jitter_ns=4_000_000, seed=2)
    return a, b


def test_required_fields_and_one_named_process_per_node(two_nodes):
    doc = _doc(*two_nodes)
    assert doc["displayTimeUnit"] == "ms" and isinstance(doc["traceEvents"], list)
    for e in doc["traceEvents"]:
        assert {"ph", "name", "pid", "tid"} <= set(e), e
        if e["ph"] in "Xistf":
            assert isinstance(e["ts"], (int, float)) and e["ts"] >= 0
        if e["ph"] == "X":
            assert isinstance(e["dur"], (int, float)) and e["dur"] >= 0
            assert {"source", "frame"} <= set(e["args"])
            if e["name"].startswith("frame "):
                assert {"delay_ms", "gap_ms", "service_ms", "wait_ms", "complete"} <= set(e["args"])
        if e["ph"] == "i":
            assert e["s"] == "t"
    procs = {e["pid"]: e["args"]["name"] for e in _by_phase(doc, "M") if e["name"] == "process_name"}
    assert procs == {1: "dcu1", 2: "dcu2"}
    names = _thread_names(doc)
    used = {(e["pid"], e["tid"]) for e in doc["traceEvents"] if e["ph"] not in "MC"}
    assert used <= set(names)  # every track has a name (counters are the process's)
    assert "infer · src 2" in {n for (pid, _), n in names.items() if pid == 2}


def test_slices_are_in_microseconds_relative_to_the_earliest_event(two_nodes):
    (h1, e1, truth), run2 = two_nodes
    doc = _doc((h1, e1, truth), run2)
    t0 = min(int(e1["ts"].min()), int(run2[1]["ts"].min()))
    assert doc["otherData"]["t0_ns"] == t0
    names = _thread_names(doc)
    infer = STAGES.index("infer")
    row = int(np.flatnonzero((truth.source == 1) & (truth.frame == 5))[0])
    [s] = [e for e in _stage_slices(doc)
           if e["pid"] == 1 and names[(1, e["tid"])] == "infer · src 1" and e["args"]["frame"] == 5]
    assert s["name"] == "frame 5" and s["args"]["source"] == 1
    assert s["ts"] == pytest.approx((truth.enter[row, infer] - t0) / 1e3, abs=1e-3)
    assert s["dur"] == pytest.approx((truth.exit[row, infer] - truth.enter[row, infer]) / 1e3, abs=1e-9)
    assert s["args"]["delay_ms"] == pytest.approx(s["dur"] / 1e3)
    assert s["args"]["gap_ms"] == pytest.approx((truth.enter[row, infer] - truth.exit[row, infer - 1]) / 1e6)
    # One slice per frame per stage with an exit; origins and sink arrivals are instants.
    assert len(_stage_slices(doc)) == (24 + 21) * len(STAGES)
    assert len(_by_phase(doc, "i")) == (24 + 21) * 2


def _assert_slices_nest_per_thread(doc):
    """Slices on one thread are disjoint or nested (in ns as Perfetto reads them); returns the
    stage slices' spans per thread."""
    per_thread, stage_spans = defaultdict(list), defaultdict(list)
    for e in _by_phase(doc, "X"):
        span = (_ns(e["ts"]), _ns(e["ts"]) + _ns(e["dur"]))
        per_thread[(e["pid"], e["tid"])].append(span)
        if e["name"].startswith("frame "):
            stage_spans[(e["pid"], e["tid"])].append(span)
    for spans in per_thread.values():
        open_ends: list[int] = []  # ends of the slices enclosing the current one
        for start, end in sorted(spans, key=lambda span: (span[0], -span[1])):
            while open_ends and open_ends[-1] <= start:
                open_ends.pop()
            assert not open_ends or end <= open_ends[-1], (start, end, open_ends)
            open_ends.append(end)
    return stage_spans


def test_batched_frames_sit_on_per_source_tracks_that_never_overlap(two_nodes):
    doc = _doc(*two_nodes)
    _assert_slices_nest_per_thread(doc)
    names = _thread_names(doc)
    # A batch: frame i of both sources leaves the mux at one instant, on two different tracks.
    mux_exits = defaultdict(set)
    for e in _stage_slices(doc):
        if e["pid"] == 1 and e["cat"] == "mux":
            mux_exits[round(e["ts"] + e["dur"], 3)].add(names[(1, e["tid"])])
    assert all(v == {"mux · src 0", "mux · src 1"} for v in mux_exits.values()) and len(mux_exits) == 12
    assert not any("#" in n for n in names.values())  # one lane suffices here


def test_a_stage_holding_two_frames_of_one_source_gets_a_second_lane():
    # 30 ms of inference per frame at 50 fps: frame n+1 enters before frame n leaves.
    run = pipeline_run(6, n_sources=1, period_ns=20_000_000, jitter_ns=1_000_000, seed=4)
    doc = _doc(run)
    per_thread = _assert_slices_nest_per_thread(doc)
    names = _thread_names(doc)
    lanes = sorted(n for n in names.values() if n.startswith("infer"))
    assert lanes == ["infer · src 0", "infer · src 0 #2"]
    assert sum(len(v) for k, v in per_thread.items() if names[k].startswith("infer")) == 6


def test_assign_lanes_reuses_the_first_free_lane():
    start = np.array([0, 5, 10, 12, 30])
    end = np.array([10, 15, 20, 13, 31])
    assert assign_lanes(start, end).tolist() == [0, 1, 0, 2, 0]
    assert assign_lanes(np.array([3, 0]), np.array([4, 3])).tolist() == [0, 0]


def test_flows_follow_each_frame_across_its_stages(two_nodes):
    doc = _doc(*two_nodes)
    flows = defaultdict(list)
    for e in doc["traceEvents"]:
        if e["ph"] in "stf":
            flows[e["id"]].append(e)
    assert len(flows) == 24 + 21  # one per frame, ids unique across nodes
    slices = defaultdict(list)
    for e in _stage_slices(doc):
        slices[(e["pid"], e["tid"])].append(e)
    for events in flows.values():
        assert [e["ph"] for e in events] == ["s"] + ["t"] * (len(STAGES) - 2) + ["f"]
        assert len({(e["name"], e["cat"], e["pid"]) for e in events}) == 1
        assert events[-1]["bp"] == "e"
        assert [e["ts"] for e in events] == sorted(e["ts"] for e in events)
        frames = set()
        for e in events:  # each flow point lies inside one slice of its own thread: that slice binds it
            [inside] = [s for s in slices[(e["pid"], e["tid"])] if s["ts"] < e["ts"] < s["ts"] + s["dur"]]
            frames.add((inside["args"]["source"], inside["args"]["frame"]))
        assert len(frames) == 1


def _read_csv(text):
    return list(csv.DictReader(io.StringIO(text)))


def test_csv_has_one_row_per_frame_per_stage_with_delays_and_gaps():
    header, events, truth = pipeline_run(4, n_sources=2, jitter_ns=2_000_000, seed=5)
    out = io.StringIO()
    assert write_csv(out, [(header, events)]) == 8 * (1 + len(STAGES) + 1)
    rows = _read_csv(out.getvalue())
    assert tuple(rows[0]) == CSV_COLUMNS
    r = {(int(x["source"]), int(x["frame"]), x["stage"]): x for x in rows}
    row = int(np.flatnonzero((truth.source == 1) & (truth.frame == 2))[0])
    origin = r[(1, 2, "src1")]
    assert (origin["enter_ns"], int(origin["exit_ns"]), origin["delay_ms"], origin["gap_ms"]) == (
        "", truth.origin[row], "", "")
    tiler = r[(1, 2, "tiler")]
    j = STAGES.index("tiler")
    assert (int(tiler["enter_ns"]), int(tiler["exit_ns"])) == (truth.enter[row, j], truth.exit[row, j])
    assert float(tiler["delay_ms"]) == pytest.approx((truth.exit[row, j] - truth.enter[row, j]) / 1e6, abs=1e-6)
    assert float(tiler["gap_ms"]) == pytest.approx((truth.enter[row, j] - truth.exit[row, j - 1]) / 1e6, abs=1e-6)
    sink = r[(1, 2, "sink")]
    assert sink["exit_ns"] == "" and sink["delay_ms"] == "" and sink["complete"] == "1"
    assert float(r[(0, 0, "mux")]["gap_ms"]) == pytest.approx((truth.enter[0, 0] - truth.origin[0]) / 1e6, abs=1e-6)


def _drifting_clock(events):
    """A correction of two estimates, the second from the middle of the run on, each with a drift and
    a bound that grows away from its reference: every frame gets its own offset and bound."""
    mid = int(np.median(events["ts"]))
    return Correction("estimate", "offset estimated by the relay", (
        Segment(from_ns=0, ref_ns=int(events["ts"].min()), offset_ns=3_000_000, drift_ppb=50_000, uncertainty_ns=120_000,
                growth_ppb=2_000),
        Segment(from_ns=mid, ref_ns=mid, offset_ns=3_100_000, drift_ppb=-20_000, uncertainty_ns=40_000, growth_ppb=1_000),
    ))


def test_exports_carry_each_nodes_clock_correction_and_each_frames_offset_and_bound():
    header, events, truth = pipeline_run(30, n_sources=2, jitter_ns=2_000_000, seed=5)
    clock = _drifting_clock(events)
    origin = {(int(s), int(f)): int(o) for s, f, o in zip(truth.source, truth.frame, truth.origin)}
    expected = {k: (int(clock.offsets(np.array([o]))[0]), int(clock.uncertainties(np.array([o]))[0]))
                for k, o in origin.items()}
    assert len(set(expected.values())) == len(expected)  # the test would see a scalar used for all
    doc = json.loads(json.dumps(perfetto_document([(header, events)], clocks=[clock]), allow_nan=False))
    last = int(events["ts"].max())
    offset, bound = clock.at(last)
    assert doc["otherData"]["clock"] == {"dcu1": {"applied": "estimate", "why": "offset estimated by the relay",
                                                  "correction_ns": offset, "uncertainty_ns": bound, "at_ns": last}}
    [label] = [e["args"]["labels"] for e in _by_phase(doc, "M") if e["name"] == "process_labels"]
    assert label == f"clock estimate: {offset / 1e6:+.3f} ms ± {bound / 1e3:.1f} µs"
    framed = [e for e in doc["traceEvents"] if e["ph"] in "Xi" and e["name"].startswith("frame ")]
    assert len(framed) == 60 * (len(STAGES) + 2)
    for e in framed:
        a = e["args"]
        assert (a["clock_ns"], a["clock_uncertainty_ns"]) == expected[a["source"], a["frame"]], e
    out = io.StringIO()
    write_csv(out, [(header, events)], [clock])
    rows = _read_csv(out.getvalue())
    assert len(rows) == 60 * (len(STAGES) + 2)
    for r in rows:
        assert (int(r["clock_ns"]), int(r["clock_uncertainty_ns"])) == expected[int(r["source"]), int(r["frame"])], r


def test_exports_without_a_correction_say_nothing_was_subtracted_and_no_bound_is_known():
    header, events, _ = pipeline_run(3, n_sources=1)
    doc = perfetto_document([(header, events)])
    assert doc["otherData"]["clock"] == {}
    assert not [e for e in doc["traceEvents"] if e.get("name") == "process_labels" or "clock_ns" in e.get("args", {})]
    out = io.StringIO()
    write_csv(out, [(header, events)])
    assert {(r["clock_ns"], r["clock_uncertainty_ns"]) for r in _read_csv(out.getvalue())} == {("0", "")}


def test_csv_marks_incomplete_frames():
    header, events, _ = pipeline_run(3, n_sources=1)
    sink = len(header.stages) - 1
    keep = ~((events["frame"] == 2) & (events["stage"] == sink))
    out = io.StringIO()
    write_csv(out, [(header, events[keep])])
    rows = _read_csv(out.getvalue())
    assert {x["complete"] for x in rows if x["frame"] == "2"} == {"0"}
    assert {x["complete"] for x in rows if x["frame"] != "2"} == {"1"}


def test_export_cli_writes_perfetto_and_csv_files(tmp_path, two_nodes):
    paths = []
    for h, e, _ in two_nodes:
        paths.append(str(tmp_path / f"{h.node}.trace"))
        write_trace(paths[-1], h, e)
    rc, _, err = _cli("export", *paths, "--format", "perfetto", "-o", str(tmp_path / "out.json"))
    assert (rc, err) == (0, "")
    doc = json.loads((tmp_path / "out.json").read_text())
    assert doc == _doc(*two_nodes)
    rc, _, _ = _cli("export", *paths, "--format", "csv", "-o", str(tmp_path / "out.csv"))
    rows = _read_csv((tmp_path / "out.csv").read_text())
    assert rc == 0 and len(rows) == (24 + 21) * (len(STAGES) + 2) and {x["node"] for x in rows} == {"dcu1", "dcu2"}
    rc, out, _ = _cli("export", paths[0], "--format", "csv", "-o", "-")
    assert rc == 0 and out.startswith(",".join(CSV_COLUMNS))


@pytest.mark.parametrize("argv", [
    ("export", "{missing}", "-o", "{out}"),
    ("export", "-o", "{out}"),
    ("export", "{trace}", "-o", "{tmp}/no/such/dir/out.json"),
])
def test_export_cli_errors_are_one_line_and_exit_2(tmp_path, two_nodes, argv):
    h, e, _ = two_nodes[0]
    write_trace(tmp_path / "t.trace", h, e)
    subst = {"missing": tmp_path / "missing.trace", "out": tmp_path / "out.json", "trace": tmp_path / "t.trace",
             "tmp": tmp_path}
    rc, out, err = _cli(*(a.format(**subst) for a in argv))
    assert rc == 2 and out == ""
    assert err.startswith("dcuscope: error: ") and err.count("\n") == 1


def test_dcuscope_export_through_the_real_command_line(tmp_path, two_nodes):
    h, e, _ = two_nodes[0]
    write_trace(tmp_path / "t.trace", h, e)
    root = Path(__file__).resolve().parents[3]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run([sys.executable, "-m", "dcuscope.cli", "export", str(tmp_path / "t.trace"), "--format",
                           "perfetto", "-o", str(tmp_path / "t.json")], capture_output=True, text=True, env=env,
                          cwd=root, timeout=60)
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "t.json").read_text()) == _doc(two_nodes[0])


def test_export_to_a_reader_that_stops_early_ends_quietly(tmp_path):
    """``dcuscope export ... -o - | head``: the reader closes the pipe after a few lines."""
    h, e, _ = pipeline_run(3000, n_sources=2, node="dcu1", seed=3)  # megabytes of JSON: more than a pipe holds
    write_trace(tmp_path / "t.trace", h, e)
    root = Path(__file__).resolve().parents[3]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "export", str(tmp_path / "t.trace"), "-o", "-"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=root)
    try:
        assert proc.stdout.read(100).startswith(b"{")
        proc.stdout.close()  # as head does once it has its lines
        err = proc.stderr.read().decode()
        assert proc.wait(60) == 0 and err == "", err
    finally:
        proc.kill()
        proc.wait()


# A real pipeline: two cameras batched by the mux, which holds the frame of one until the other's
# arrives (wait > 0 there), then a slow element and the usual stages (service > 0 everywhere).
REAL_YAML = """\
sources:
  - {test: smpte, width: 320, height: 240, rate: 30}
  - {test: ball, width: 320, height: 240, rate: 30}
stages:
  - mux: {batch-size: 2, width: 320, height: 240}
  - {factory: identity, name: slow, properties: {sleep-time: 5000}}
  - tiler: {rows: 1, columns: 2, width: 640, height: 240}
  - convert: {format: RGBA}
  - osd: {}
"""


@pytest.fixture(scope="module")
def real_trace(tmp_path_factory):
    where = tmp_path_factory.mktemp("real")
    (where / "p.yaml").write_text(REAL_YAML)
    done = run_cli("run", where / "p.yaml", "--probes", "--trace", where / "t.jsonl", "--num-frames", "40", "-q",
                   cwd=where)
    assert done.returncode == 0, done.stderr
    trace = read_trace(where / "t.jsonl")
    assert trace.header.format == FORMAT_VERSION and trace.complete
    return trace


def _ns(us: float) -> int:
    """A ``ts`` or ``dur`` as Perfetto reads it: int(µs * 1000), truncated."""
    return int(us * 1000)


def _raw(events) -> dict:
    """(source, frame, stage, point) -> earliest ts, straight from the events."""
    out: dict = {}
    for key, ts in zip(zip(*(events[c].tolist() for c in ("source", "frame", "stage", "point"))), events["ts"].tolist()):
        out[key] = min(ts, out.get(key, ts))
    return out


def _stage_slices_and_parts(doc):
    """(tid, source, frame, stage) -> (start ns, dur ns, args, position in the file) of each stage
    slice, and -> {"wait" | "service": (start ns, dur ns, args, position)} of the parts."""
    t0 = doc["otherData"]["t0_ns"]
    slices, parts = {}, defaultdict(dict)
    for i, e in enumerate(doc["traceEvents"]):
        if e["ph"] != "X" or e["cat"] == "capture":
            continue
        key = (e["tid"], e["args"]["source"], e["args"]["frame"], e["cat"])
        value = (t0 + _ns(e["ts"]), _ns(e["dur"]), e["args"], i)
        if e["name"] in ("wait", "service"):
            parts[key][e["name"]] = value
        else:
            assert e["name"] == f"frame {e['args']['frame']}"
            slices[key] = value
    return slices, parts


def test_wait_and_service_slices_of_a_real_run_nest_in_each_stage_slice_exactly(real_trace):
    header, events = real_trace.header, real_trace.events
    doc = _doc((header, events, None))
    slices, parts = _stage_slices_and_parts(doc)
    assert parts.keys() <= slices.keys()
    raw = _raw(events)
    seen = defaultdict(int)
    for (tid, src, frm, stage), (start, dur, args, at) in slices.items():
        s = header.stages.index(stage)
        enter, exit_ = raw[src, frm, s, ENTER], raw[src, frm, s, EXIT]
        assert (start, dur) == (enter, exit_ - enter)
        # The model's split, computed here from the events: work starts at ready, within [enter, exit].
        begin = min(max(raw[src, frm, s, READY], enter), exit_)
        wait, service = begin - enter, exit_ - begin
        assert (args["wait_ms"], args["service_ms"]) == (wait / 1e6, service / 1e6)
        mine = parts[tid, src, frm, stage]
        assert set(mine) == {name for name, ns in (("wait", wait), ("service", service)) if ns > 0}
        w_start, w_dur, _, w_at = mine.get("wait", (start, 0, None, at + 1))
        s_start, s_dur, _, s_at = mine.get("service", (start + wait, 0, None, at + 1))
        assert (w_start, w_dur, s_start, s_dur) == (start, wait, start + wait, service)
        assert w_dur + s_dur == dur and s_start + s_dur == start + dur  # nested to the nanosecond
        assert at < min(w_at, s_at)  # the enclosing slice first: viewers break ties by file order
        for name, (_, ns, part_args, _) in mine.items():
            assert part_args == {"source": src, "frame": frm, f"{name}_ms": ns / 1e6}
        seen[stage, "wait"] += wait > 0
        seen[stage, "service"] += service > 0
    assert seen["mux", "wait"] >= 10  # frames waited for their batch
    assert all(seen[stage, "service"] >= 30 for stage in ("mux", "slow", "tiler", "convert", "osd"))


def test_utilization_counters_of_a_real_run_are_the_models_busy_time_per_bucket(real_trace):
    header, events = real_trace.header, real_trace.events
    doc = _doc((header, events, None))
    t0 = doc["otherData"]["t0_ns"]
    counters = [e for e in doc["traceEvents"] if e["ph"] == "C" and e["name"] == "utilization"]
    stages = ("mux", "slow", "tiler", "convert", "osd")
    assert counters and all(set(e["args"]) == set(stages) and e["pid"] == 1 for e in counters)
    times = [t0 + _ns(e["ts"]) for e in counters]
    fd = frame_delays(frame_table(header, events))
    summary = delay_summary(series(fd))
    complete = fd.chains.complete
    assert times[0] == fd.table.origin[complete].min() and times[-1] == fd.chains.end[complete].max()
    assert all(b - a == 100_000_000 for a, b in zip(times[:-2], times[1:-1]))  # 100 ms buckets, the last cut
    lengths = np.diff(times)
    span = times[-1] - times[0]
    for stage in stages:
        values = np.array([e["args"][stage] for e in counters])
        assert values[-1] == 0.0 and ((values >= 0) & (values <= 1 + 1e-9)).all(), stage
        # Busy time over the buckets adds up to the utilization the statistics report.
        assert (values[:-1] * lengths).sum() / span == pytest.approx(summary["stages"][stage]["utilization"], rel=1e-9)
    assert max(e["args"]["slow"] for e in counters) > 0.05  # 5 ms of sleep per 33 ms batch


def test_fill_level_counters_of_a_real_run_count_the_frames_inside_each_stage(real_trace):
    header, events = real_trace.header, real_trace.events
    doc = _doc((header, events, None))
    t0 = doc["otherData"]["t0_ns"]
    raw = _raw(events)
    levels = defaultdict(list)
    for e in doc["traceEvents"]:
        if e["ph"] == "C" and e["name"] == "frames in":
            [(stage, n)] = e["args"].items()
            levels[stage].append((t0 + _ns(e["ts"]), n))
    assert set(levels) == {"mux", "slow", "tiler", "convert", "osd"}
    for stage, points in levels.items():
        s = header.stages.index(stage)
        spans = [(raw[src, frm, s, ENTER], raw[src, frm, s, EXIT]) for (src, frm, st, pt) in raw
                 if st == s and pt == ENTER and (src, frm, s, EXIT) in raw]
        # A point for every instant a frame entered or left, with the frames inside from then on.
        assert [t for t, _ in points] == sorted({t for span in spans for t in span})
        for t, n in points:
            assert n == sum(enter <= t < exit_ for enter, exit_ in spans), (stage, t)
    assert max(n for _, n in levels["mux"]) >= 2  # the mux holds a frame of each camera


def _as_format_1(trace, path):
    """The real trace as a format-1 dcuscope wrote it: origin, enter and exit only, 5 columns."""
    header = {**trace.header.to_dict(), "format": 1}
    keep = trace.events[trace.events["point"] <= EXIT]
    rows = np.stack([keep[c].astype(np.int64) for c in ("ts", "stage", "point", "source", "frame")], axis=1)
    lines = [{"dcuscope_trace": 1, "header": header}, {"events": rows.tolist()}, {"end": {"events": len(rows), "dropped": 0}}]
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))


def test_a_format_1_trace_exports_without_wait_service_or_utilization(tmp_path, real_trace):
    _as_format_1(real_trace, tmp_path / "v1.jsonl")
    rc, _, err = _cli("export", str(tmp_path / "v1.jsonl"), "-o", str(tmp_path / "v1.json"))
    assert (rc, err) == (0, "")
    doc = json.loads((tmp_path / "v1.json").read_text())
    slices = _by_phase(doc, "X")
    assert slices and all(e["name"].startswith("frame ") for e in slices)
    assert all({"delay_ms", "gap_ms"} <= set(e["args"]) and not {"service_ms", "wait_ms"} & set(e["args"])
               for e in slices)
    counters = {e["name"] for e in _by_phase(doc, "C")}
    assert counters == {"frames in"}
    rc, _, _ = _cli("export", str(tmp_path / "v1.jsonl"), "--format", "csv", "-o", str(tmp_path / "v1.csv"))
    rows = _read_csv((tmp_path / "v1.csv").read_text())
    assert rc == 0 and rows and any(r["delay_ms"] for r in rows)
    assert {r[c] for r in rows for c in ("service_ms", "wait_ms", "capture_ns", "glass_ms")} == {""}


def test_csv_of_a_real_run_has_service_and_wait_summing_to_the_delay(real_trace, tmp_path):
    write_trace(tmp_path / "t.trace", real_trace.header, real_trace.events)
    rc, _, _ = _cli("export", str(tmp_path / "t.trace"), "--format", "csv", "-o", str(tmp_path / "t.csv"))
    rows = _read_csv((tmp_path / "t.csv").read_text())
    assert rc == 0 and {"service_ms", "wait_ms"} <= set(rows[0])
    timed = [r for r in rows if r["delay_ms"]]
    assert timed and all(r["service_ms"] and r["wait_ms"] for r in timed)
    for r in timed:  # 6 decimals of ms: whole ns, so the sum is exact
        assert round(float(r["service_ms"]) * 1e6) + round(float(r["wait_ms"]) * 1e6) == round(float(r["delay_ms"]) * 1e6)
    assert any(float(r["wait_ms"]) > 0 for r in timed if r["stage"] == "mux")


def _with_capture(run, lead_ns, source=0):
    """A synthetic run whose ``source`` frames carry a capture time ``lead_ns`` before their origin."""
    header, events, truth = run
    origins = events[(events["point"] == ORIGIN) & (events["source"] == source)]
    captures = origins.copy()
    captures["point"], captures["ts"] = CAPTURE, origins["ts"] - lead_ns
    return header, np.concatenate([events, captures]), truth


def test_capture_slices_and_glass_to_glass_where_frames_have_a_capture_time(tmp_path):
    header, events, truth = _with_capture(pipeline_run(5, n_sources=2, jitter_ns=2_000_000, seed=7), 250_000_000)
    doc = _doc((header, events, truth))
    t0 = doc["otherData"]["t0_ns"]
    names = _thread_names(doc)
    captures = [e for e in _by_phase(doc, "X") if e["cat"] == "capture"]
    # 250 ms from capture to origin at 10 fps: frames overlap, so they take lanes.
    assert {names[1, e["tid"]] for e in captures} == {"capture · src 0", "capture · src 0 #2", "capture · src 0 #3"}
    _assert_slices_nest_per_thread(doc)
    sink = len(header.stages) - 1
    for e in captures:
        row = int(np.flatnonzero((truth.source == 0) & (truth.frame == e["args"]["frame"]))[0])
        assert e["name"] == "capture" and e["args"]["source"] == 0
        assert (t0 + _ns(e["ts"]), _ns(e["dur"])) == (truth.origin[row] - 250_000_000, 250_000_000)
        assert e["args"]["glass_ms"] == (truth.enter[row, sink - len(header.sources)] - truth.origin[row] + 250_000_000) / 1e6
    assert len(captures) == 5
    out = io.StringIO()
    write_csv(out, [(header, events)])
    rows = _read_csv(out.getvalue())
    for r in rows:
        row = int(np.flatnonzero((truth.source == int(r["source"])) & (truth.frame == int(r["frame"])))[0])
        if r["source"] == "0":
            glass = truth.enter[row, -1] - truth.origin[row] + 250_000_000
            assert (int(r["capture_ns"]), r["glass_ms"]) == (truth.origin[row] - 250_000_000, f"{glass / 1e6:.6f}")
        else:
            assert r["capture_ns"] == r["glass_ms"] == ""


def test_a_capture_time_after_the_origin_gives_an_instant_wide_slice_never_a_negative_one():
    header, events, truth = _with_capture(pipeline_run(3, n_sources=2, seed=8), -3_000_000, source=1)
    doc = _doc((header, events, truth))
    t0 = doc["otherData"]["t0_ns"]
    late = [e for e in _by_phase(doc, "X") if e["cat"] == "capture" and e["args"]["source"] == 1]
    assert len(late) == 3 and all(e["dur"] == 0 for e in late)
    assert sorted(t0 + _ns(e["ts"]) for e in late) == sorted((truth.origin[truth.source == 1] + 3_000_000).tolist())


def test_export_cli_takes_the_utilization_bucket_width(tmp_path, real_trace):
    write_trace(tmp_path / "t.trace", real_trace.header, real_trace.events)
    rc, _, err = _cli("export", str(tmp_path / "t.trace"), "--bucket-ms", "50", "-o", str(tmp_path / "t.json"))
    assert (rc, err) == (0, "")
    doc = json.loads((tmp_path / "t.json").read_text())
    times = [_ns(e["ts"]) for e in _by_phase(doc, "C") if e["name"] == "utilization"]
    assert len(times) >= 4 and all(b - a == 50_000_000 for a, b in zip(times[:-2], times[1:-1]))
    for bad in ("0", "-5", "nan"):
        rc, out, err = _cli("export", str(tmp_path / "t.trace"), "--bucket-ms", bad, "-o", str(tmp_path / "x.json"))
        assert (rc, out) == (2, "") and err.count("\n") == 1 and "--bucket-ms must be a positive" in err, err
