"""Frames as the API carries them: node timestamps corrected per timestamp, the capture time (the
camera's clock) left alone, glass-to-glass taken from the corrected end."""

from __future__ import annotations

import numpy as np

from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.relay.clock.correction import Correction, Segment
from dcuscope.relay.live import framepack
from dcuscope.relay.live.framejson import frame_dicts
from dcuscope.relay.live.run import LiveRun
from tests.probes.synth import T0
from tests.relay.api.test_moments import node_run

PERIOD = 100_000_000


def test_node_times_are_corrected_the_capture_is_not_and_glass_uses_the_corrected_end():
    captures = T0 + np.arange(5, dtype=np.int64) * PERIOD
    offset, drift_ppb = 37_000_000, 50_000  # a node 37 ms ahead, gaining 50 ppm
    _, fd = node_run("dcu", captures, delay_ns=20_000_000, offset_ns=offset)
    corr = Correction("estimate", "test", (Segment(T0, T0, offset, drift_ppb=drift_ppb, uncertainty_ns=5_000),))
    frames = frame_dicts(np.arange(1, 6), fd, corr)
    assert [f["capture"] for f in frames] == captures.tolist()
    for f, cap, origin, end in zip(frames, captures, fd.table.origin, fd.chains.end):
        off_origin = offset + round(drift_ppb * (origin - T0) / 1e9)
        off_end = offset + round(drift_ppb * (end - T0) / 1e9)
        assert f["origin"] == origin - off_origin and f["end"] == end - off_end
        assert f["clock_ns"] == off_origin and f["clock_uncertainty_ns"] == 5_000
        assert abs(f["glass_ms"] - (end - off_end - cap) / 1e6) < 1e-6
        assert abs(f["glass_ms"] - 50.0 + (off_end - offset) / 1e6) < 1e-6  # 30 ms to origin + 20 ms, true clock


def test_pushed_frames_packed_unpack_to_exactly_the_frames_of_the_api():
    """Pushes carry frames packed in binary columns (relay.live.framepack); unpacked they are the
    API's frames value for value: corrected times, missing ones (the sink has no exit) as null,
    NaN figures as null, whole numbers as ints, and a cut keeps the newest."""
    header = header_for("dcu", 2)
    live = LiveRun(header)
    live.add(synth_events(40, 2, 30.0, T0, drop_rate=0.1, seed=3))
    live.maintain()
    n, fd = live.recent(0, 500)
    assert len(n) > 20
    corr = Correction("estimate", "test", (Segment(T0, T0, 37_000_000, drift_ppb=50_000, uncertainty_ns=5_000),
                                           Segment(T0 + 600_000_000, T0, -1, uncertainty_ns=9_000)))
    ints, floats = framepack.columns(n, fd, corr)
    stages = len(header.stages)
    whole = framepack.unpack({"node": "dcu", "frames": [], "packed": framepack.packed(ints, floats, stages)})
    expected = frame_dicts(n, fd, corr)
    assert whole["frames"] == expected and "packed" not in whole
    assert any(f["exit"][-1] is None for f in expected) and any(f["capture"] is None for f in expected)
    assert any(v is None for f in expected for v in f["stage_delay_ms"])
    assert all(type(f["origin"]) is int and type(f["complete"]) is bool for f in whole["frames"])
    newest = framepack.unpack({"frames": [], "packed": framepack.packed(ints, floats, stages, last=7)})
    assert newest["frames"] == expected[-7:]
    assert framepack.unpack({"frames": [], "packed": framepack.packed(ints[:, :0], floats[:, :0], stages)})["frames"] == []
