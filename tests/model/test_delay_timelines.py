"""Utilization over time and fill levels (model.delays) of a run whose every interval is known."""

import numpy as np
import pytest

from dcuscope.model.delays import busy_timeline, fill_levels, frame_delays, series
from dcuscope.model.frametable import frame_table
from dcuscope.protocol.events import ENTER, EVENT_DTYPE, EXIT, ORIGIN, READY, TraceHeader

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
# frame: (origin, enter, ready, exit) at stage "work", ms after T0; the sink sees it 1 ms later.
# 0: service 10..40; 1: waits 20..40, service 40..60; 2 and 3 leave in one buffer at 100 (a
# batch whose work, 70..100, counts once); 4 enters at 100, the instant 2 and 3 leave.
FRAMES = {0: (0, 10, 10, 40), 1: (5, 20, 40, 60), 2: (60, 65, 70, 100), 3: (62, 68, 70, 100), 4: (95, 100, 100, 105)}


def _run():
    header = TraceHeader(node="n", clock="realtime", stages=["src0", "work", "sink"])
    rows = []
    for f, (origin, enter, ready, exit_) in FRAMES.items():
        rows += [(origin, 0, ORIGIN, f), (enter, 1, ENTER, f), (ready, 1, READY, f), (exit_, 1, EXIT, f),
                 (exit_ + 1, 2, ENTER, f)]
    events = np.zeros(len(rows), EVENT_DTYPE)
    for i, (ms, stage, point, f) in enumerate(rows):
        events[i] = (T0 + ms * MS, f, 0, stage, point, {2: 2, 3: -2}.get(f, 1) if point == READY else 0)
    return frame_delays(frame_table(header, events))


def test_busy_timeline_splits_each_buffers_service_over_the_buckets_a_batch_once():
    fd = _run()
    timeline = busy_timeline(fd, 50 * MS)
    # Span: first origin (0) to last end (sink at 106); the last bucket is 6 ms long.
    assert ((timeline.edges - T0) // MS).tolist() == [0, 50, 100, 106]
    assert list(timeline.busy) == ["work"]
    # Bucket 0: 10..40 and 40..50; bucket 1: 50..60 and 70..100; bucket 2: 100..105.
    assert (timeline.busy["work"] / MS).tolist() == [40.0, 40.0, 5.0]
    assert timeline.utilization("work").tolist() == pytest.approx([0.8, 0.8, 5 / 6])
    assert timeline.busy["work"].sum() == series(fd).busy["work"]


def test_busy_timeline_of_buckets_wider_than_the_span_is_one_bucket():
    fd = _run()
    timeline = busy_timeline(fd, 10_000 * MS)
    assert ((timeline.edges - T0) // MS).tolist() == [0, 106]
    assert timeline.utilization("work").tolist() == pytest.approx([85 / 106])  # 30 + 20 + 30 (the batch once) + 5


def test_busy_timeline_refuses_an_empty_bucket():
    with pytest.raises(ValueError, match="bucket_ns"):
        busy_timeline(_run(), 0)


def test_fill_levels_count_frames_between_enter_and_exit_exits_first_at_one_instant():
    fd = _run()
    times, levels = fill_levels(fd, 1)
    assert ((times - T0) // MS).tolist() == [10, 20, 40, 60, 65, 68, 100, 105]
    assert levels.tolist() == [1, 2, 1, 0, 1, 2, 1, 0]
    for stage in (0, 2):  # the origin and the sink: no enter and exit pairs there
        times, levels = fill_levels(fd, stage)
        assert times.size == levels.size == 0
