"""The delay model on a graph (the trace header's links): branches through a tee, a source whose
stage was numbered after those downstream of it (the GStreamer tracer numbers stages as they
first carry a frame)."""

from __future__ import annotations

import numpy as np

from dcuscope.model.delays import frame_delays
from dcuscope.model.frametable import frame_table
from dcuscope.protocol.events import ENTER, EVENT_DTYPE, EXIT, ORIGIN, TraceHeader

MS = 1_000_000


def events(rows: list[tuple[int, int, int, int, int]]) -> np.ndarray:
    """(ts_ms, stage, point, source, frame) -> EVENT_DTYPE."""
    out = np.zeros(len(rows), EVENT_DTYPE)
    for i, (ts, stage, point, source, frame) in enumerate(rows):
        out[i] = (ts * MS, frame, source, stage, point, 0)
    return out


def test_a_source_numbered_after_its_downstream_stages_is_complete():
    # stages: a (source 0), mix, sink, b (source 1, found last); a -> mix -> sink <- mix <- b
    header = TraceHeader(node="N", clock="realtime", stages=["a", "mix", "sink", "b"],
                         links=[[0, 1], [1, 2], [3, 1]])
    ev = events([(0, 0, ORIGIN, 0, 0), (1, 1, ENTER, 0, 0), (3, 1, EXIT, 0, 0), (4, 2, ENTER, 0, 0),
                 (0, 3, ORIGIN, 1, 0), (2, 1, ENTER, 1, 0), (3, 1, EXIT, 1, 0), (5, 2, ENTER, 1, 0)])
    fd = frame_delays(frame_table(header, ev))
    assert fd.chains.complete.tolist() == [True, True]
    assert (fd.delay / MS).tolist() == [4.0, 5.0]
    gap = fd.per_stage["gap"] / MS
    assert gap[1, 1] == 2.0  # b -> mix, from b's origin: the upstream stage by the links, not by number
    assert fd.chains.prev[1, 1] == 3


def test_each_branch_of_a_tee_must_reach_its_end():
    # src -> t -> qa -> sinka ; t -> qb -> sinkb
    header = TraceHeader(node="N", clock="realtime", stages=["src", "t", "qa", "sinka", "qb", "sinkb"],
                         links=[[0, 1], [1, 2], [2, 3], [1, 4], [4, 5]])
    both = [(0, 0, ORIGIN, 0, 0), (1, 1, ENTER, 0, 0), (1, 1, EXIT, 0, 0), (2, 2, ENTER, 0, 0), (3, 2, EXIT, 0, 0),
            (4, 3, ENTER, 0, 0), (2, 4, ENTER, 0, 0), (8, 4, EXIT, 0, 0), (9, 5, ENTER, 0, 0)]
    stuck = [(10, 0, ORIGIN, 0, 1), (11, 1, ENTER, 0, 1), (11, 1, EXIT, 0, 1), (12, 2, ENTER, 0, 1),
             (13, 2, EXIT, 0, 1), (14, 3, ENTER, 0, 1), (12, 4, ENTER, 0, 1)]  # never left qb
    fd = frame_delays(frame_table(header, events(both + stuck)))
    assert fd.chains.complete.tolist() == [True, False]
    assert fd.delay[0] / MS == 9.0  # the frame's delay ends where its last branch ends
    gap = fd.per_stage["gap"] / MS
    assert gap[0, 4] == 1.0 and fd.chains.prev[0, 4] == 1  # qb's gap from the tee, not from sinka
