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

from probes.export import CSV_COLUMNS, assign_lanes, perfetto_document, write_csv
from probes.tracefile import write_trace
from tests.probes.synth import run_commands as _cli
from tests.probes.synth import STAGES, pipeline_run

EPS_US = 1e-6


def _doc(*runs):
    doc = perfetto_document([(h, e) for h, e, _ in runs])
    # Valid JSON as the viewers read it: no NaN or Infinity, everything serialisable.
    return json.loads(json.dumps(doc, allow_nan=False))


def _by_phase(doc, ph):
    return [e for e in doc["traceEvents"] if e["ph"] == ph]


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
            assert {"source", "frame", "delay_ms"} <= set(e["args"])
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
    [s] = [e for e in _by_phase(doc, "X")
           if e["pid"] == 1 and names[(1, e["tid"])] == "infer · src 1" and e["args"]["frame"] == 5]
    assert s["name"] == "frame 5" and s["args"]["source"] == 1
    assert s["ts"] == pytest.approx((truth.enter[row, infer] - t0) / 1e3, abs=1e-3)
    assert s["dur"] == pytest.approx((truth.exit[row, infer] - truth.enter[row, infer]) / 1e3, abs=1e-9)
    assert s["args"]["delay_ms"] == pytest.approx(s["dur"] / 1e3)
    assert s["args"]["gap_ms"] == pytest.approx((truth.enter[row, infer] - truth.exit[row, infer - 1]) / 1e6)
    # One slice per frame per stage with an exit; origins and sink arrivals are instants.
    assert len(_by_phase(doc, "X")) == (24 + 21) * len(STAGES)
    assert len(_by_phase(doc, "i")) == (24 + 21) * 2


def _assert_slices_nest_per_thread(doc):
    per_thread = defaultdict(list)
    for e in _by_phase(doc, "X"):
        per_thread[(e["pid"], e["tid"])].append((e["ts"], e["ts"] + e["dur"]))
    for spans in per_thread.values():
        spans.sort()
        for (_, end), (start, _) in zip(spans, spans[1:]):
            assert start >= end - EPS_US
    return per_thread


def test_batched_frames_sit_on_per_source_tracks_that_never_overlap(two_nodes):
    doc = _doc(*two_nodes)
    _assert_slices_nest_per_thread(doc)
    names = _thread_names(doc)
    # A batch: frame i of both sources leaves the mux at one instant, on two different tracks.
    mux_exits = defaultdict(set)
    for e in _by_phase(doc, "X"):
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
    for e in _by_phase(doc, "X"):
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
    root = Path(__file__).resolve().parents[2]
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
    root = Path(__file__).resolve().parents[2]
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
