"""Probes on real pipelines run through the CLI: accuracy, lineage, drops, exports."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from dcuscope.model.delays import chains
from dcuscope.model.frametable import MISSING, frame_table
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.protocol.events import ENTER, EXIT, ORIGIN
from tests.conftest import REPO, run_cli

MODEL = REPO / "assets" / "models" / "ssdlite_mobilenetv2_person.onnx"
FIVE = ("mux", "infer", "tiler", "convert", "osd")


def probed_run(tmp_path: Path, yaml: str, frames: int, *extra: str, env: dict | None = None, output: list | None = None):
    """The trace of ``dcuscope run --num-frames FRAMES``; ``output`` gets the run's stderr."""
    config = tmp_path / "p.yaml"
    config.write_text(yaml)
    trace = tmp_path / "t.jsonl"
    result = run_cli("run", config, "--probes", "--trace", trace, "--num-frames", frames, *extra, cwd=tmp_path, env=env)
    assert result.returncode == 0, result.stderr
    if output is not None:
        output.append(result.stderr)
    return read_trace(trace)


def quad_yaml(slow_us: int = 0, drop: float = 0.0) -> str:
    sources = "\n".join(f"  - {{test: {p}, width: 320, height: 240, rate: 30}}" for p in ("smpte", "ball", "snow", "pinwheel"))
    inserted = ""
    if slow_us:
        inserted += f"  - {{factory: identity, name: slow, properties: {{sleep-time: {slow_us}}}}}\n"
    if drop:
        inserted += f"  - {{factory: identity, name: lossy, properties: {{drop-probability: {drop}}}}}\n"
    return f"""\
sources:
{sources}
stages:
  - mux: {{batch-size: 4, width: 320, height: 240}}
  - infer: {{model: {MODEL}}}
{inserted}  - tiler: {{rows: 2, columns: 2, width: 640, height: 480}}
  - convert: {{format: RGBA}}
  - osd: {{}}
"""


def test_lineage_every_frame_has_one_origin_and_one_enter_exit_per_stage(tmp_path):
    said: list[str] = []
    trace = probed_run(tmp_path, quad_yaml(), 30, output=said)
    header, events = trace.header, trace.events
    assert header.stages == ["src0", "src1", "src2", "src3", *FIVE, "sink"]
    assert [header.kinds[s] for s in header.stages[:-1]] == ["framestamp"] * 4 + list(FIVE)
    assert trace.complete and trace.dropped == 0
    sink = header.stages.index("sink")
    reached = {(int(e["source"]), int(e["frame"])) for e in events[(events["stage"] == sink) & (events["point"] == ENTER)]}
    assert len(reached) >= 4 * 25 and {s for s, _ in reached} == {0, 1, 2, 3}
    keys = np.stack([events["source"], events["frame"], events["stage"], events["point"]], axis=1)
    uniq, counts = np.unique(keys, axis=0, return_counts=True)
    seen = {tuple(k): c for k, c in zip(uniq.tolist(), counts.tolist())}
    for source, frame in reached:
        assert seen.get((source, frame, source, ORIGIN)) == 1
        for stage in FIVE:
            s = header.stages.index(stage)
            assert seen.get((source, frame, s, ENTER)) == 1, (source, frame, stage)
            assert seen.get((source, frame, s, EXIT)) == 1, (source, frame, stage)
        assert seen.get((source, frame, sink, ENTER)) == 1
    # The run's count says what it counts: 30 collages at the sink, the camera frames in them, and those
    # past the limit (not written), which add up to the frames the trace saw reach the sink.
    counts = re.search(r"^30 frames in [\d.]+ s \([\d.]+ fps\), (\d+) camera frames in them"
                       r"(?:; (\d+) more \((\d+) camera frames\) had passed every stage)?", said[0], re.M)
    assert counts, said[0]
    assert int(counts[1]) + int(counts[3] or 0) == len(reached), said[0]


def test_frame_delay_is_the_sum_of_its_stage_delays_and_gaps(tmp_path):
    trace = probed_run(tmp_path, quad_yaml(), 20)
    table = frame_table(trace.header, trace.events)
    ch = chains(table)
    assert ch.complete.sum() >= 60
    rows = np.flatnonzero(ch.complete)
    for r in rows:
        stages_sum = sum(int(table.exit[r, s] - table.enter[r, s]) for s in range(len(table.stages))
                         if table.enter[r, s] != MISSING and table.exit[r, s] != MISSING)
        gaps_sum = sum(int(ch.t_in[r, b] - ch.t_out[r, ch.prev[r, b]]) for b in range(len(table.stages))
                       if ch.t_in[r, b] != MISSING and ch.prev[r, b] >= 0)
        assert int(ch.end[r] - table.origin[r]) == stages_sum + gaps_sum
        assert stages_sum > 0


def latency_tracer_env(log: Path) -> dict:
    """GStreamer's own ``latency`` tracer, per element, logging to ``log``: C hooks on the same pad
    pushes, an independent measure of each buffer's time inside an element, in the same run."""
    return {"GST_TRACERS": "latency(flags=element)", "GST_DEBUG": "GST_TRACER:7", "GST_DEBUG_FILE": str(log),
            "GST_DEBUG_NO_COLOR": "1"}


def element_latencies_ms(log: Path, element: str) -> np.ndarray:
    """The latency tracer's ``element-latency`` of ``element``, per buffer in order, in ms."""
    times = re.findall(rf"element-latency, element-id=\(string\)\S+, element=\(string\){element}, "
                       r"src=\(string\)\w+, time=\(g?u?int64\)(\d+)", log.read_text(errors="replace"))
    return np.array([int(t) for t in times]) / 1e6


@pytest.mark.alone  # p99 within 1.5 ms: between two instruments, the tail is the machine's scheduling jitter
def test_inserted_20ms_stage_is_measured_accurately(tmp_path):
    """An inserted identity that sleeps 20 ms per batch, through the CLI and ``dcuscope stats``:
    per buffer, its delay is within 0.5 ms on average, p99 within 1.5 ms, of what GStreamer's own
    latency tracer measures for it in the same run. Not of the 20 ms asked for: on a loaded
    machine a sleep that wakes up late really makes the stage slower, and both see it. Being
    preempted between the tracer's hook and the tracepoint (the tracer writes its log line there)
    is rare but real on a loaded host, so up to 3 runs, one must meet it."""
    runs = []
    for attempt in range(3):
        log = tmp_path / f"gst-latency-{attempt}.log"
        trace = probed_run(tmp_path, quad_yaml(slow_us=20000), 25, env=latency_tracer_env(log))
        ev, slow_index = trace.events, trace.header.stages.index("slow")
        enter, exit_ = (ev[(ev["stage"] == slow_index) & (ev["point"] == point)] for point in (ENTER, EXIT))
        # A batch of 4 frames is one buffer: its frames share their enter and exit times.
        exits = {(s, f): t for s, f, t in zip(exit_["source"].tolist(), exit_["frame"].tolist(), exit_["ts"].tolist())}
        per_buffer = sorted({(t, exits[(s, f)])
                             for s, f, t in zip(enter["source"].tolist(), enter["frame"].tolist(), enter["ts"].tolist())})
        ours_ms = np.array([out - into for into, out in per_buffer]) / 1e6
        theirs_ms = element_latencies_ms(log, "slow")
        assert len(ours_ms) == len(theirs_ms) >= 25, (len(ours_ms), len(theirs_ms))
        assert ours_ms.min() >= 20.0  # the sleep lies between the two tracepoints
        # dcuscope stats says the same, frame by frame (4 per buffer).
        result = run_cli("stats", tmp_path / "t.jsonl", "--json", cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        slow = json.loads(result.stdout)["nodes"]["DCU-1"]["stages"]["slow"]
        assert slow["count"] == len(enter) >= 100
        diff_ms = np.abs(ours_ms - theirs_ms)
        runs.append((round(float(diff_ms.mean()), 3), round(float(np.percentile(diff_ms, 99)), 3),
                     round(slow["mean_ms"] - float(theirs_ms.mean()), 3)))
        if diff_ms.mean() <= 0.5 and np.percentile(diff_ms, 99) < 1.5 and abs(runs[-1][2]) <= 0.5:
            return
    pytest.fail(f"(mean, p99 of the difference per buffer, stats' mean minus the tracer's) ms, 3 runs: {runs}")


def test_frames_dropped_by_the_pipeline_are_counted_never_zero_delays(tmp_path):
    trace = probed_run(tmp_path, quad_yaml(drop=0.3), 15)
    result = run_cli("stats", tmp_path / "t.jsonl", "--json", cwd=tmp_path)
    node = json.loads(result.stdout)["nodes"]["DCU-1"]
    assert node["frames"]["incomplete"] >= 4  # ~30 % of the collages (4 frames each) were lost
    assert node["frames"]["complete"] == node["frame"]["count"] >= 40
    assert node["stages"]["tiler"]["count"] == node["frame"]["count"]  # dropped frames are not in the stats
    table = frame_table(trace.header, trace.events)
    ch = chains(table)
    assert (ch.end[ch.complete] - table.origin[ch.complete] > 0).all()


def test_perfetto_and_csv_exports_of_a_real_trace(tmp_path):
    probed_run(tmp_path, quad_yaml(), 10)
    out = tmp_path / "t.json"
    assert run_cli("export", tmp_path / "t.jsonl", "--format", "perfetto", "-o", out, cwd=tmp_path).returncode == 0
    doc = json.loads(out.read_text())
    events = doc["traceEvents"]
    names = {e["args"]["name"] for e in events if e.get("ph") == "M" and e["name"] == "process_name"}
    assert names == {"DCU-1"}
    slices = [e for e in events if e["ph"] == "X"]
    assert {e["name"] for e in slices} and all(e["dur"] >= 0 for e in slices)
    starts = {e["id"] for e in events if e["ph"] == "s"}
    ends = {e["id"] for e in events if e["ph"] == "f"}
    assert starts and starts == ends
    # Each stage slice splits into its wait and service, to the nanosecond as Perfetto reads
    # them (int(µs * 1000)); the mux makes frames wait for their batch.
    parts = {}
    for e in slices:
        if e["name"] in ("wait", "service"):
            parts[e["tid"], e["args"]["source"], e["args"]["frame"], e["cat"], e["name"]] = int(e["dur"] * 1000)
    stage_slices = [e for e in slices if e["name"].startswith("frame ")]
    for e in stage_slices:
        key = (e["tid"], e["args"]["source"], e["args"]["frame"], e["cat"])
        wait, service = parts.get((*key, "wait"), 0), parts.get((*key, "service"), 0)
        assert (wait, service) == (round(e["args"]["wait_ms"] * 1e6), round(e["args"]["service_ms"] * 1e6))
        assert wait + service == int(e["dur"] * 1000)
    assert sum(1 for k in parts if k[3] == "mux" and k[4] == "wait") >= 20
    assert {k[3] for k in parts if k[4] == "service"} == set(FIVE)
    counters = {e["name"] for e in events if e["ph"] == "C"}
    assert counters == {"utilization", "frames in"}
    csv = tmp_path / "t.csv"
    assert run_cli("export", tmp_path / "t.jsonl", "--format", "csv", "-o", csv, cwd=tmp_path).returncode == 0
    header, *rows = csv.read_text().splitlines()
    assert header.startswith("node,source,frame,stage") and len(rows) >= 40 * 5
    assert "service_ms,wait_ms" in header and "capture_ns,glass_ms" in header
