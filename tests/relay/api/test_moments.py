"""The moments matcher on synthetic frame tables: tolerance, one-to-one pairs, unmatched frames,
a node that joined later, corrected ends and their error bars; and the --clock-offset-ms aid
leaving capture times (the camera's clock) alone."""

from __future__ import annotations

import numpy as np
import pytest

from dcuscope.core.clocks import PretendClock
from dcuscope.model.delays import frame_delays
from dcuscope.model.frametable import frame_table
from dcuscope.probes.ship.shifted import Shifted
from dcuscope.protocol.events import CAPTURE, ENTER, EXIT, ORIGIN, TraceHeader
from dcuscope.relay.api.moments import MATCH_TOLERANCE_NS, MomentsError, Side, compare, match, pairs_of
from dcuscope.relay.clock.correction import Correction, Segment
from tests.probes.synth import T0, _events

URI = "uri:rtsp://127.0.0.1:8554/cam0"
PERIOD = 100_000_000


def node_run(node: str, captures: np.ndarray, delay_ns: int, offset_ns: int = 0, source: int = 0,
             with_capture: bool = True):
    """FrameDelays of one node: one frame per capture time, origin 30 ms after capture, ``delay_ns``
    from origin to the sink, every node timestamp (not the capture) shifted by ``offset_ns``;
    without ``with_capture``, the frames carry no capture time (a file's)."""
    n = len(captures)
    frame = np.arange(n, dtype=np.int64)
    src = np.full(n, source, np.int32)
    origin = captures + 30_000_000 + offset_ns
    header = TraceHeader(node=node, clock="realtime", stages=["src0", "work", "sink"],
                         sources={source: URI}, started_ns=T0)
    k = n if with_capture else 0
    events = np.concatenate([
        _events(captures[:k], src[:k], frame[:k], 0, CAPTURE), _events(origin, src, frame, 0, ORIGIN),
        _events(origin + 1000, src, frame, 1, ENTER), _events(origin + delay_ns - 1000, src, frame, 1, EXIT),
        _events(origin + delay_ns, src, frame, 2, ENTER)])
    return header, frame_delays(frame_table(header, events))


def estimate(offset_ns: int, uncertainty_ns: int) -> Correction:
    return Correction("estimate", "test", (Segment(T0, T0, offset_ns, uncertainty_ns=uncertainty_ns),))


def test_match_pairs_mutual_nearest_capture_times_within_the_tolerance_only():
    a = np.array([0, 100, 200, 300], np.int64) * 1_000_000 + T0
    b = np.array([a[0] + MATCH_TOLERANCE_NS, a[1] + MATCH_TOLERANCE_NS + 1, a[2] - 10, a[2] + 20, a[3]])
    ia, jb = match(a, np.sort(b))
    pairs = {(int(a[i]), int(np.sort(b)[j])) for i, j in zip(ia, jb)}
    # At the tolerance: matched; one ns beyond: not; two near one: only the nearest, one-to-one.
    assert pairs == {(a[0], a[0] + MATCH_TOLERANCE_NS), (a[2], a[2] - 10), (a[3], a[3])}
    assert match(a, np.zeros(0, np.int64))[0].size == 0 and match(a[:1], a[:1] + 5)[0].tolist() == [0]


def test_moments_of_a_node_that_joined_later_with_lost_and_stray_frames():
    captures = T0 + np.arange(50, dtype=np.int64) * PERIOD
    # b joined at the 10th frame (numbers its frames from 0), lost the 30th, and one of its capture
    # times is 2 ms off any of a's (out of the tolerance): it and a's frame stay unmatched.
    b_caps = np.delete(captures[10:], 20) + np.where(np.arange(39) == 5, 2_000_000, 300)
    _, fa = node_run("DCU-1", captures, 50_000_000)
    _, fb = node_run("DCU-2", b_caps, 70_000_000, offset_ns=37_000_000, source=3)
    sides = Side("DCU-1", {0: URI}, fa, estimate(0, 100_000)), Side("DCU-2", {3: URI}, fb,
                                                                     estimate(37_000_000, 200_000))
    out = compare(pairs_of(*sides), limit=10)
    s = out["summary"]
    assert s["matched"] == 38 and s["frames"] == {"DCU-1": 50, "DCU-2": 39}
    assert s["unmatched"] == {"DCU-1": 12, "DCU-2": 1}
    assert out["sources"] == [{"uri": URI, "a": 0, "b": 3}] and out["clock"] == {"DCU-1": "estimate", "DCU-2": "estimate"}
    # Corrected, b ends 20 ms after a (+0.3 µs of capture jitter) at every moment, ±0.3 ms.
    assert s["diff_ms"]["mean"] == pytest.approx(20.0003) and s["diff_ms"]["p95"] == pytest.approx(20.0003)
    assert s["first_share"] == {"DCU-1": 1.0, "DCU-2": 0.0} and s["significant"] is True
    assert s["error_ms"]["mean"] == pytest.approx(0.3) and s["capture_spread_us"] == pytest.approx(0.3)
    assert "DCU-1 finished first by 20.000 ms" in s["verdict"] and "significant" in s["verdict"]
    assert len(out["moments"]) == 10  # the newest 10, by capture time
    last = out["moments"][-1]
    assert last["capture"] == captures[-1] and last["a"]["frame"] == 49 and last["b"]["frame"] == 38
    assert last["a"]["end"] == captures[-1] + 80_000_000 and last["b"]["end"] == captures[-1] + 300 + 100_000_000
    assert last["first"] == "DCU-1" and last["error_ms"] == pytest.approx(0.3) and last["significant"]
    assert last["b"]["uncertainty_ns"] == 200_000 and last["source"] == URI


def test_a_difference_within_the_error_bar_is_not_significant_and_an_unknown_bound_is_not_judged():
    captures = T0 + np.arange(20, dtype=np.int64) * PERIOD
    _, fa = node_run("a", captures, 50_000_000)
    _, fb = node_run("b", captures, 50_100_000)
    out = compare(pairs_of(Side("a", {0: URI}, fa, estimate(0, 60_000)), Side("b", {0: URI}, fb, estimate(0, 60_000))))
    assert out["summary"]["diff_ms"]["mean"] == pytest.approx(0.1) and out["summary"]["significant"] is False
    assert out["summary"]["significant_moments"] == 0 and "not significant" in out["summary"]["verdict"]
    unknown = compare(pairs_of(Side("a", {0: URI}, fa, Correction("none")), Side("b", {0: URI}, fb, estimate(0, 1))))
    assert unknown["summary"]["significant"] is None and "not judged" in unknown["summary"]["verdict"]
    none = compare(pairs_of(Side("a", {0: URI}, fa, estimate(0, 1)),
                            Side("b", {0: URI}, node_run("b", captures + 7_000_000, 1)[1], estimate(0, 1))))
    assert none["summary"]["matched"] == 0 and none["moments"] == [] and none["summary"]["unmatched"]["a"] == 20
    assert none["summary"]["verdict"].startswith("none of a's 20 and b's 20 frames with a capture time match within 1 ms")


@pytest.mark.parametrize("uris, with_b, said", [
    (("uri:/media/vtest.avi",) * 2, False, "no capture times: moments match the frames of one camera on two DCUs by its "
                                           "capture time, which an RTSP camera's RTCP sender reports give"),
    ((URI, URI), False, "no capture time yet: an RTSP camera's frames carry one once its first RTCP sender report came"),
    ((URI, URI), True, "a has no frame with a capture time of the shared cameras yet (b has 5)"),
])
def test_when_no_moment_matched_the_verdict_says_what_is_missing(uris, with_b, said):
    captures = T0 + np.arange(5, dtype=np.int64) * PERIOD
    fa = node_run("a", captures, 1_000_000, with_capture=False)[1]
    fb = node_run("b", captures, 1_000_000, with_capture=with_b)[1]
    out = compare(pairs_of(Side("a", {0: uris[0]}, fa, estimate(0, 1)), Side("b", {0: uris[1]}, fb, estimate(0, 1))))
    assert out["summary"]["matched"] == 0 and out["summary"]["verdict"].startswith(said), out["summary"]["verdict"]
    if not uris[0].startswith("uri:rtsp"):
        assert out["summary"]["verdict"].endswith("/media/vtest.avi is not RTSP, and files and test sources have none")


def test_sources_are_matched_by_uri_or_named_explicitly_and_a_missing_one_is_said():
    captures = T0 + np.arange(5, dtype=np.int64) * PERIOD
    _, fd = node_run("a", captures, 1_000_000)
    a = Side("a", {0: URI, 1: "uri:rtsp://h/cam1"}, fd, estimate(0, 1))
    b = Side("b", {0: "uri:rtsp://other/x"}, fd, estimate(0, 1))
    with pytest.raises(MomentsError, match="share no source"):
        pairs_of(a, b)
    with pytest.raises(MomentsError, match="not a source of both"):
        pairs_of(a, b, uri="rtsp://h/cam1")
    with pytest.raises(MomentsError, match="node 'b' has no source 4"):
        pairs_of(a, b, ids=(0, 4))
    explicit = compare(pairs_of(a, b, ids=(0, 0)))
    assert explicit["summary"]["matched"] == 5 and explicit["sources"][0]["uri"] == URI
    c = Side("c", {2: "uri:rtsp://h/cam1", 5: URI}, fd, estimate(0, 1))
    assert [(p[0].source, p[1].source, p[2]) for p in pairs_of(a, c, uri="rtsp://h/cam1")] == [(1, 2, "uri:rtsp://h/cam1")]
    assert [(p[0].source, p[1].source) for p in pairs_of(a, c)] == [(0, 5), (1, 2)]


class _Keep:
    def start(self, header):
        self.header = header

    def write(self, events):
        self.events = events

    def close(self, dropped):
        pass


def test_the_clock_offset_aid_shifts_the_nodes_timestamps_but_not_the_cameras_capture_times():
    inner = _Keep()
    shifted = Shifted(inner, PretendClock(37_000_000))
    src = np.zeros(2, np.int32)
    events = np.concatenate([_events(np.array([T0, T0 + 1]), src, np.arange(2), 0, CAPTURE),
                             _events(np.array([T0 + 5, T0 + 6]), src, np.arange(2), 0, ORIGIN)])
    shifted.write(events)
    got = inner.events
    assert got["ts"][got["point"] == CAPTURE].tolist() == [T0, T0 + 1]
    assert got["ts"][got["point"] == ORIGIN].tolist() == [T0 + 5 + 37_000_000, T0 + 6 + 37_000_000]
    assert events["ts"][events["point"] == ORIGIN].tolist() == [T0 + 5, T0 + 6]  # the caller's array is untouched
