"""Trace files: round trip, runs that died (no end line, cut last line), files that are not traces."""

import json

import numpy as np
import pytest

from dcuscope.probes.trace.errors import TraceError
from dcuscope.probes.trace.tracefile import TraceFileWriter, read_trace, write_trace
from dcuscope.protocol.events import EVENT_DTYPE, TraceHeader
from tests.probes.synth import pipeline_run


@pytest.fixture
def run():
    header, events, _ = pipeline_run(6, n_sources=2, jitter_ns=1_000_000, batched_mux=True)
    return header, events


def _write_batches(path, header, events, batches=3, dropped=None):
    writer = TraceFileWriter(path)
    writer.start(header)
    for chunk in np.array_split(events, batches):
        writer.write(chunk)
    if dropped is not None:
        writer.close(dropped)
    return writer


def test_round_trip_keeps_header_events_and_drops(tmp_path, run):
    header, events = run
    header.versions = {"gstreamer": "1.22.0"}
    path = tmp_path / "node.trace"
    _write_batches(path, header, events, batches=4, dropped=7)

    trace = read_trace(path)
    assert trace.header.to_dict() == header.to_dict()
    assert trace.events.dtype == EVENT_DTYPE
    assert np.array_equal(trace.events, events)  # same order, same values, every field
    assert (trace.dropped, trace.complete, trace.path) == (7, True, str(path))
    lines = path.read_text().splitlines()
    assert len(lines) == 1 + 4 + 1
    assert json.loads(lines[-1]) == {"end": {"events": len(events), "dropped": 7}}


def test_empty_batches_write_no_line_and_an_empty_trace_reads_back(tmp_path, run):
    header, _ = run
    path = tmp_path / "empty.trace"
    writer = TraceFileWriter(path)
    writer.start(header)
    writer.write(np.zeros(0, EVENT_DTYPE))
    writer.close(0)
    assert len(path.read_text().splitlines()) == 2
    trace = read_trace(path)
    assert len(trace.events) == 0 and trace.complete


def test_a_run_that_died_leaves_a_readable_trace_without_end_line(tmp_path, run):
    header, events = run
    path = tmp_path / "crashed.trace"
    writer = _write_batches(path, header, events, batches=3)  # never closed: each line is flushed
    trace = read_trace(path)
    assert np.array_equal(trace.events, events)
    assert (trace.complete, trace.dropped) == (False, 0)
    writer.close(0)


def test_truncated_last_line_is_dropped_not_fatal(tmp_path, run):
    header, events = run
    path = tmp_path / "cut.trace"
    _write_batches(path, header, events, batches=3)
    data = path.read_bytes()
    last_line_start = data.rstrip(b"\n").rfind(b"\n") + 1
    path.write_bytes(data[: last_line_start + 40])  # cut inside the last events line
    trace = read_trace(path)
    two_batches = sum(len(c) for c in np.array_split(events, 3)[:2])
    assert np.array_equal(trace.events, events[:two_batches])
    assert not trace.complete


def test_truncated_end_line_keeps_all_events(tmp_path, run):
    header, events = run
    path = tmp_path / "cut_end.trace"
    write_trace(path, header, events, dropped=3)
    path.write_bytes(path.read_bytes()[:-5])
    trace = read_trace(path)
    assert np.array_equal(trace.events, events)
    assert (trace.complete, trace.dropped) == (False, 0)


def test_last_line_without_newline_still_counts(tmp_path, run):
    header, events = run
    path = tmp_path / "nonl.trace"
    write_trace(path, header, events, dropped=2)
    path.write_bytes(path.read_bytes().rstrip(b"\n"))
    trace = read_trace(path)
    assert (len(trace.events), trace.complete, trace.dropped) == (len(events), True, 2)


HEADER_LINE = json.dumps({"dcuscope_trace": 1, "header": TraceHeader("n", "realtime", ["a", "b"]).to_dict()})


@pytest.mark.parametrize("content, message", [
    (b"", "empty file"),
    (b"node,source,frame\n1,2,3\n", "not a dcuscope trace"),
    (b"\x7fELF\x02\x01\x01\x00\xff\xfe\x00\x00garbage\n", "not a dcuscope trace"),
    (b'{"traceEvents": []}\n', "not a dcuscope trace"),
    (b'{"dcuscope_trace": 4, "header": {}}\n', "version 4 is not supported"),
    (b'{"dcuscope_trace": 1, "header": {"node": "n"}}\n', ":1: malformed trace header"),
    ((HEADER_LINE + '\n{"events": [[1, 0, 0, 0, 0]]}\n{"events": [[1, 0\n'
      '{"end": {"events": 1, "dropped": 0}}\n').encode(), ":3: not valid JSON"),
    ((HEADER_LINE + '\n{"events": [[1, 5, 1, 0, 0]]}\n').encode(), ":2: event stage index out of range"),
    ((HEADER_LINE + '\n{"events": [[1, 0, 7, 0, 0]]}\n').encode(), ":2: event point must be"),
    ((HEADER_LINE + '\n{"events": [[1, 0, 0]]}\n').encode(), ":2: events must be lists of 5 integers"),
    ((HEADER_LINE + '\n{"events": [[1, 0, 0, 0, 0]]}\n{"end": {"events": 4, "dropped": 0}}\n').encode(),
     ":3: end line counts 4 events but the file holds 1"),
    ((HEADER_LINE + '\n{"end": {"events": 0, "dropped": 0}}\n{"events": [[1, 0, 0, 0, 0]]}\n').encode(),
     ":3: data after the end line"),
    ((HEADER_LINE + '\n{"frames": []}\n').encode(), ":2: expected an 'events' or 'end' line"),
])
def test_files_that_are_not_traces_raise_trace_error_naming_file_and_line(tmp_path, content, message):
    path = tmp_path / "bad.trace"
    path.write_bytes(content)
    with pytest.raises(TraceError) as err:
        read_trace(path)
    text = str(err.value)
    assert text.startswith(str(path)) and message in text, text
    assert "\n" not in text


def test_missing_file_raises_trace_error(tmp_path):
    with pytest.raises(TraceError, match="nope.trace: cannot read trace file"):
        read_trace(tmp_path / "nope.trace")


def test_writer_to_an_unwritable_place_raises_trace_error(tmp_path, run):
    header, _ = run
    writer = TraceFileWriter(tmp_path / "no" / "such" / "dir.trace")
    with pytest.raises(TraceError, match="cannot write trace file"):
        writer.start(header)
