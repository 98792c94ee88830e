"""Joining nodes' crossings into hops and journeys (model.journeys), on events made here: each case
is a situation the tracer records (tests/test_journeys_net.py and tests/probes/test_shm_journey.py
run real pipelines)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dcuscope.model.journeys import JOIN_WINDOW_NS, crossings, join, journeys_document
from dcuscope.protocol.events import (ENTER, EVENT_DTYPE, KEY, LINK, ORIGIN, RTP_IN, RTP_OUT, SHM_IN, SHM_OUT,
                                      TraceHeader)
from dcuscope.relay.clock.correction import Correction, Segment

T0 = 1_800_000_000_000_000_000
MS = 1_000_000


class Node:
    """One node's events, written as its tracer would."""

    def __init__(self, name: str, correction: Correction | None = None) -> None:
        self.rows: list[tuple] = []
        self.header = TraceHeader(node=name, clock="realtime", stages=["a", "b", "c"])
        self.correction = correction

    def frame(self, source: int, frame: int, start_ms: float, end_ms: float) -> Node:
        self.rows += [(T0 + round(start_ms * MS), frame, source, 0, ORIGIN, 0),
                      (T0 + round(end_ms * MS), frame, source, 2, ENTER, 0)]
        return self

    def link(self, kind: int, source: int, frame: int, at_ms: float, key: int, stage: int = 1) -> Node:
        ts = T0 + round(at_ms * MS)
        self.rows += [(ts, frame, source, stage, LINK, kind), (ts, key, source, stage, KEY, kind)]
        return self

    @property
    def events(self) -> np.ndarray:
        return np.array(self.rows, dtype=EVENT_DTYPE)


def trace(node: Node):
    return SimpleNamespace(header=node.header, events=node.events, correction=node.correction)


def test_a_frame_through_three_nodes_has_one_journey_made_of_its_five_parts():
    a = Node("A").frame(0, 7, 0, 1).link(RTP_OUT, 0, 7, 2.0, key=11)
    b = Node("B").link(RTP_IN, 0, 3, 5.0, key=11).frame(0, 3, 5.1, 5.8).link(SHM_OUT, 0, 3, 6.0, key=22)
    c = Node("C").link(SHM_IN, 1, 40, 9.0, key=22).frame(1, 40, 9.0, 9.5)
    joined = join([trace(a), trace(b), trace(c)])
    assert set(joined.hops) == {"net A → B", "shm B → C"}
    assert joined.hops["net A → B"].delays_ns == [3 * MS] and joined.hops["shm B → C"].delays_ns == [3 * MS]
    (journey,) = joined.journeys  # B's frame went on: only C's frame ends a chain
    assert journey.nodes == ["A", "B", "C"]
    assert journey.parts == [("A", 2 * MS), ("net A → B", 3 * MS), ("B", 1 * MS), ("shm B → C", 3 * MS),
                             ("C", MS // 2)]
    assert journey.total_ns == sum(ns for _, ns in journey.parts) == round(9.5 * MS)
    assert journey.errors_ns == {1: None, 3: None}  # trace files: no clock aligned them


def test_a_key_two_sent_frames_share_joins_neither_and_is_counted_ambiguous():
    # The same bytes twice over shm (a still picture): which one arrived is unknowable.
    a = Node("A").frame(0, 0, 0, 1).frame(0, 1, 40, 41).link(SHM_OUT, 0, 0, 1, key=5).link(SHM_OUT, 0, 1, 41, key=5)
    b = Node("B").link(SHM_IN, 0, 0, 41.2, key=5).frame(0, 0, 41.2, 42)
    joined = join([trace(a), trace(b)])
    assert joined.ambiguous == {"B": 1} and not joined.hops and not joined.journeys


def test_a_frame_no_traced_node_sent_is_untraced():
    b = Node("B").link(RTP_IN, 0, 0, 10, key=99).frame(0, 0, 10, 11)
    joined = join([trace(Node("A").frame(0, 0, 0, 1)), trace(b)])
    assert joined.untraced == {"B": 1} and not joined.hops


def test_a_key_seen_again_beyond_the_window_is_another_frame():
    # An RTP timestamp wraps after ~13 h: the key's earlier use is not a candidate.
    far = JOIN_WINDOW_NS / MS + 1000
    a = Node("A").frame(0, 0, -far - 1, -far).link(RTP_OUT, 0, 0, -far, key=8).frame(0, 1, 0, 1).link(RTP_OUT, 0, 1, 1, key=8)
    b = Node("B").link(RTP_IN, 0, 0, 4, key=8).frame(0, 0, 4, 5)
    joined = join([trace(a), trace(b)])
    assert joined.hops["net A → B"].delays_ns == [3 * MS] and not joined.ambiguous


def test_frames_sent_between_two_that_arrived_and_never_arriving_are_lost_on_the_hop():
    a = Node("A")
    for f in range(6):
        a.frame(0, f, 40 * f, 40 * f + 1).link(RTP_OUT, 0, f, 40 * f + 1, key=100 + f)
    b = Node("B")
    for g, f in enumerate((0, 1, 3, 4)):  # 2 lost in between; 5 after the last that came: not counted
        b.link(RTP_IN, 0, g, 40 * f + 21, key=100 + f).frame(0, g, 40 * f + 21, 40 * f + 22)
    hop = join([trace(a), trace(b)]).hops["net A → B"]
    assert hop.lost == 1 and len(hop.delays_ns) == 4


def test_a_link_cut_from_its_key_is_left_out():
    node = Node("A").link(RTP_OUT, 0, 0, 1, key=3)
    events = node.events[:-1]  # the trace ended between the two
    assert len(crossings(events)) == 0
    both = np.concatenate([node.events, node.events[:1]])
    assert crossings(both)["key"].tolist() == [3]


def test_a_hops_clock_error_adds_both_nodes_bounds():
    def corrected(bound_ns: int) -> Correction:
        return Correction("estimate", "test", (Segment(from_ns=0, ref_ns=0, offset_ns=0, uncertainty_ns=bound_ns),))

    a = Node("A", corrected(40_000)).frame(0, 0, 0, 1).link(RTP_OUT, 0, 0, 1, key=1)
    b = Node("B", corrected(25_000)).link(RTP_IN, 0, 0, 3, key=1).frame(0, 0, 3, 4)
    joined = join([trace(a), trace(b)])
    assert joined.hops["net A → B"].clock_error_ns == 65_000 and joined.journeys[0].errors_ns == {1: 65_000}
    doc = journeys_document(join([trace(Node("A").frame(0, 0, 0, 1).link(RTP_OUT, 0, 0, 1, key=1)),
                                  trace(Node("B").link(RTP_IN, 0, 0, 3, key=1).frame(0, 0, 3, 4))]))
    assert doc["hops"]["net A → B"]["clock_error_ms"] is None  # trace files: nothing aligned them


@pytest.mark.parametrize("names", [None, ["DCU-1", "DCU-1_2"]])
def test_the_document_gives_each_path_its_parts_whose_means_add_up(names):
    a = Node("DCU-1")
    b = Node("DCU-1")  # two runs of one name: told apart by the names the statistics give
    for f in range(3):
        a.frame(0, f, 40 * f, 40 * f + 2).link(RTP_OUT, 0, f, 40 * f + 2, key=f + 1)
        b.link(RTP_IN, 0, f, 40 * f + 7, key=f + 1).frame(0, f, 40 * f + 7, 40 * f + 9 + f)
    doc = journeys_document(join([trace(a), trace(b)], names))
    (path,) = doc["paths"].values()
    assert path["count"] == 3
    assert sum(p["mean_ms"] for p in path["parts"].values()) == pytest.approx(path["mean_ms"])
    if names:
        assert list(doc["hops"]) == ["net DCU-1 → DCU-1_2"]
