"""The OTLP exporter's parts in-process, on finalised batches of synthetic frames (probes.ship.simnode):
which frames the sampler chooses, what a full queue keeps, the spans one frame becomes, and the
exporter's thread (against a real receiver on loopback): its share of a core, its clean stop."""

from __future__ import annotations

import asyncio
import time
from collections import Counter

import numpy as np
import pytest

from dcuscope.model.delays import frame_delays, series
from dcuscope.model.frametable import frame_table
from dcuscope.probes.ship.simnode import STAGES, header_for, synth_events
from dcuscope.relay.export.otlp import MAX_BUSY, OtlpExporter
from dcuscope.relay.export.otlpconfig import OtlpConfig
from dcuscope.relay.export.otlpqueue import FrameQueue, OtlpCounters
from dcuscope.relay.export.otlpsample import Sampler
from dcuscope.relay.export.otlpspans import node_resource, spans_of, trace_id
from dcuscope.relay.live.framelimits import FrameLimits
from dcuscope.relay.live.run import LiveRun
from dcuscope.relay.live.seqset import SeqSet
from dcuscope.relay.live.state import RelayState, RunState
from dcuscope.relay.store.writer import Storage
from tests.relay.helpers import wait_for
from tests.relay.otlpreceiver import OtlpReceiver

HEADER = header_for("DCU-1", 2)


def batches(n: int = 2, frames: int = 40):
    """``n`` finalised batches of ``frames`` frames per source, with 1 in 10 frames lost on the way."""
    out = []
    for k in range(n):
        events = synth_events(frames, 2, 25.0, 10**18, drop_rate=0.1, seed=3, first_frame=frames * k)
        fd = frame_delays(frame_table(HEADER, events))
        out.append((fd, series(fd)))
    return out


@pytest.fixture
def run(tmp_path):
    def make(limit_ns: int | None, every: int, capacity: int):
        state = RelayState(Storage(tmp_path / "r.db"), "estimate", frame_limits=FrameLimits(limit_ns))
        rs = RunState(run="run-1", node="DCU-1", session=1, header=HEADER, live=LiveRun(HEADER), seqs=SeqSet())
        state.runs[rs.run] = rs
        queue, counters = FrameQueue(capacity), OtlpCounters()
        return Sampler(state, every, queue, counters), rs, queue, counters
    return make


def taken(queue: FrameQueue) -> list[tuple[int, int, bool]]:
    queue.close()
    return [(s, f, o) for b in queue.take(10**6, 0)
            for s, f, o in zip(b.source.tolist(), b.frame.tolist(), b.over.tolist())]


def test_every_nth_complete_frame_across_batches_and_every_frame_over_the_limit(run):
    data = batches()
    delays = np.concatenate([fd.delay[fd.chains.complete] for fd, _ in data])
    limit = int(np.percentile(delays, 80))
    sampler, rs, queue, counters = run(limit, 7, 10_000)
    expected, position = set(), 0
    for fd, values in data:
        sampler(rs, fd, values)
        for row in np.flatnonzero(fd.chains.complete):
            over = fd.delay[row] > limit
            if over or position % 7 == 0:
                expected.add((int(fd.table.source[row]), int(fd.table.frame[row]), bool(over)))
            position += 1
    got = taken(queue)
    assert len(got) == len(set(got)) and set(got) == expected
    assert counters.frames == {"over_limit": sum(o for *_, o in got), "sampled": sum(not o for *_, o in got)}
    assert counters.frames["over_limit"] > 0 and counters.frames["sampled"] > 0 and counters.dropped["queue_full"] == 0


def test_a_full_queue_keeps_the_frames_over_the_limit_and_counts_the_rest(run):
    (fd, values), = batches(1)
    limit = int(np.percentile(fd.delay[fd.chains.complete], 90))
    n_over = int((fd.delay[fd.chains.complete] > limit).sum())
    sampler, rs, queue, counters = run(limit, 1, n_over + 2)
    sampler(rs, fd, values)
    sampler(rs, fd, values)  # no room left: all of it dropped, never waited for
    got = taken(queue)
    assert len(got) == n_over + 2 and sum(o for *_, o in got) == n_over
    assert counters.dropped["queue_full"] == 2 * int(fd.chains.complete.sum()) - len(got)


def test_only_over_limit_frames_with_every_0_and_none_without_a_limit(run):
    (fd, values), = batches(1)
    sampler, rs, queue, counters = run(None, 0, 100)
    sampler(rs, fd, values)
    assert queue.frames == 0 and counters.frames == {"sampled": 0, "over_limit": 0}


def test_a_frame_s_spans_nest_under_its_root_with_a_trace_id_of_its_identity(run):
    (fd, values), = batches(1)
    sampler, rs, queue, _ = run(None, 1, 1000)
    sampler(rs, fd, values)
    queue.close()
    (batch,) = queue.take(1000, 0)
    spans = spans_of(batch, node_resource("DCU-1"))
    by_trace = {}
    for s in spans:
        by_trace.setdefault(s.context.trace_id, []).append(s)
    assert len(by_trace) == len(batch) == int(fd.chains.complete.sum())
    assert len({s.context.span_id for s in spans}) == len(spans)
    for i, (source, frame) in enumerate(zip(batch.source.tolist(), batch.frame.tolist())):
        trace = by_trace[trace_id("run-1", source, frame)]
        root, = [s for s in trace if s.parent is None]
        names = Counter(s.name for s in trace)
        # simnode's probes give no ready times: stages without wait and service.
        assert names["frame"] == 1 and names["wait"] == names["service"] == 0
        assert [n for n in names if n.startswith("stage ")] == [f"stage {s}" for s in STAGES]
        assert f"gap src{source}->mux" in names and "gap osd->sink" in names and len(trace) == 1 + 5 + 6
        assert all(s.parent.span_id == root.context.span_id for s in trace if s is not root)
        assert root.end_time - root.start_time == fd.delay[fd.chains.complete][i]
        assert sum(s.end_time - s.start_time for s in trace if s is not root) == root.end_time - root.start_time


def test_the_exporter_rests_within_its_share_of_a_core_and_stops_cleanly(tmp_path):
    (fd, values), = batches(1, 2000)
    state = RelayState(Storage(tmp_path / "r.db"), "estimate")
    rs = RunState(run="run-1", node="DCU-1", session=1, header=HEADER, live=LiveRun(HEADER), seqs=SeqSet())
    state.runs[rs.run] = rs
    with OtlpReceiver() as receiver:
        exporter = OtlpExporter(OtlpConfig(receiver.url, every=1, queue=10_000, timeout_s=2), state)
        exporter.sampler(rs, fd, values)
        queued = exporter.queue.frames
        started = time.monotonic()
        exporter.start()
        time.sleep(2)
        c = exporter.counters
        cpu, most, wall, left = c.cpu_seconds, c.most_cpu_seconds, time.monotonic() - started, exporter.queue.frames
        asyncio.run(exporter.stop())
        assert not exporter._thread.is_alive()
        received = len(receiver.spans)
    # Work was left (the budget, not a lack of frames, held it back), and it took its share at most.
    assert left > 0 and c.exports > 1 and cpu <= MAX_BUSY * wall + most, (cpu, most, wall)
    # What stop() could not send in its time counts as dropped: every frame is accounted for.
    assert queued == int(fd.chains.complete.sum()) == c.frames_exported + c.dropped["export_failed"]
    assert received == c.spans_exported > 0


def test_a_backend_answering_500_costs_its_frames_counted_as_export_failed(tmp_path):
    (fd, values), = batches(1)
    state = RelayState(Storage(tmp_path / "r.db"), "estimate")
    rs = RunState(run="run-1", node="DCU-1", session=1, header=HEADER, live=LiveRun(HEADER), seqs=SeqSet())
    with OtlpReceiver("fail") as receiver:
        exporter = OtlpExporter(OtlpConfig(receiver.url, every=1, queue=1000, timeout_s=2), state)
        exporter.start()
        exporter.sampler(rs, fd, values)
        wait_for(lambda: exporter.counters.exports, 30, 0.05, "an export answered 500")
        asyncio.run(exporter.stop())
    c = exporter.counters
    assert c.exports >= 1 and c.frames_exported == c.spans_exported == 0 and receiver.spans == []
    assert c.dropped == {"queue_full": 0, "export_failed": int(fd.chains.complete.sum())}
